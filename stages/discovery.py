"""Finding the scans: KITTI raw drives, odometry sequences and plain `.bin` folders, each scan
named by a frame identity that is unique and stable, and fingerprinted.

Layouts (what `discover` accepts, `kind` "auto" tells them apart):
- raw: BASE/DATE/DATE_drive_XXXX_sync/velodyne_points/data/NNNNNNNNNN.bin;
- odometry: BASE/sequences/NN/velodyne/NNNNNN.bin;
- bin: a folder of `.bin` scans (KITTI Velodyne format: float32 x, y, z, reflectance per point);
  the folder's own scans and those of each of its direct sub-folders are one sequence per folder
  (deeper folders are not read).
`path` may be the base folder, a date folder, a drive folder, a `sequences` folder, a sequence
folder, or a folder of `.bin` files; under a base folder every drive and sequence is found, and
every folder of `.bin` scans at the base or directly in it.

Identity (`FrameRef.key`, which names the output files): dataset/sequence/index.
- index: the last group of digits in the file name (`000042.bin` and `scan_0042.bin` are frame
  42). A name without digits is refused: a position in the folder would change when a file is
  added, and a stored frame would then be taken for another.
- sequence: the drive folder (raw) or the sequence id (odometry); for a `.bin` folder its name
  plus a hash of its resolved path (`velodyne-1f2e3d4c`), so that two folders of the same name
  are two sequences.
Two scans with the same identity in one discovery are an error naming both files.
"""

from __future__ import annotations

import hashlib
import json
import os
import re
import sys
from dataclasses import dataclass
from pathlib import Path

from .errors import InputError

DRIVE_PATTERN = re.compile(r"^(\d{4}_\d{2}_\d{2})_drive_(\d{4})_(\w+)$")
#: The `frame` column is int32: a frame number must fit.
MAX_INDEX = 2**31 - 1
#: The end of a frame range without a last frame: past any frame number (Unix times name scans).
OPEN_END = sys.maxsize
_DIGITS = re.compile(r"\d+")


@dataclass(frozen=True)
class FrameRef:
    """Where one scan is and how to read its metadata (picklable, cheap).

    Attributes:
        dataset: "raw", "odometry" or "bin".
        sequence: drive folder name (raw), sequence id (odometry) or folder name plus path hash (bin).
        index: frame index, the last number in the file name.
        source: path of the .bin file.
        base: raw/odometry base folder ("" for bin).
        date, drive: raw only, e.g. "2011_09_26" and "0001".
        fingerprint: `source_fingerprint(source)` when discovered ("" when the file could not be
            read then: loading it reports why).
    """

    dataset: str
    sequence: str
    index: int
    source: str
    base: str = ""
    date: str = ""
    drive: str = ""
    fingerprint: str = ""

    @property
    def key(self) -> str:
        """dataset/sequence/index, unique within a run."""
        return f"{self.dataset}/{self.sequence}/{self.index:06d}"


def source_fingerprint(path: str | Path) -> str:
    """What identifies a scan file's contents without reading it: its resolved path, size in
    bytes and modification time in nanoseconds, as compact JSON ("" when the file cannot be
    stat'ed). A copy, an edit or a replacement of the file changes it."""
    try:
        real = os.path.realpath(path)
        stat = os.stat(real)
    except OSError:
        return ""
    return fingerprint_of(real, stat)


def content_digest(path: str | Path) -> str:
    """The first 16 hex digits of the sha256 of a file's bytes: the same for every copy of a scan,
    wherever it lies ("" when the file cannot be read). Reads the whole file (about 2 ms for a
    KITTI scan)."""
    digest = hashlib.sha256()
    try:
        with open(path, "rb") as stream:  # hashlib.file_digest is Python 3.11's; the project takes 3.10
            while chunk := stream.read(1 << 20):
                digest.update(chunk)
    except OSError:
        return ""
    return digest.hexdigest()[:DIGEST_HEX]


