"""The lock a run holds on its output folder, and whether another run holds it now.

Kept apart from `pipeline.runner` (which imports Dask) so that `kitti-pu info` can tell that a
run is writing without loading it.
"""

from __future__ import annotations

import os
from pathlib import Path

from filelock import FileLock, Timeout

#: The lock file a run holds in its output folder (`pipeline.runner.OutputBusy` for a second run).
LOCK_NAME = ".kitti-pu.lock"


def output_busy(out_dir: Path) -> bool:
    """Whether another run holds `out_dir`'s lock now; False when the folder has no lock file or
    it cannot be read (another user's folder: nothing to say). Nothing is created.

    On POSIX the lock is probed with a shared, non-blocking flock on a read-only descriptor: a run
    holds it exclusively (filelock's flock), so the probe fails exactly while one does, and it needs
    no write permission (taking the lock did, and raised PermissionError on a folder of another
    user's: a review)."""
    lock_path = Path(out_dir) / LOCK_NAME
    if not lock_path.is_file():
        return False
    try:
        import fcntl
    except ImportError:  # not POSIX: filelock's own lock, taken for a moment
        try:
            with FileLock(lock_path, timeout=0):
                return False
        except Timeout:
            return True
        except OSError:
            return False
    try:
        descriptor = os.open(lock_path, os.O_RDONLY)
    except OSError:
        return False
    try:
        fcntl.flock(descriptor, fcntl.LOCK_SH | fcntl.LOCK_NB)
    except BlockingIOError:
        return True
    except OSError:
        return False
    finally:
        os.close(descriptor)  # releases the shared lock too
    return False
