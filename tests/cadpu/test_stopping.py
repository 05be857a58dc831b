"""cadpu.stopping: a signal asks a training run to stop after its step."""

from __future__ import annotations

import os
import signal

from cadpu.stopping import StopRequest


def test_a_signal_is_a_request_and_the_handlers_are_given_back() -> None:
    before = signal.getsignal(signal.SIGTERM)
    with StopRequest() as stop:
        assert not stop.requested
        os.kill(os.getpid(), signal.SIGTERM)
        assert stop.requested and (stop.signal_name, stop.exit_status) == ("SIGTERM", 143)
    assert signal.getsignal(signal.SIGTERM) is before


def test_an_ignored_signal_stays_ignored() -> None:
    # a background job (`cmd &` in a script) ignores SIGINT: its shell's Ctrl-C is not for it, and it
    # stopped the training with exit 130
    before = signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        with StopRequest() as stop:
            os.kill(os.getpid(), signal.SIGINT)
            assert not stop.requested
        assert signal.getsignal(signal.SIGINT) is signal.SIG_IGN
    finally:
        signal.signal(signal.SIGINT, before)