def scans_among(sources: list[str], paths: list[str] | set[str], digests: list[str] | set[str],
                digest_of: dict[str, str] | None = None) -> dict[str, str]:
    """The scans of `sources` that a list names: {source: "path"} for one it names by path (both
    resolved), {source: "copy"} for one whose `content_digest` it holds, in the order of `sources`.

    `digest_of` (source -> digest) is filled as scans are hashed, so that a caller asking twice of
    the same scans reads each once; a scan is hashed only when `digests` is not empty."""
    named = {str(Path(path).resolve()) for path in paths}
    held = set(digests)
    digest_of = {} if digest_of is None else digest_of
    found: dict[str, str] = {}
    for source in sources:
        if str(Path(source).resolve()) in named:
            found[source] = "path"
        elif held:
            if source not in digest_of:
                digest_of[source] = content_digest(source)
            if digest_of[source] in held:
                found[source] = "copy"
    return found


#: Hex digits of the sha256 that `content_digest` and `bytes_digest` keep.
DIGEST_HEX = 16


def bytes_digest(data: bytes | memoryview) -> str:
    """`content_digest` of bytes already read (a scan's, as the load stage read them)."""
    return hashlib.sha256(data).hexdigest()[:DIGEST_HEX]


def fingerprint_of(real_path: str, stat: os.stat_result) -> str:
    """`source_fingerprint`'s JSON for a file at `real_path` (resolved) with status `stat`."""
    return json.dumps({"path": real_path, "size": stat.st_size, "mtime_ns": stat.st_mtime_ns},
                      sort_keys=True, separators=(",", ":"))


def frame_index(path: Path) -> int:
    """The frame number of a scan file: the last group of digits in its name (without suffix).

    Raises:
        InputError naming the file when the name holds no number or one too large for int32, or is
        not UTF-8 (the outputs record the source path as text: the write failed after the network).
    """
    try:
        str(path).encode("utf-8")
    except UnicodeEncodeError:
        shown = str(path).encode("utf-8", "surrogateescape").decode("utf-8", "replace")
        raise InputError("load", shown, "the path is not UTF-8 text, which the outputs record it as: rename "
                                        "the file or folder") from None
    index = frame_number(path.name)
    if index is None:
        raise InputError("load", str(path), "no frame number in the file name: name scans by "
                                            "their frame number (e.g. 000042.bin)")
    if index > MAX_INDEX:
        raise InputError("load", str(path), f"frame number {index} is larger than {MAX_INDEX}")
    return index


def frame_number(name: str) -> int | None:
    """The frame number a scan file name holds: the last group of digits of its stem (None when it
    holds none). What `frame_index` checks, and the KITTI mirror names copies by."""
    numbers = _DIGITS.findall(Path(name).stem)
    return int(numbers[-1]) if numbers else None


def layout_name_problem(name: str) -> str | None:
    """Why `name` cannot name a folder of the outputs' Parquet dataset (OUT/points/DATASET/SEQUENCE),
    or None: its readers (pyarrow, pandas, Dask, DuckDB) skip folders whose names start with "." or
    "_", and read a "key=value" folder as a partition column."""
    if name.startswith((".", "_")):
        return "starts with '.' or '_', and readers of the Parquet dataset skip such folders"
    if "=" in name:
        return "holds '=', and readers of the Parquet dataset read such a folder as a partition column"
    return None


def bin_sequence_name(folder: Path) -> str:
    """The sequence name of a folder of .bin scans: its name plus 8 hex digits of the SHA-256 of
    its resolved path, e.g. "velodyne-1f2e3d4c"; an "=" of the name becomes "-", and leading "."
    and "_" are left out (`layout_name_problem`; "scans" when nothing is left)."""
    digest = hashlib.sha256(os.path.realpath(folder).encode("utf-8", "surrogateescape")).hexdigest()
    name = folder.name.replace("=", "-").lstrip("._") or "scans"
    return f"{name}-{digest[:8]}"


#: The files beside `velodyne/` that make a folder an odometry sequence's (`odometry_folders_read_as_bin`).
ODOMETRY_SEQUENCE_FILES = ("calib.txt", "times.txt")


