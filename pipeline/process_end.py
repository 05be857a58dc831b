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
    ignore_stop_signals()
    threading._shutdown()  # type: ignore[attr-defined]  (what Py_FinalizeEx calls first)
    atexit._run_exitfuncs()
    flush_and_exit(status)


def ignore_stop_signals() -> None:
    """From here on SIGINT and SIGTERM are dropped (in the main thread; elsewhere nothing changes):
    the process has its exit status and is closing. A Ctrl-C pressed again meanwhile landed in
    Dask's exit handler that closes the cluster, and printed its traceback after the run's summary
    (an operator's trial); the cluster's workers still close with it."""
    if threading.current_thread() is threading.main_thread():
        for number in (signal.SIGINT, signal.SIGTERM):
            signal.signal(number, signal.SIG_IGN)


def exit_without_teardown() -> None:
    """Make this process, when it exits, end in its first exit handler (`atexit` runs the latest
    registered first) with `flush_and_exit(0)`, skipping the other exit handlers and the
    interpreter's teardown. For a worker process that is closing normally, whose exit status is 0
    then anyway."""
    atexit.register(flush_and_exit, 0)
