"""The `kitti-pu` program's entry point (`kitti-pu` and `python -m pipeline`).

The command line's modules take about a second to import. A SIGINT or SIGTERM that arrives
meanwhile ends the program with one line and the signal's exit status (130, 143), where it printed
a traceback from inside an import or ended without a word; nothing has been done by then. Once the
modules are loaded the default handlers are back, and each verb handles the signals itself
(`kitti-pu run`: `pipeline.cli`).
"""

from __future__ import annotations

import signal
import sys

#: Exit status per signal, as the README's table has them (`pipeline.summary.EXIT_INTERRUPTED`).
_EXIT = {signal.SIGINT: 130, signal.SIGTERM: 143}


def _stopped_while_starting(signum: int, frame: object) -> None:
    sys.stderr.write(f"kitti-pu: stopped by {signal.Signals(signum).name} while starting; nothing was done\n")
    raise SystemExit(_EXIT[signal.Signals(signum)])


def main() -> None:
    """Run the command line (`pipeline.cli.app`) with the start-up's signals handled."""
    previous = {number: signal.signal(number, _stopped_while_starting) for number in _EXIT}
    from .cli import app

    for number, handler in previous.items():
        signal.signal(number, handler)
    app()