def odometry_folders_read_as_bin(refs: list[FrameRef]) -> list[str]:
    """One line per `.bin` folder among `refs` that is the `velodyne/` of what looks like a KITTI
    odometry sequence (`ODOMETRY_SEQUENCE_FILES` beside it), outside a `sequences` folder or
    inside one and read as `.bin` scans by `--kind bin`: its scans are read as plain `.bin` scans,
    and its timestamps, calibration, poses and labels are not (a sequence folder copied elsewhere
    was read so without a word: a trial)."""
    lines = []
    for folder in sorted({Path(ref.source).parent for ref in refs if ref.dataset == "bin"}):
        beside = [name for name in ODOMETRY_SEQUENCE_FILES if (folder.parent / name).is_file()]
        if folder.name == "velodyne" and beside and folder.parent.parent.name == "sequences":
            # in place: only --kind bin reads it so (the trial's warning said it was misplaced)
            # given as velodyne/ itself, or with --kind bin ("leave out --kind bin" puzzled a user who
            # had given the velodyne/ folder without it: a new user's trial)
            lines.append(f"{folder} holds the scans of KITTI odometry sequence {folder.parent.name}, read as a plain "
                         "folder of .bin scans, without timestamps, calibration, poses or labels, and written "
                         f"as another sequence than odometry {folder.parent.name}; give {folder.parent} (without "
                         "--kind bin) to read it as the sequence")
        elif folder.name == "velodyne" and beside:
            sequence = folder.parent
            lines.append(f"{sequence} holds {' and '.join(beside)} beside velodyne/, as a KITTI odometry sequence "
                         f"does, but is not in a folder named 'sequences': its scans are read as a plain folder "
                         f"of .bin scans, without timestamps, calibration, poses or labels. To read it as "
                         f"odometry sequence {sequence.name}, put it (or a symbolic link to it) at "
                         f"BASE/sequences/{sequence.name} and give BASE")
    return lines


def _scans(folder: Path) -> list[Path]:
    """The `.bin` entries of `folder` (the suffix in any case) that are not directories (a folder
    named `x.bin` is not a scan; a broken link is kept, so that loading it reports it) nor hidden
    (a name starting with ".", such as the `._000000.bin` files macOS leaves on shared drives),
    sorted."""
    if not folder.is_dir():
        return []
    return sorted(p for p in folder.iterdir()
                  if p.suffix.lower() == ".bin" and not p.name.startswith(".") and not p.is_dir())


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
    """The folders of .bin scans a plain folder holds: itself and its direct sub-folders, each that
    holds scans (each is a sequence of its own; deeper folders are not read)."""
    return [p for p in [path, *sorted(p for p in path.iterdir() if p.is_dir())] if _scans(p)]


@dataclass(frozen=True)
class _Group:
    """One drive, sequence or .bin folder found by `discover`: its names, scans and ref fields."""

    names: tuple[str, ...]
    files: list[Path]
    fields: dict[str, str]


def _groups(root: Path, kind: str) -> list[_Group]:
    """Every drive/sequence/.bin folder of `kind` at or under `root` ("auto": raw drives, odometry
    sequences, and the .bin folders `_bin_folders` finds that are not one of theirs)."""
    groups: list[_Group] = []
    if kind in ("auto", "raw"):
        for drive_dir in _raw_drives(root):
            date, drive, _ = DRIVE_PATTERN.match(drive_dir.name).groups()  # type: ignore[union-attr]
            groups.append(_Group((drive_dir.name, f"{date}_drive_{drive}", drive),
                                 _scans(drive_dir / "velodyne_points" / "data"),
                                 dict(dataset="raw", sequence=drive_dir.name,
                                      base=str(drive_dir.parent.parent), date=date, drive=drive)))
    if kind in ("auto", "odometry"):
        for sequence_dir in _odometry_sequences(root):
            problem = layout_name_problem(sequence_dir.name)
            if problem is not None:  # its frames written where readers skip them, or break the dataset
                raise InputError("load", str(sequence_dir), f"the sequence folder's name {problem}: rename it")
            groups.append(_Group((sequence_dir.name,), _scans(sequence_dir / "velodyne"),
                                 dict(dataset="odometry", sequence=sequence_dir.name,
                                      base=str(sequence_dir.parent.parent))))
    if kind in ("auto", "bin"):
        # "auto": also the .bin folders beside drives and sequences (the KITTI mirror of a run over
        # all three holds one, which was left out without a word: a trial), not those inside them
        inside = {file.parent for group in groups for file in group.files}
        for folder in _bin_folders(root) if root.is_dir() else []:
            if folder in inside:
                continue
            name = bin_sequence_name(folder)
            groups.append(_Group((name, folder.name), _scans(folder), dict(dataset="bin", sequence=name)))
    return [g for g in groups if g.files]


