"""Ending a process without the interpreter's teardown (module clean-up, library destructors),
which torch makes last a noticeable part of a second: for the `kitti-pu` program
(`end_process`) and the tool's own LocalCluster workers (`exit_without_teardown`)."""

from __future__ import annotations

import atexit
import contextlib
import logging
import os
import signal
import sys
import threading
import time
from typing import Any


def flush_and_exit(status: int) -> None:
    """Flush logging's handlers, stdout and stderr, then end the process at once with `status`."""
    with contextlib.suppress(Exception):
        logging.shutdown()
    for stream in (sys.stdout, sys.stderr):
        with contextlib.suppress(Exception):
            stream.flush()
    os._exit(status)


def end_process(code: Any) -> None:
    """End this process as `sys.exit(code)` would (`code`: None or an int status, or a message
    printed to stderr with status 1), after what the interpreter does first at exit (wait for
    non-daemon threads, run the exit handlers) and flushing, but without its teardown."""
    if code is None:
        status = 0
    elif isinstance(code, int):
        status = code
    else:
        print(code, file=sys.stderr)
        status = 1
    drop_stop_signals(status)
    threading._shutdown()  # type: ignore[attr-defined]  (what Py_FinalizeEx calls first)
    atexit._run_exitfuncs()
    flush_and_exit(status)


#: Seconds of a closing process during which SIGINT and SIGTERM are dropped (`drop_stop_signals`).
CLOSING_GRACE_S = 10.0


def drop_stop_signals(status: int) -> None:
    """From here on SIGINT and SIGTERM are dropped for `CLOSING_GRACE_S` seconds (in the main
    thread; elsewhere nothing changes), and after that end the process at once with `status`: the
    process has its exit status and is closing. A Ctrl-C pressed again meanwhile landed in Dask's
    exit handler that closes the cluster and printed its traceback after the run's summary (an
    operator's trial); one pressed when closing hangs still ends it."""
    if threading.current_thread() is not threading.main_thread():
        return
    closing_since = time.monotonic()

    def on_signal(number: int, frame: object) -> None:
        if time.monotonic() - closing_since > CLOSING_GRACE_S:
            flush_and_exit(status)

    for number in (signal.SIGINT, signal.SIGTERM):
        signal.signal(number, on_signal)


def exit_without_teardown() -> None:
    """Make this process, when it exits, end in its first exit handler (`atexit` runs the latest
    registered first) with `flush_and_exit(0)`, skipping the other exit handlers and the
    interpreter's teardown. For a worker process that is closing normally, whose exit status is 0
    then anyway."""
    atexit.register(flush_and_exit, 0)
