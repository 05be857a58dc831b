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

from .summary import EXIT_INTERRUPTED  # a light module (about 30 ms): the heavy ones come after


def _stopped_while_starting(signum: int, frame: object) -> None:
    name = signal.Signals(signum).name
    sys.stderr.write(f"kitti-pu: stopped by {name} while starting; nothing was done\n")
    raise SystemExit(EXIT_INTERRUPTED[name])


def main() -> None:
    """Run the command line (`pipeline.cli.app`) with the start-up's signals handled."""
    previous = {number: signal.signal(number, _stopped_while_starting)
                for number in (signal.Signals[name] for name in EXIT_INTERRUPTED)}
    from .cli import app

    for number, handler in previous.items():
        signal.signal(number, handler)
    app()
