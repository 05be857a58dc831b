"""Temporary files of an output folder: named so that no reader takes them, swept once their
writer is gone.

Every output file is written under a temporary name and renamed into place. What readers of a
Hive folder pick up (pyarrow 26, pandas 3.1 and dask 2026.8, checked by
tests/stages/test_write_faults.py): pyarrow.dataset and pandas read every file except names
starting with "." or "_"; dask.dataframe reads every file whose name ends in ".parquet", hidden
or not. A temporary therefore lives outside the Hive folder (`OUT/.tmp/`, or beside a file that is
not data, such as summary.json), starts with "." and ends in ".part".

Its name also says who writes it: `.PID@HOST~NONCE~FINAL_NAME.part`. A sweep removes a temporary
whose writer ran on this host and is no longer alive, or which has not been written to for
`TEMPORARY_MAX_AGE_S` (a writer on another host, or a reused process id); a live writer's
temporary is left alone, so a run may sweep while another run writes into the same folder.
Temporaries of earlier versions (`.NAME.tmp-XXXXXXXX.SUFFIX` beside the file, and the like) are
removed whatever their age: no current writer makes them.
"""

from __future__ import annotations

import errno
import hashlib
import os
import re
import socket
import time
import uuid
from collections.abc import Callable
from pathlib import Path

#: The folder, under an output folder, of the data files' temporaries (outside `points/`).
TEMPORARY_DIR = ".tmp"
#: A temporary untouched for this long (seconds) is stale whoever wrote it: writing one frame's
#: file takes seconds, and a writer keeps its file's modification time fresh while it writes.
TEMPORARY_MAX_AGE_S = 3600.0
#: The longest file name, in bytes, of the usual file systems (ext4, XFS, APFS, NTFS's 255 units).
NAME_MAX_BYTES = 255

_CURRENT = re.compile(r"^\.(?P<pid>\d+)@(?P<host>[^~/]+)~[0-9a-f]{8}~.+\.part$")
#: Names earlier versions used: stages.write (.000000.tmp-0123abcd.parquet), summary.json
#: (.summary.json.XXXXXXXX.tmp), previews (.000000.png.tmp.png).
_LEGACY = re.compile(r"^\.(.+\.tmp-[0-9a-f]{8}(\.\w+)?|.+\.json\.\w{8}\.tmp|.+\.tmp\.png)$")


def file_in_the_way(folder: Path) -> Path | None:
    """The first of `folder` and its parents that exists and is not a folder (a file where the
    folder, or one it goes in, must be), or None: why nothing can be written in `folder`."""
    return next((part for part in (folder, *folder.parents) if part.exists() and not part.is_dir()), None)


def temporary_name(final_name: str) -> str:
    """A temporary file name for a file to be renamed to `final_name`, owned by this process: the
    final name in it as it is when the whole fits the file systems' NAME_MAX_BYTES, else a hash of
    it and its suffix (the KITTI mirror keeps its scans' names, which may be long)."""
    prefix = f".{os.getpid()}@{socket.gethostname()}~{uuid.uuid4().hex[:8]}~"
    if len(f"{prefix}{final_name}.part".encode("utf-8", "surrogateescape")) > NAME_MAX_BYTES:
        digest = hashlib.sha256(final_name.encode("utf-8", "surrogateescape")).hexdigest()[:16]
        final_name = f"{digest}{Path(final_name).suffix[:16]}"
    return f"{prefix}{final_name}.part"


def replace_atomically(path: Path, write: Callable[[Path], None], folder: Path | None = None) -> None:
    """Run `write(temporary)`, then rename the temporary onto `path`; never leave it behind
    (short of the process being killed: `sweep` removes those).

    Args:
        path: the final file.
        write: writes the whole file at the path it is given.
        folder: where the temporary goes (on `path`'s file system); `path`'s folder when None.
    """
    path.parent.mkdir(parents=True, exist_ok=True)
    folder = path.parent if folder is None else folder
    folder.mkdir(parents=True, exist_ok=True)
    temporary = folder / temporary_name(path.name)
    try:
        write(temporary)
        _sync(temporary)  # its data on disk before its name: a power loss leaves no part of a file in place
        os.replace(temporary, path)
        _sync(path.parent)  # and the rename itself
    finally:
        temporary.unlink(missing_ok=True)


def _sync(path: Path) -> None:
    """fsync a file or folder `path` (what the writers wrote through their own handles); where a
    platform cannot open a folder for it (Windows), nothing."""
    try:
        descriptor = os.open(path, os.O_RDONLY)
    except (IsADirectoryError, PermissionError):
        return
    try:
        os.fsync(descriptor)
    except OSError as error:
        if error.errno not in (errno.EINVAL, errno.EBADF):  # a file system without fsync of folders
            raise
    finally:
        os.close(descriptor)


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except OSError:  # e.g. another user's process: it exists
        return True
    return True


def is_stale(path: Path, now: float | None = None, max_age_s: float = TEMPORARY_MAX_AGE_S) -> bool:
    """True when `path` is a temporary (by its name) that no running writer will rename.

    Current names: the writer ran on this host and is gone, or the file is older than
    `max_age_s`. Names of earlier versions: always. Any other name: never.
    """
    name = path.name
    if _LEGACY.match(name) and not _CURRENT.match(name):
        return True
    match = _CURRENT.match(name)
    if not match:
        return False
    if match["host"] == socket.gethostname() and not _alive(int(match["pid"])):
        return True
    try:
        age = (time.time() if now is None else now) - path.stat().st_mtime
    except OSError:  # renamed or removed meanwhile: nothing to sweep
        return False
    return age > max_age_s


def sweep(root: Path, max_age_s: float = TEMPORARY_MAX_AGE_S) -> list[Path]:
    """Remove every stale temporary (`is_stale`) anywhere under `root`; return those removed.

    Safe while other processes write under `root`: a live writer's temporary is kept, and one
    that disappears meanwhile is skipped.
    """
    removed = []
    now = time.time()
    for folder, _, files in os.walk(root):
        for name in files:
            if not name.startswith("."):
                continue
            path = Path(folder, name)
            if is_stale(path, now, max_age_s):
                try:
                    path.unlink()
                except FileNotFoundError:
                    continue
                removed.append(path)
    return removed
