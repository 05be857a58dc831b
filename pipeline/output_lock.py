"""The lock a run holds on its output folder, and whether another run holds it now.

Kept apart from `pipeline.runner` (which imports Dask) so that `kitti-pu info` can tell that a
run is writing without loading it.
"""

from __future__ import annotations

from pathlib import Path

from filelock import FileLock, Timeout

#: The lock file a run holds in its output folder (`pipeline.runner.OutputBusy` for a second run).
LOCK_NAME = ".kitti-pu.lock"


def output_busy(out_dir: Path) -> bool:
    """Whether another run holds `out_dir`'s lock now (nothing is created: a folder without the
    lock file is free)."""
    lock_path = Path(out_dir) / LOCK_NAME
    if not lock_path.is_file():
        return False
    try:
        with FileLock(lock_path, timeout=0):
            return False
    except Timeout:
        return True