def _numbered(groups: list[_Group]) -> list[tuple[_Group, Path, int]]:
    """(group, file, index) of every scan, after checking that no two scans share a
    frame identity.

    Raises:
        InputError naming both files of the first collision, or a file without a frame number.
    """
    numbered, seen = [], {}
    for group in groups:
        for file in group.files:
            index = frame_index(file)
            key = (group.fields["dataset"], group.fields["sequence"], index)
            if key in seen:
                raise InputError("load", str(file), f"frame {key[0]}/{key[1]}/{index:06d} is also "
                                 f"{seen[key]}: two scans would write the same output (rename or "
                                 "move one)")
            seen[key] = file
            numbered.append((group, file, index))
    return numbered


def discover(path: str | Path, kind: str = "auto", sequences: list[str | int] | str | int | None = None,
             frames: range | None = None, exclude: list[Path] | None = None) -> list[FrameRef]:
    """Every scan under `path`, sorted by dataset, sequence and frame number.

    Args:
        path: see the module docstring.
        kind: "raw", "odometry", "bin" or "auto" (all raw drives and odometry sequences found,
            and the folder, or its subfolders, of .bin files that are not theirs).
        sequences: drive names (full folder name, "DATE_drive_XXXX" or "XXXX"), sequence ids or
            bin folder names (with or without the path hash) to keep, or one of them; None keeps
            all. Digit-only names and integers match without their leading zeros (0 and "0" take
            sequence "00").
        frames: frame indices to keep; None keeps all.
        exclude: folders whose drives, sequences and .bin folders are left out (a run's data
            folders, `stages.write.data_folders`, when they lie under the input: its KITTI mirror
            is a scan tree of its own).

    Returns:
        One `FrameRef` per scan, fingerprinted; a `.bin` file given as `path` is one frame
        (dataset "bin", sequence named after its folder).

    Raises:
        InputError: `path` is missing, holds nothing of the requested kind, lacks any of the
            requested `sequences` (the message names them and lists those it holds) or holds
            several that one of them names (drive 0001 of two dates), is one scan
            while `sequences` are named, or `frames` selects none of
            its scans (the message lists the frames each sequence holds); a scan name holds no
            frame number; two scans have the same identity (naming both). Nothing is read then.
    """
    root = Path(path)
    if isinstance(sequences, (str, int)) and not isinstance(sequences, bool):
        sequences = [sequences]  # one name, not its characters ("05" selected "0" and "5")
    if sequences is not None:
        sequences = [str(name) for name in sequences]  # 0 is sequence "00", as the CLI's -s 0
    if not root.exists():
        raise InputError("load", str(root), "does not exist")
    if kind not in ("auto", "raw", "odometry", "bin"):
        raise InputError("load", str(root), f"unknown input kind {kind!r}")
    # Through a symbolic link to a folder or the folder itself, the same scans are the same frames
    # (the same sequence names and sources), so a run by either path skips what the other did. A
    # scan's own name stays as given: it carries the frame number.
    if root.is_file():
        if sequences:
            raise InputError("load", str(root), f"one scan is one frame: sequences {list(sequences)} select nothing "
                                                "in it (give the folder to choose sequences)")
        return _single_scan(Path(os.path.realpath(root.parent)) / root.name, frames)
    root = Path(os.path.realpath(root))
    groups = _groups(root, kind)
    found_anywhere = bool(groups)
    if exclude:  # a run's own output under its input (its KITTI mirror is a scan tree)
        left_out = [Path(os.path.realpath(folder)) for folder in exclude]
        # a group's scans all lie in one folder: resolved once, not once per scan
        groups = [g for g in groups if g.files and not any(
            folder in Path(os.path.realpath(g.files[0].parent), g.files[0].name).parents for folder in left_out)]
    if not groups:
        expected = {"auto": "KITTI raw drives, odometry sequences or .bin scans",
                    "raw": "KITTI raw drives (DATE/DATE_drive_XXXX_sync/velodyne_points/data/*.bin)",
                    "odometry": "KITTI odometry sequences (sequences/NN/velodyne/*.bin)",
                    "bin": ".bin scans"}[kind]
        if found_anywhere:  # "no scans found" where the scans were plainly there
            raise InputError("load", str(root), f"no {expected} found outside the run's own output folders "
                                                f"({', '.join(map(str, exclude or []))}); write the output "
                                                "elsewhere to read them")
        raise InputError("load", str(root), f"no {expected} found")
    wanted = None if sequences is None else {_sequence_name(name) for name in sequences}
    chosen = [g for g in groups if wanted is None or any(_sequence_name(name) in wanted for name in g.names)]
    found = {_sequence_name(name) for g in chosen for name in g.names}
    missing = [name for name in sequences or [] if _sequence_name(name) not in found]
    if missing:  # one name mistyped among several must not lose its sequence without a word
        available = ", ".join(g.names[0] for g in groups)
        raise InputError("load", str(root), f"sequences {missing} not found; found: {available}")
    for name in sequences or []:  # "1" names drive 0001 of every date: KITTI numbers drives per date
        named = [g.names[0] for g in chosen if _sequence_name(name) in {_sequence_name(n) for n in g.names}]
        if len(named) > 1:
            raise InputError("load", str(root), f"sequence {name!r} names {len(named)} drives or sequences: "
                                                f"{', '.join(named)}; name each one wanted by its full name")
    numbered = _numbered(chosen)
    # frame order within a sequence (file names may differ in case or prefix: SCAN_000003.BIN
    # sorted before scan_000001.bin, and the run went 3, 0, 1)
    position = {id(group): place for place, group in enumerate(chosen)}
    numbered.sort(key=lambda item: (position[id(item[0])], item[2]))
    refs = [FrameRef(index=index, source=str(file),
                     fingerprint=source_fingerprint(file), **group.fields)  # type: ignore[arg-type]
            for group, file, index in numbered if frames is None or index in frames]
    selected = {ref.sequence for ref in refs}
    # with no sequence named, any selecting frames will do; a named one must give some
    empty = [g for g in chosen if g.fields["sequence"] not in selected] if sequences else chosen if not refs else []
    if frames is not None and empty:
        held = "; ".join(f"{g.names[0]}: {_index_span([i for h, _, i in numbered if h is g])}" for g in empty)
        raise InputError("load", str(root), f"no frames in the selected range ({_describe_range(frames)}) in "
                                            f"{', '.join(g.names[0] for g in empty)}; frames found: {held}")
    return refs


