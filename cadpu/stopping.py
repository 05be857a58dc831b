"""Stopping a training run at a step boundary when the user asks (Ctrl-C, SIGTERM), as `--max-seconds`
stops it: with a checkpoint and the weights written, so `--resume` continues where it stopped.

A signal in the middle of a step used to end the run at once: a KeyboardInterrupt traceback, the
steps since the last checkpoint lost, and, under `kitti-pu finetune`, now and then a segmentation
fault at exit while a thread of the step (the EMD's assignment) was still running.
"""

from __future__ import annotations

import signal
import threading
from pathlib import Path
from types import FrameType, TracebackType

#: The signals a run stops for, with their exit statuses (128 + the signal's number).
STOP_SIGNALS = {signal.SIGINT: 130, signal.SIGTERM: 143}


class TrainingStopped(Exception):
    """A run stopped by a signal after writing its checkpoint and weights.

    Attributes:
        weights: the weights file written. step: the step it stopped after. signal_name: "SIGINT"
        or "SIGTERM". exit_status: 130 or 143.
    """

    def __init__(self, weights: Path, step: int, signal_name: str, exit_status: int) -> None:
        super().__init__(f"stopped by {signal_name} after step {step}; weights written to {weights}; "
                         "continue with --resume")
        self.weights, self.step, self.signal_name, self.exit_status = weights, step, signal_name, exit_status


class StopRequest:
    """While entered (in the main thread), SIGINT and SIGTERM set `signal_name` instead of ending
    the process; a second one ends it as before (KeyboardInterrupt, or the default SIGTERM). A
    signal the process ignores stays ignored. In another thread, where signals cannot be caught,
    it never requests a stop."""

    def __init__(self) -> None:
        self.signal_name: str | None = None
        self.exit_status = 0
        self._previous: dict[int, object] = {}

    @property
    def requested(self) -> bool:
        return self.signal_name is not None

    def _handle(self, number: int, frame: FrameType | None) -> None:
        if self.requested:  # asked twice: stop now
            self._restore()
            signal.raise_signal(number)
            return
        self.signal_name = signal.Signals(number).name
        self.exit_status = STOP_SIGNALS[signal.Signals(number)]

    def _restore(self) -> None:
        for number, handler in self._previous.items():
            signal.signal(number, handler)  # type: ignore[arg-type]
        self._previous = {}

    def __enter__(self) -> "StopRequest":
        if threading.current_thread() is threading.main_thread():
            for number in STOP_SIGNALS:
                current = signal.getsignal(number)
                # an ignored signal stays ignored (a background job's SIGINT: its shell's Ctrl-C is
                # not for it), and a handler set outside Python could not be put back
                if current is signal.SIG_IGN or current is None:
                    continue
                self._previous[number] = signal.signal(number, self._handle)
        return self

    def __exit__(self, kind: type[BaseException] | None, error: BaseException | None,
                 trace: TracebackType | None) -> None:
        self._restore()
