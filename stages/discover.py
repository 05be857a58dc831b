"""Finding the scans of the load stage (`stages.load`): KITTI raw drives, odometry sequences and
plain `.bin` folders, one `FrameRef` per scan.

Layouts (what `discover` accepts, `kind` "auto" tells them apart): see `stages.load`.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path

from .errors import InputError

DRIVE_PATTERN = re.compile(r"^(\d{4}_\d{2}_\d{2})_drive_(\d{4})_(\w+)$")


@dataclass(frozen=True)
class FrameRef:
    """Where one scan is and how to read its metadata (picklable, cheap).

    Attributes:
        dataset: "raw", "odometry" or "bin".
        sequence: drive folder name (raw), sequence id (odometry) or folder name (bin).
        index: frame index (the number in the file name when it has one, else its position).
        source: path of the .bin file.
        position: position of the file in its drive/sequence's sorted file list.
        base: raw/odometry base folder ("" for bin).
        date, drive: raw only, e.g. "2011_09_26" and "0001".
    """

    dataset: str
    sequence: str
    index: int
    source: str
    position: int
    base: str = ""
    date: str = ""
    drive: str = ""

    @property
    def key(self) -> str:
        """dataset/sequence/index, unique within a run."""
        return f"{self.dataset}/{self.sequence}/{self.index:06d}"


# --- discovery ----------------------------------------------------------------------------


def _index_of(path: Path, position: int) -> int:
    return int(path.stem) if path.stem.isdigit() else position


def _refs(files: list[Path], frames: range | None, **fields: str) -> list[FrameRef]:
    refs = []
    for position, file in enumerate(files):
        index = _index_of(file, position)
        if frames is None or index in frames:
            refs.append(FrameRef(index=index, source=str(file), position=position, **fields))  # type: ignore[arg-type]
    return refs


def _raw_drives(path: Path) -> list[Path]:
    """Drive folders at, or up to two levels under, `path`."""
    if DRIVE_PATTERN.match(path.name) and path.is_dir():
        return [path]
    found = [p for pattern in ("*", "*/*", "*/*/*") for p in sorted(path.glob(pattern))
             if p.is_dir() and DRIVE_PATTERN.match(p.name) and (p / "velodyne_points").is_dir()]
    return found


def _odometry_sequences(path: Path) -> list[Path]:
    """Sequence folders (…/sequences/NN with a velodyne/ folder) at or under `path`."""
    if path.parent.name == "sequences" and (path / "velodyne").is_dir():
        return [path]
    candidates = []
    for pattern in ("*", "sequences/*", "*/sequences/*"):
        candidates += [p for p in sorted(path.glob(pattern))
                       if p.parent.name == "sequences" and (p / "velodyne").is_dir()]
    return list(dict.fromkeys(candidates))


def _bin_folders(path: Path) -> list[Path]:
    if any(path.glob("*.bin")):
        return [path]
    return [p for p in sorted(path.iterdir()) if p.is_dir() and any(p.glob("*.bin"))]


@dataclass(frozen=True)
class _Group:
    """One drive, sequence or .bin folder found by `discover`: its names, scans and ref fields."""

    names: tuple[str, ...]
    files: list[Path]
    fields: dict[str, str]


def _groups(root: Path, kind: str) -> list[_Group]:
    """Every drive/sequence/.bin folder of `kind` at or under `root` ("auto": raw and odometry,
    else .bin folders)."""
    groups: list[_Group] = []
    if kind in ("auto", "raw"):
        for drive_dir in _raw_drives(root):
            date, drive, _ = DRIVE_PATTERN.match(drive_dir.name).groups()  # type: ignore[union-attr]
            files = sorted((drive_dir / "velodyne_points" / "data").glob("*.bin"))
            groups.append(_Group((drive_dir.name, f"{date}_drive_{drive}", drive), files,
                                 dict(dataset="raw", sequence=drive_dir.name,
                                      base=str(drive_dir.parent.parent), date=date, drive=drive)))
    if kind in ("auto", "odometry"):
        for sequence_dir in _odometry_sequences(root):
            files = sorted((sequence_dir / "velodyne").glob("*.bin"))
            groups.append(_Group((sequence_dir.name,), files,
                                 dict(dataset="odometry", sequence=sequence_dir.name,
                                      base=str(sequence_dir.parent.parent))))
    if kind == "bin" or (kind == "auto" and not groups):
        for folder in _bin_folders(root) if root.is_dir() else []:
            groups.append(_Group((folder.name,), sorted(folder.glob("*.bin")),
                                 dict(dataset="bin", sequence=folder.name)))
    return [g for g in groups if g.files]


def discover(path: str | Path, kind: str = "auto", sequences: list[str] | None = None,
             frames: range | None = None) -> list[FrameRef]:
    """Every scan under `path`, sorted by dataset, sequence and index.

    Args:
        path: see the module docstring.
        kind: "raw", "odometry", "bin" or "auto" (all raw drives and odometry sequences found,
            else a folder, or subfolders, of .bin files).
        sequences: drive names (full folder name, "DATE_drive_XXXX" or "XXXX"), sequence ids or
            bin folder names to keep; None keeps all.
        frames: frame indices to keep; None keeps all.

    Returns:
        One `FrameRef` per scan (an empty list when `frames` selects none).

    Raises:
        InputError: `path` is missing, holds nothing of the requested kind, or holds none of
            the requested `sequences` (the message lists those it holds).
    """
    root = Path(path)
    if not root.exists():
        raise InputError("load", str(root), "does not exist")
    if kind not in ("auto", "raw", "odometry", "bin"):
        raise InputError("load", str(root), f"unknown input kind {kind!r}")
    groups = _groups(root, kind)
    if not groups:
        expected = {"auto": "KITTI raw drives, odometry sequences or .bin scans",
                    "raw": "KITTI raw drives (DATE/DATE_drive_XXXX_sync/velodyne_points/data/*.bin)",
                    "odometry": "KITTI odometry sequences (sequences/NN/velodyne/*.bin)",
                    "bin": ".bin scans"}[kind]
        raise InputError("load", str(root), f"no {expected} found")
    chosen = [g for g in groups if sequences is None or any(name in sequences for name in g.names)]
    if not chosen:
        available = ", ".join(g.names[0] for g in groups)
        raise InputError("load", str(root), f"sequences {sequences} not found; found: {available}")
    refs: list[FrameRef] = []
    for group in chosen:
        refs += _refs(group.files, frames, **group.fields)
    return refs