def _sequence_name(name: str) -> str:
    """A drive or sequence name as `discover` compares them: digit-only names without leading
    zeros ("0" and "00" both name odometry sequence 00, "1" drive 0001)."""
    name = str(name)
    return str(int(name)) if name.isdigit() else name


def _index_span(indices: list[int]) -> str:
    """The frame indices of a drive or sequence, e.g. "6 frames, 0 to 5", or with gaps "4 frames
    from 0 to 5: 0, 1, 3, 5" (up to `LISTED_INDICES` of them; "0 to 5" alone read as if frame 2
    were there: a batch user's trial)."""
    if not indices:
        return "no frames"
    low, high, count = min(indices), max(indices), len(set(indices))
    if count == high - low + 1:
        return f"{len(indices)} frames, {low} to {high}"
    shown = sorted(set(indices))
    listed = ", ".join(map(str, shown[:LISTED_INDICES])) + (", ..." if count > LISTED_INDICES else "")
    return f"{len(indices)} frames from {low} to {high}: {listed}"


#: How many frame numbers a message lists of a drive or sequence with gaps (`_index_span`).
LISTED_INDICES = 12


def _describe_range(frames: range) -> str:
    last = "the end" if frames.stop >= OPEN_END else str(frames.stop - 1)
    step = f", every {frames.step}" if frames.step != 1 else ""
    return f"first {frames.start}, last {last}{step}"


def _single_scan(path: Path, frames: range | None) -> list[FrameRef]:
    """One `.bin` file given as the input: one frame (dataset "bin", its folder's sequence name)."""
    if path.suffix.lower() != ".bin":
        raise InputError("load", str(path), "is a file but not a KITTI .bin scan (give a .bin file or a folder)")
    index = frame_index(path)
    if frames is not None and index not in frames:
        raise InputError("load", str(path), f"frame {index} is outside the selected range ({_describe_range(frames)})")
    return [FrameRef(dataset="bin", sequence=bin_sequence_name(path.parent), index=index, source=str(path),
                     fingerprint=source_fingerprint(path))]
