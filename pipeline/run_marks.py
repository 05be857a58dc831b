"""The mark a run keeps in `OUT/runs/` while it writes frames.

A run settles its frames against the disk at its end (`pipeline.runner`): among other things it
removes a replaced frame's files in the formats it did not write. A run killed before that (kill -9,
a crash, a lost machine) left those files beside the new ones, and nothing said it had run: the
next run skipped the frames and kept them. The mark (`<UTC time>-<run id>.unfinished`, JSON:
run_id, started, pid, config_hash and the keys of the frames the run set out to write) is
written before the frames and removed once they are settled, so a mark found by a run that holds
the folder's lock is a run that never finished: that run then checks those of its frames it
selects, and keeps the mark, holding the frames it did not settle, for a later run (a run of one
sequence checks that sequence only); `kitti-pu info` says so.
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


def leave_mark(out_dir: Path, run_id: str, config_hash: str, frames: Iterable[str]) -> Path | None:
    """Write the mark of a run that starts writing `frames` (their keys) now; its path, or None
    when it cannot be written (a full disk: the run goes on, unmarked, as runs did before marks)."""
    started = time.gmtime()
    mark = Path(out_dir) / RUNS_DIR / f"{time.strftime('%Y%m%dT%H%M%SZ', started)}-{run_id[:6]}{MARK_SUFFIX}"
    held = {"run_id": run_id, "started": time.strftime("%Y-%m-%dT%H:%M:%SZ", started), "pid": os.getpid(),
            "config_hash": config_hash, "frames": sorted(frames)}
    try:
        mark.parent.mkdir(parents=True, exist_ok=True)
        mark.write_text(json.dumps(held))
    except OSError:
        # a full disk creates the file and fails its write: the empty mark, left, read as a run
        # killed before it settled (an operator's trial)
        clear_marks([mark])
        return None
    return mark


def unfinished_runs(out_dir: Path) -> list[dict[str, Any]]:
    """The marks in `out_dir` (oldest first), each {"mark": its path, "started", "pid",
    "config_hash", "run_id", "frames"}; a mark that does not read (cut short by the kill) gives its
    path and None for the rest (its frames None: any frame may be one of them). While no run holds
    the folder's lock, each is a run that never finished."""
    marks = []
    for mark in sorted((Path(out_dir) / RUNS_DIR).glob(f"*{MARK_SUFFIX}")):
        try:
            held = json.loads(mark.read_text())
            held = held if isinstance(held, dict) else {}
        except (OSError, ValueError):
            held = {}
        frames = held.get("frames")
        marks.append({"mark": str(mark), **{key: held.get(key) for key in ("started", "pid", "config_hash", "run_id")},
                      "frames": frames if isinstance(frames, list) else None})
    return marks


def frames_to_check(marks: list[dict[str, Any]]) -> set[str] | None:
    """The keys of the frames `marks`' runs set out to write (None: every frame, as a mark that does
    not read may hold any)."""
    if any(mark["frames"] is None for mark in marks):
        return None
    return {key for mark in marks for key in mark["frames"]}


def settle_marks(marks: list[dict[str, Any]], settled: set[str]) -> None:
    """After a run checked the frames of `settled` (keys): remove each of `marks` none of whose
    frames is left, and write the others again holding only the frames still to check (a mark
    that does not read is removed: the run checked every frame it selected)."""
    for mark in marks:
        left = sorted(set(mark["frames"] or ()) - settled)
        path = Path(mark["mark"])
        try:
            if not left:
                path.unlink(missing_ok=True)
            else:
                held = json.loads(path.read_text())
                path.write_text(json.dumps({**held, "frames": left}))
        except (OSError, ValueError):
            pass  # it stays as it was: checked again next time


def clear_marks(marks: Iterable[Path | str]) -> None:
    """Remove marks: a run's own once its frames are settled, or when it wrote no frame."""
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
