"""Tests of how the `kitti-pu` program ends its process (pipeline.process_end)."""

from __future__ import annotations

import signal
import subprocess
import sys
import textwrap
import time


def _closing_process(handler_seconds: float, grace_s: float) -> subprocess.Popen:
    """A process ending through `end_process(3)` whose exit handler (as Dask's close_clusters,
    while the workers close) takes `handler_seconds`, with `grace_s` of dropped signals; returned
    once its exit handlers run (it prints "closing" from the first of them, after `end_process`
    has set its signal handling), so that no signal lands before."""
    script = textwrap.dedent(f"""
        import atexit, time
        import pipeline.process_end as process_end
        process_end.CLOSING_GRACE_S = {grace_s}
        atexit.register(lambda: time.sleep({handler_seconds}))
        atexit.register(lambda: print("closing", flush=True))  # runs first: the latest registered
        process_end.end_process(3)
    """)
    process = subprocess.Popen([sys.executable, "-c", script], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                               text=True)
    assert process.stdout.readline().strip() == "closing"
    return process


def test_stop_signals_while_the_process_closes_are_dropped_without_a_traceback() -> None:
    # a Ctrl-C pressed again after the summary landed in Dask's exit handler that closes the
    # cluster and printed its traceback (an operator's trial)
    process = _closing_process(handler_seconds=3.0, grace_s=60.0)
    for _ in range(4):
        process.send_signal(signal.SIGINT)
        time.sleep(0.1)
    process.send_signal(signal.SIGTERM)
    _, stderr = process.communicate(timeout=60)
    assert process.returncode == 3
    assert "KeyboardInterrupt" not in stderr and "Traceback" not in stderr, stderr


def test_a_stop_signal_past_the_grace_ends_a_closing_that_hangs() -> None:
    # dropped for good, a hung exit handler left only kill -9 (a review)
    process = _closing_process(handler_seconds=120.0, grace_s=0.2)
    started = time.monotonic()
    time.sleep(0.5)  # past the grace
    process.send_signal(signal.SIGINT)
    _, stderr = process.communicate(timeout=60)
    assert process.returncode == 3 and time.monotonic() - started < 30
    assert "Traceback" not in stderr, stderr
