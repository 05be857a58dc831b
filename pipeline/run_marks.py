"""The mark a run keeps in `OUT/runs/` while it writes frames.

A run settles its frames against the disk at its end (`pipeline.runner`): among other things it
removes a replaced frame's files in the formats it did not write. A run killed before that (kill -9,
a crash, a lost machine) left those files beside the new ones, and nothing said it had run: the
next run skipped the frames and kept them. The mark (`<UTC time>-<run id>.unfinished`, JSON:
run_id, started, pid, config_hash) is written before the frames and removed once they are
settled, so a mark found by a run that holds the folder's lock is a run that never finished: that
run then checks every finished frame's other formats, and `kitti-pu info` says so.
"""

from __future__ import annotations

import json
import os
import time
from collections.abc import Iterable
from pathlib import Path
from typing import Any

#: The folder of the output that holds the runs' records and marks.
RUNS_DIR = "runs"
#: The suffix of a run's mark (not `.json`: readers of the records glob those).
MARK_SUFFIX = ".unfinished"


def leave_mark(out_dir: Path, run_id: str, config_hash: str) -> Path | None:
    """Write the mark of a run that starts writing frames now; its path, or None when it cannot
    be written (a full disk: the run goes on, unmarked, as runs did before marks)."""
    started = time.gmtime()
    mark = Path(out_dir) / RUNS_DIR / f"{time.strftime('%Y%m%dT%H%M%SZ', started)}-{run_id[:6]}{MARK_SUFFIX}"
    text = json.dumps({"run_id": run_id, "started": time.strftime("%Y-%m-%dT%H:%M:%SZ", started),
                       "pid": os.getpid(), "config_hash": config_hash})
    try:
        mark.parent.mkdir(parents=True, exist_ok=True)
        mark.write_text(text)
    except OSError:
        return None
    return mark


def unfinished_runs(out_dir: Path) -> list[dict[str, Any]]:
    """The marks in `out_dir` (oldest first), each {"mark": its path, "started", "pid",
    "config_hash", "run_id"}; a mark that does not read (cut short by the kill) gives its path and
    None for the rest. While no run holds the folder's lock, each is a run that never finished."""
    marks = []
    for mark in sorted((Path(out_dir) / RUNS_DIR).glob(f"*{MARK_SUFFIX}")):
        try:
            held = json.loads(mark.read_text())
            held = held if isinstance(held, dict) else {}
        except (OSError, ValueError):
            held = {}
        marks.append({"mark": str(mark), **{key: held.get(key) for key in ("started", "pid", "config_hash", "run_id")}})
    return marks


def clear_marks(marks: Iterable[Path | str]) -> None:
    """Remove marks: the run's own once its frames are settled, and those of earlier runs whose
    leftovers it has checked. One that cannot be removed stays, and is checked again next time."""
    for mark in marks:
        try:
            Path(mark).unlink(missing_ok=True)
        except OSError:
            pass


def describe_runs(marks: list[dict[str, Any]]) -> str:
    """One phrase naming the runs of `marks` ("a run started 2026-11-27T03:00:00Z (pid 123)")."""
    named = [f"started {mark['started']} (pid {mark['pid']})" if mark.get("started") else f"marked {Path(mark['mark']).name}"
             for mark in marks]
    return ("a run " if len(named) == 1 else f"{len(named)} runs, ") + "; ".join(named)
