"""Tests of how the `kitti-pu` program ends its process (pipeline.process_end)."""

from __future__ import annotations

import signal
import subprocess
import sys
import textwrap
import time


def test_stop_signals_while_the_process_closes_are_dropped_without_a_traceback() -> None:
    # a Ctrl-C pressed again after the summary landed in Dask's exit handler that closes the
    # cluster and printed its traceback (an operator's trial)
    script = textwrap.dedent("""
        import atexit, sys, time
        from pipeline.process_end import end_process
        atexit.register(lambda: time.sleep(1.5))  # as Dask's close_clusters, while the workers close
        print("closing", flush=True)
        end_process(3)
    """)
    process = subprocess.Popen([sys.executable, "-c", script], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                               text=True)
    assert process.stdout.readline().strip() == "closing"
    time.sleep(0.3)
    for _ in range(4):
        process.send_signal(signal.SIGINT)
        time.sleep(0.1)
    process.send_signal(signal.SIGTERM)
    _, stderr = process.communicate(timeout=30)
    assert process.returncode == 3
    assert "KeyboardInterrupt" not in stderr and "Traceback" not in stderr, stderr
