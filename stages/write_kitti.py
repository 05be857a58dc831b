"""The `kitti` output format: a mirror of the input's KITTI layout under `OUT/kitti/`.

Each frame's cloud is written as a KITTI Velodyne `.bin` (float32 x, y, z, reflectance per point,
sensor frame, metres), at the place the input scan had in its own layout, so every KITTI reader
(pykitti, OpenPCDet- and mmdetection3d-style loaders, SemanticKITTI tools, kiss-icp, and
`kitti-pu run` itself) opens the densified tree as it opened the original:

    raw:      kitti/DATE/DATE_drive_XXXX_sync/velodyne_points/data/NNNNNNNNNN.bin
              (+ DATE/calib_*.txt, the drive's oxts/ and velodyne_points/timestamps*.txt copied)
    odometry: kitti/sequences/NN/velodyne/NNNNNN.bin
              (+ sequences/NN/calib.txt and times.txt, poses/NN.txt and SemanticKITTI's
              sequences/NN/poses.txt when present, copied)
    bin:      kitti/FOLDER/NAME.bin (the input file's own name)

What a `.bin` cannot hold goes into a sidecar per frame, `kitti_pu/STEM.npz` beside the scan folder
(`sequences/NN/kitti_pu/`, `DRIVE/kitti_pu/`, `FOLDER/kitti_pu/`, like SemanticKITTI's `labels/`
beside `velodyne/`; for a folder of `.bin` files, `FOLDER/kitti_pu/` inside it): `generated` and
`ground` ((Q,) bool) and `parent` ((Q,) int64), row for row with the scan, and `record`, the frame's
record as a JSON string (source, counts, config hash, model checksum: `stages.write.frame_record`). It is `.npz`, not Parquet, so that no `**/*.parquet` glob over the output folder
counts a frame twice, and so that numpy alone reads it: `np.load(path)["generated"]`.

SemanticKITTI labels: where an odometry sequence has `labels/STEM.label` beside `velodyne/` (uint32
per point, semantic class in the low 16 bits, instance in the high 16), the mirror gets its own
`labels/STEM.label`, each point the label of the return it comes from (`parent`): a generated point
takes its parent's, a returned point keeps its own.
"""

from __future__ import annotations

import filecmp
import io
import json
import os
import re
import shutil
import zipfile
import zlib
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .discovery import frame_number
from .errors import InputError
from .frame import Frame, StitchedCloud

SIDECAR_FOLDER = "kitti_pu"
#: The datasets the mirror lays out (the module docstring's layouts).
LAYOUTS = ("raw", "odometry", "bin")
#: SemanticKITTI's folder of per-point labels beside `velodyne/`.
LABELS_FOLDER = "labels"
_RAW_DRIVE = re.compile(r"^(\d{4}_\d{2}_\d{2})_drive_\d{4}_\w+$")


def scan_path(out_dir: Path, dataset: str, sequence: str, index: int, source: str = "") -> Path:
    """Where the frame's mirrored `.bin` goes under `out_dir/kitti` (layouts in the module docstring).

    The file keeps the input's name, its suffix in lower case, when `source` is a `.bin` whose
    number is `index` (as discovery names frames), else it is named by `index` the KITTI way (10
    digits for raw, 6 otherwise): frames made in memory from one file of another kind, or given
    another number, overwrote each other's copy under that file's name. (A `.BIN` copy was missed by
    every reader that globs `*.bin`, pykitti's among them: a trial.)
    """
    root = Path(out_dir) / "kitti"
    digits = 10 if dataset == "raw" else 6
    own = Path(source).name if source else ""
    keeps_name = own.lower().endswith(".bin") and frame_number(own) == index
    name = f"{own[:-4]}.bin" if keeps_name else f"{index:0{digits}d}.bin"
    if dataset == "raw":
        match = _RAW_DRIVE.match(sequence)
        date = match.group(1) if match else "unknown_date"
        return root / date / sequence / "velodyne_points" / "data" / name
    if dataset == "odometry":
        return root / "sequences" / sequence / "velodyne" / name
    return root / sequence / name


def sidecar_path(scan: Path) -> Path:
    """The sidecar (.npz: generated, ground, parent) of a mirrored scan path."""
    scan = Path(scan)
    folder = scan.parent
    if folder.name == "data" and folder.parent.name == "velodyne_points":  # raw: DRIVE/kitti_pu/
        folder = folder.parent.parent
    elif folder.name == "velodyne":  # odometry: sequences/NN/kitti_pu/
        folder = folder.parent
    return folder / SIDECAR_FOLDER / f"{scan.stem}.npz"


def scan_bytes(cloud: StitchedCloud) -> bytes:
    """The cloud as a KITTI `.bin`: (Q, 4) float32 x, y, z, reflectance, row-major."""
    rows = np.empty((len(cloud), 4), dtype=np.float32)
    rows[:, :3] = cloud.xyz
    rows[:, 3] = cloud.reflectance
    return rows.tobytes()


def sidecar_bytes(cloud: StitchedCloud, record: Mapping[str, str] | None = None) -> bytes:
    """The sidecar's .npz content: generated, ground ((Q,) bool) and parent ((Q,) int64), and the
    frame's record (`stages.write.frame_record`) as a JSON string under "record"."""
    buffer = io.BytesIO()
    np.savez_compressed(buffer, generated=cloud.generated.astype(bool), ground=cloud.ground.astype(bool),
                        parent=cloud.parent.astype(np.int64), record=np.array(json.dumps(dict(record or {}))))
    return buffer.getvalue()


def stored_record(scan: Path) -> dict[str, str]:
    """The record a mirrored scan's sidecar holds ({} for a sidecar of an earlier version).

    Raises OSError or ValueError when the sidecar is missing or unreadable."""
    return sidecar_record(sidecar_path(scan))[0]


def sidecar_record(sidecar: Path) -> tuple[dict[str, str], int]:
    """(the record a sidecar holds, {} for one of an earlier version; its row count).

    Raises OSError or ValueError when the sidecar is missing or unreadable."""
    try:
        with np.load(sidecar) as arrays:
            record = json.loads(str(arrays["record"])) if "record" in arrays.files else {}
        (rows,) = sidecar_shapes(sidecar, ("generated",))["generated"]
        return record, rows
    except (zipfile.BadZipFile, KeyError, zlib.error) as error:
        raise ValueError(f"{sidecar}: {error}") from None


def sidecar_shapes(sidecar: Path, names: tuple[str, ...] = ("generated", "ground", "parent")
                   ) -> dict[str, tuple[int, ...]]:
    """The shapes of a sidecar's arrays `names`, from their .npy headers: only each member's first
    bytes are decompressed. `np.load` decompressed every array whole, 2-12 ms a frame, on every
    rerun's check of every finished frame (a trial at scale); the data's checksums are read by
    `kitti-pu info --verify`.

    Raises OSError, KeyError or zipfile.BadZipFile when the sidecar or a member is missing,
    ValueError when a member's header does not read (a damaged byte, which zlib reports)."""
    shapes = {}
    with zipfile.ZipFile(sidecar) as archive:
        for name in names:
            try:
                with archive.open(f"{name}.npy") as member:
                    version = np.lib.format.read_magic(member)
                    header = (np.lib.format.read_array_header_1_0 if version == (1, 0)
                              else np.lib.format.read_array_header_2_0)
                    shapes[name] = header(member)[0]
            except zlib.error as error:
                raise ValueError(f"{sidecar}: {name}: {error}") from None
    return shapes


def _metadata_files(dataset: str, sequence: str, index: int, source: str, scan: Path,
                    packets: tuple[str, int, str] | None = None) -> list[tuple[Path, Path]]:
    """(source, target) pairs of the input's metadata files that the mirror copies for the frame
    `index` of `sequence` read from `source` and mirrored at `scan` (every pair, also those whose
    source is missing): `_shared_metadata`, and a raw drive's OXTS packets (`_oxts_files`;
    `packets` is the drive's `_packets_version`)."""
    pairs = _shared_metadata(dataset, sequence, source, scan)
    scan_source = Path(source)
    if dataset == "raw" and scan_source.parent.name == "data":
        drive_dir, target_drive = scan_source.parent.parent.parent, Path(scan).parent.parent.parent
        pairs += [(oxts, target_drive / oxts.relative_to(drive_dir))
                  for oxts in _oxts_files(drive_dir / "oxts", index, packets) if oxts.parent.name == "data"]
    return pairs


def _shared_metadata(dataset: str, sequence: str, source: str, scan: Path) -> list[tuple[Path, Path]]:
    """(source, target) pairs of the metadata files the frames of a sequence share, for a frame
    read from `source` and mirrored at `scan`: odometry calib.txt, times.txt, SemanticKITTI's
    poses.txt and poses/NN.txt; raw the date's calib_*.txt (shared by every drive of the date), the
    drive's velodyne timestamps and its oxts/ files but the packets. Every pair, also those whose
    source is missing; the input's paths as discovered, not resolved (a `velodyne/` linked into
    another tree takes its metadata from its own)."""
    scan_source, scan = Path(source), Path(scan)
    pairs: list[tuple[Path, Path]] = []
    if dataset == "odometry" and scan_source.parent.name == "velodyne":
        sequence_dir, target_dir = scan_source.parent.parent, scan.parent.parent
        # poses.txt: SemanticKITTI's copy of the poses, in the sequence folder
        pairs += [(sequence_dir / name, target_dir / name) for name in ("calib.txt", "times.txt", "poses.txt")]
        pairs.append((sequence_dir.parent.parent / "poses" / f"{sequence}.txt",
                      target_dir.parent.parent / "poses" / f"{sequence}.txt"))
    elif dataset == "raw" and scan_source.parent.name == "data":
        drive_dir, target_drive = scan_source.parent.parent.parent, scan.parent.parent.parent
        pairs += [(calib, target_drive.parent / calib.name) for calib in sorted(drive_dir.parent.glob("calib_*.txt"))]
        pairs += [(stamps, target_drive / "velodyne_points" / stamps.name)
                  for stamps in sorted((drive_dir / "velodyne_points").glob("timestamps*.txt"))]
        pairs += [(oxts, target_drive / "oxts" / oxts.name) for oxts in sorted((drive_dir / "oxts").glob("*.txt"))]
    return pairs


def _optional(target: Path) -> bool:
    """Whether a mirrored metadata file is one the input may lack (poses): removed from the mirror
    when the input no longer has it."""
    return target.parent.name == "poses" or target.name == "poses.txt"


def _one_line_a_frame(target: Path) -> bool:
    """Whether a metadata file holds one line per frame (times, timestamps, poses), so that lines
    appended for new frames change nothing the frames before them read."""
    return target.name == "times.txt" or target.name.startswith("timestamps") or _optional(target)


def copy_metadata(dataset: str, sequence: str, index: int, source: str, scan: Path,
                  atomic: Callable[[Path, Callable[[Path], None]], None]) -> None:
    """Bring the mirror's copies of the input's metadata files (calibration, times, poses, OXTS) up
    to date for the frame `index` of `sequence` read from `source` and mirrored at `scan`: each file
    the mirror lacks, or whose input differs (size or modification time: the copy keeps the
    input's), is copied through `atomic(path, write)`; a poses file the input no longer has is
    removed (its frames, redone, record no pose). Called with each frame written, and by a run
    for each sequence it selected, so that a correction that redoes no frame reaches the mirror."""
    packets = (_packets_version(Path(source).parent.parent.parent / "oxts", scan.parent.parent.parent)
               if dataset == "raw" else None)
    for origin, target in _metadata_files(dataset, sequence, index, source, scan, packets):
        if origin.is_file():
            if not _same_copy(origin, target):
                atomic(target, lambda temporary, origin=origin: _copy_with_its_time(origin, temporary))
        elif _optional(target) and target.is_file():
            target.unlink()
    if packets is not None:  # copied whole (or checked) without an error: later frames copy their own
        _SYNCED_PACKETS.add(packets)


def _copy_with_its_time(origin: Path, copy: Path) -> None:
    """Copy the file `origin` to `copy` with its modification time (what `_same_copy` compares),
    and the mode of any new file (0666 less the umask): shutil.copy2 kept a read-only input's
    r--r--r-- in the mirror (an operator's trial)."""
    shutil.copyfile(origin, copy)
    status = origin.stat()
    os.utime(copy, ns=(status.st_atime_ns, status.st_mtime_ns))


#: OXTS packet folders (with their modification times) this process has copied whole, each with
#: the mirrored drive folder it copied them to (a second output of the same drive needs them too).
_SYNCED_PACKETS: set[tuple[str, int, str]] = set()


def _packets_version(oxts_dir: Path, target_drive: Path) -> tuple[str, int, str] | None:
    """A raw drive's packet folder, its modification time (packets added or removed change it)
    and the mirrored drive folder `target_drive` it is copied to, or None when it cannot be read."""
    data = oxts_dir / "data"
    try:
        return str(data), data.stat().st_mtime_ns, str(target_drive)
    except OSError:
        return None


def _oxts_files(oxts_dir: Path, index: int, version: tuple[str, int, str] | None) -> list[Path]:
    """The OXTS files a raw frame's write copies: every one while this process has not copied the
    drive's packet folder whole (as it is now: `_SYNCED_PACKETS`); after that the folder's own
    files (timestamps, data format), frame 0's packet (the poses' origin) and the frame's own.
    Each frame checked every packet of the drive, a cost that grew with it; a corrected packet of
    another frame reaches the mirror when that frame is written again, which a rerun does (its
    pose changed, `pipeline.resume`). `version` is the folder's `_packets_version`."""
    if version is None or version not in _SYNCED_PACKETS:
        return sorted(oxts_dir.rglob("*.txt"))
    data = oxts_dir / "data"
    return [*sorted(oxts_dir.glob("*.txt")), data / f"{0:010d}.txt", data / f"{index:010d}.txt"]


def write_kitti(cloud: StitchedCloud, frame: Frame, scan: Path,
                atomic: Callable[[Path, Callable[[Path], None]], None],
                record: Mapping[str, str] | None = None) -> None:
    """Write the frame's mirrored `.bin`, its sidecar (with the frame's `record`), and (once per
    sequence) the input's metadata files, each through `atomic(path, write)` (a temporary name
    renamed into place).

    A metadata file is copied when the mirror lacks it or the input's differs from the copy (size
    or modification time: the copy keeps the input's), so times, poses or calibration that grow
    with a dataset, or are corrected, reach the mirror with the next frame written; the labels (when
    the input has them) and the sidecar are written before the scan, so a scan on disk has both. A
    scan mirrored before is removed first: a process killed before the new scan is in place leaves
    the frame incomplete (`is_complete`), never the old scan beside the new sidecar and labels.

    Raises:
        InputError naming the input's label file when it does not hold one label per return.
    """
    copy_metadata(frame.dataset, frame.sequence, frame.index, frame.source, scan, atomic)
    Path(scan).unlink(missing_ok=True)
    labels = label_paths(frame.dataset, frame.source, scan)
    if labels is not None:
        _write_labels(*labels, cloud.parent, Path(frame.source), atomic)
    payload = sidecar_bytes(cloud, record)
    atomic(sidecar_path(scan), lambda temporary: Path(temporary).write_bytes(payload))
    data = scan_bytes(cloud)
    atomic(scan, lambda temporary: Path(temporary).write_bytes(data))


@dataclass
class ConflictMemo:
    """What `shared_metadata_conflict` has read, kept across its calls in one check: the mirror's
    targets already found to hold no conflict with an input file (target, origin: a date's
    calibration is shared by its drives), and the sources the mirrored frames record (each sidecar
    is read once)."""

    cleared: set[tuple[Path, Path]] = field(default_factory=set)
    sources: dict[Path, str] = field(default_factory=dict)

    def source_of(self, scan: Path) -> str:
        """`recorded_source` of a mirrored scan, read once."""
        if scan not in self.sources:
            self.sources[scan] = recorded_source(scan)
        return self.sources[scan]


def shared_metadata_conflict(dataset: str, sequence: str, source: str, scan: Path,
                             selected: set[tuple[str, int]], memo: ConflictMemo | None = None) -> str | None:
    """Why mirroring frames of `sequence` from `source`'s folder would change what frames the mirror
    holds from another input folder read, or None.

    The mirror keeps one copy of each metadata file the frames of a sequence share
    (`_shared_metadata`; raw calibration is shared by every drive of a date), brought up to date
    from the input of every run (`copy_metadata`). Where this input's file differs from the copy,
    frames of another input folder that read it and that this run does not redo would be read with
    this folder's times, poses or calibration: KITTI readers of the mirror got the wrong ones.
    Lines appended for new frames (a dataset that grows) differ from nothing those frames read,
    and the same files in another folder (a dataset moved) do not differ at all. The folder a
    mirrored frame reads a file from is found from the source it records, whether or not that
    folder is still there.

    Args:
        dataset, sequence, source: one selected frame of the sequence (its `FrameRef`).
        scan: where that frame is mirrored (`scan_path`).
        selected: (sequence, frame number) of every frame of `dataset` this run selected.
        memo: what earlier calls of one check have read (`ConflictMemo`), or None.
    """
    memo = memo if memo is not None else ConflictMemo()
    for origin, target in _shared_metadata(dataset, sequence, source, scan):
        if (target, origin) in memo.cleared or not _differs(origin, target):
            continue
        # the mirrored scan folders whose frames read `target`: a date's calibration, every drive's
        readers = (sorted(target.parent.glob("*/velodyne_points/data")) if target.name.startswith("calib_")
                   else [Path(scan).parent])
        for folder in readers:
            reader_sequence = folder.parent.parent.name if dataset == "raw" else sequence
            for number, copies in sorted(_scans_by_number(folder).items()):
                if (reader_sequence, number) in selected:
                    continue
                other = memo.source_of(copies[0])
                if not other:  # an incomplete frame, redone by the next run that selects it
                    continue
                theirs = _origin_for(dataset, other, target)
                if theirs is not None and theirs != origin:
                    how = ("holds only its first lines" if origin.is_file() and
                           target.read_bytes().startswith(origin.read_bytes()) else
                           "is missing" if not origin.is_file() else "differs from it")
                    if not Path(other).exists():  # its scan is gone: no run can ever redo the frame
                        return (f"{folder} holds frame {number}, mirrored from {other}, which no longer exists; it "
                                f"reads {target.name} from {theirs}, and this run's {origin} {how}, so the frame "
                                f"would be read with times, poses or calibration not its own. If the frame is gone "
                                f"for good, remove its files from the mirror ({', '.join(_frame_files(copies[0]))}) "
                                "and run again; otherwise write to another output folder")
                    # "is missing, and would replace" read as a contradiction (a batch user's trial)
                    effect = "would remove" if not origin.is_file() else "would replace"
                    return (f"{folder} holds frames of {Path(other).parent} (frame {number} the first this run "
                            f"would not redo), which read {target.name} from {theirs}; this run's {origin} "
                            f"{how}, and so {effect} the file those frames are read with. Write frames of "
                            "another input folder to another output folder")
        memo.cleared.add((target, origin))
    return _packet_conflict(sequence, source, scan, selected, memo) if dataset == "raw" else None


def _packet_conflict(sequence: str, source: str, scan: Path, selected: set[tuple[str, int]],
                     memo: ConflictMemo) -> str | None:
    """`shared_metadata_conflict` of a raw drive's OXTS packets: a mirrored frame of another input
    drive folder, not redone, reads its own packet and packet 0 (its pose's world origin), which
    this run would replace with other content (a first frame copies its drive's packets whole:
    another folder's frames got this one's poses, a trial). Copies as `copy_metadata` makes them
    (same size and time) are not compared further, so a drive of one folder costs a stat a packet."""
    drive_dir = Path(source).parent.parent.parent
    ours, mirrored = drive_dir / "oxts" / "data", Path(scan).parent.parent.parent / "oxts" / "data"
    for number, copies in sorted(_scans_by_number(Path(scan).parent).items()):
        if (sequence, number) in selected:
            continue
        changed = [name for name in (f"{number:010d}.txt", f"{0:010d}.txt")
                   if (ours / name).is_file() and (mirrored / name).is_file()
                   and not _same_copy(ours / name, mirrored / name)
                   and not filecmp.cmp(ours / name, mirrored / name, shallow=False)]
        if not changed:
            continue
        other = memo.source_of(copies[0])
        if other and Path(other).parent.parent.parent != drive_dir:
            return (f"{Path(scan).parent} holds frame {number} of {Path(other).parent}, which reads its pose from "
                    f"OXTS packet {changed[0]} of {Path(other).parent.parent.parent / 'oxts' / 'data'}; this run's "
                    f"{ours / changed[0]} differs from it, and would replace it. Write frames of another input "
                    "folder to another output folder")
    return None


def inputs_at_odds(frames: list[tuple[str, str, str, Path]]) -> str | None:
    """Why the frames one run mirrors, of several sequences, cannot share the mirror's copies of
    their metadata (`_shared_metadata`), or None: two of them read one mirrored file (a raw date's
    calibration) from two input files of other content (two raw bases with the same date in one
    run: one calibration won, silently, a trial).

    Args:
        frames: (dataset, sequence, source, scan) of one selected frame of each sequence.
    """
    read_from: dict[Path, tuple[Path, str]] = {}
    for dataset, sequence, source, scan in frames:
        for origin, target in _shared_metadata(dataset, sequence, source, scan):
            if not origin.is_file():
                continue
            first = read_from.setdefault(target, (origin, sequence))
            if first[0] != origin and not filecmp.cmp(first[0], origin, shallow=False):
                return (f"{first[1]} and {sequence} read {target.name} from {first[0]} and {origin}, which differ; "
                        f"the mirror keeps one {target}. Run them into two output folders")
    return None


def _origin_for(dataset: str, source: str, target: Path) -> Path | None:
    """The input file a frame read from `source` takes the mirror's shared metadata file `target`
    from (`_shared_metadata`'s pairs, by the layout's paths alone: the input folder may be gone);
    None for a target that is not one of those."""
    scan_source = Path(source)
    if dataset == "odometry" and scan_source.parent.name == "velodyne":
        sequence_dir = scan_source.parent.parent
        return sequence_dir.parent.parent / "poses" / target.name if target.parent.name == "poses" else (
            sequence_dir / target.name)
    if dataset == "raw" and scan_source.parent.name == "data":
        drive_dir = scan_source.parent.parent.parent
        if target.name.startswith("calib_"):
            return drive_dir.parent / target.name
        if target.parent.name in ("velodyne_points", "oxts"):
            return drive_dir / target.parent.name / target.name
    return None


def recorded_source(scan: Path) -> str:
    """The source a mirrored scan's sidecar records ("" when it records none or cannot be read);
    reads the record alone."""
    try:
        with np.load(sidecar_path(scan)) as arrays:
            return str(json.loads(str(arrays["record"])).get("source", "")) if "record" in arrays.files else ""
    except (OSError, ValueError, KeyError, zipfile.BadZipFile):
        return ""


def _differs(origin: Path, target: Path) -> bool:
    """Whether the mirror's copy `target` holds what this input's `origin` would change for frames
    already mirrored: other content where both exist (for a file of one line a frame, unless the
    copy's lines are the first of the origin's), or a poses file the mirror keeps that the input no
    longer has (`copy_metadata` removes it)."""
    if not origin.is_file():
        return _optional(target) and target.is_file()
    if not target.is_file() or filecmp.cmp(origin, target, shallow=False):
        return False
    copy = target.read_bytes()
    # whole lines only: a copy ending mid-line ("1.0") is not the start of "1.05\n"
    return not (_one_line_a_frame(target) and copy.endswith(b"\n") and origin.read_bytes().startswith(copy))


def label_paths(dataset: str, source: str, scan: Path) -> tuple[Path, Path] | None:
    """(the input's SemanticKITTI label file, the mirror's) of an odometry frame read from
    `sequences/NN/velodyne/STEM.bin` and mirrored at `scan`; None for other layouts. Either file may
    not exist."""
    scan_source = Path(source)
    if dataset != "odometry" or scan_source.parent.name != "velodyne" or Path(scan).parent.name != "velodyne":
        return None
    return (scan_source.parent.parent / LABELS_FOLDER / f"{scan_source.stem}.label",
            mirrored_labels(scan))


def mirrored_labels(scan: Path) -> Path:
    """Where the mirror keeps the labels of the odometry scan mirrored at `scan`."""
    return Path(scan).parent.parent / LABELS_FOLDER / f"{Path(scan).stem}.label"


def labels_problem(dataset: str, source: str) -> InputError | None:
    """The error of an odometry frame whose input has SemanticKITTI labels that are not one for each
    return of its scan (found before the frame runs: the network's pass was spent on it before, and
    a finished frame was kept with stale labels and a warning), or None."""
    scan_source = Path(source)
    if dataset != "odometry" or scan_source.parent.name != "velodyne":
        return None
    labels = scan_source.parent.parent / LABELS_FOLDER / f"{scan_source.stem}.label"
    try:
        problem = _label_count_problem(labels, scan_source)
    except OSError:  # no labels (or no scan: the load stage names it)
        return None
    return InputError("load", str(labels), problem) if problem else None


def _label_count_problem(labels_file: Path, scan_source: Path) -> str | None:
    """What is wrong with a label file that does not hold one 4-byte label for each return of its
    scan, or None. Raises OSError when either file cannot be read."""
    returns = Path(scan_source).stat().st_size // 16
    size = Path(labels_file).stat().st_size
    return None if size == 4 * returns else (f"{size} bytes: not one 4-byte label for each of the {returns} "
                                             f"returns of {scan_source}")


def labels_of_points(labels_file: Path, parent: np.ndarray, scan_source: Path) -> bytes:
    """The mirror's label file: (Q,) uint32, each point the label of its parent return.

    Args:
        labels_file: the input's `.label` (one uint32 per return of `scan_source`, in its order).
        parent: (Q,) int64 row of each output point in the input scan (`StitchedCloud.parent`).
        scan_source: the input scan, whose size says how many returns it holds.

    Raises:
        InputError("write", labels_file, ...) when the file does not hold one label per return.
    """
    problem = _label_count_problem(labels_file, scan_source)
    if problem:
        raise InputError("write", str(labels_file), problem)
    labels = np.fromfile(labels_file, dtype=np.uint32)
    return labels[np.asarray(parent, dtype=np.int64)].tobytes()


def update_labels(dataset: str, source: str, scan: Path,
                  atomic: Callable[[Path, Callable[[Path], None]], None]) -> str | None:
    """Bring a finished frame's labels in the mirror up to date with the input's, without a network
    pass: written from the sidecar's `parent` when the input has labels the mirror lacks or other
    than those it was written from (its modification time differs: the mirror's copy keeps the
    input's, so labels unpacked from an older archive are noticed too), removed when the input has
    none. Returns what it did ("written", "removed") or None.

    Raises:
        InputError (see `labels_of_points`), OSError or ValueError for an unreadable sidecar.
    """
    due = labels_update_due(dataset, source, scan)
    if due is None:
        return None
    origin, target = label_paths(dataset, source, scan)
    if due == "removed":
        target.unlink()
        return due
    with np.load(sidecar_path(scan)) as arrays:
        parent = arrays["parent"]
    _write_labels(origin, target, parent, Path(source), atomic)
    return due


def labels_update_due(dataset: str, source: str, scan: Path) -> str | None:
    """What `update_labels` would do to the finished frame mirrored at `scan` ("written",
    "removed" or None), without doing it (`kitti-pu run --dry-run` counts these)."""
    paths = label_paths(dataset, source, scan)
    if paths is None:
        return None
    origin, target = paths
    if not origin.is_file():
        return "removed" if target.is_file() else None
    if _labels_current(origin, target) or not is_complete(scan):
        return None
    return "written"


def _labels_current(origin: Path, target: Path) -> bool:
    """Whether the mirror's labels were written from the input's as they are (same modification
    time, which `_write_labels` gives the copy)."""
    try:
        return target.stat().st_mtime_ns == origin.stat().st_mtime_ns
    except OSError:
        return False


def _write_labels(origin: Path, target: Path, parent: np.ndarray, scan_source: Path,
                  atomic: Callable[[Path, Callable[[Path], None]], None]) -> None:
    """Write the mirror's labels at `target` from the input's at `origin` (`labels_of_points`), with
    `origin`'s modification time; remove a copy at `target` when the input has none (a frame redone
    after its labels went: the old ones no longer matched its points)."""
    if not origin.is_file():
        target.unlink(missing_ok=True)
        return
    stamp = origin.stat().st_mtime_ns  # before the read: labels replaced meanwhile then differ in time
    mirrored = labels_of_points(origin, parent, scan_source)

    def write(temporary: Path) -> None:
        Path(temporary).write_bytes(mirrored)
        os.utime(temporary, ns=(stamp, stamp))

    atomic(target, write)


def _same_copy(source: Path, target: Path) -> bool:
    """Whether `target` is a copy of `source` as `write_kitti` makes them: same size, same
    modification time."""
    try:
        a, b = source.stat(), target.stat()
    except OSError:
        return False
    return a.st_size == b.st_size and a.st_mtime_ns == b.st_mtime_ns


def remove(scan: Path) -> None:
    """Remove a frame's mirrored scan, sidecar and labels, those that are files (when a frame's
    write failed in another format, or its files are stale)."""
    labels = [mirrored_labels(scan)] if Path(scan).parent.name == "velodyne" else []  # odometry only
    for path in (Path(scan), sidecar_path(scan), *labels):
        if path.is_file():
            path.unlink()


def renamed_copies(scans: list[Path]) -> dict[Path, list[Path]]:
    """For mirrored scan paths (`scan_path` of frames under their current source names), the other
    `.bin` files in each one's folder that hold the same frame number: what the mirror kept of the
    frame under an earlier name of its input file (a renamed scan; two input files of one number
    are refused when the frames are discovered, so such a copy is never another frame's). Each
    folder is listed once.

    Returns:
        {scan: [stale copies]} for the scans that have any.
    """
    by_folder: dict[Path, dict[int, list[Path]]] = {}
    stale: dict[Path, list[Path]] = {}
    for scan in map(Path, scans):
        if scan.parent not in by_folder:
            by_folder[scan.parent] = _scans_by_number(scan.parent)
        number = frame_number(scan.name)
        copies = [other for other in by_folder[scan.parent].get(number, []) if other.name != scan.name]
        if number is not None and copies:
            stale[scan] = copies
    return stale


def adopt_case_copy(scan: Path, source: str) -> bool:
    """Rename to `scan` the copy an earlier version mirrored under the input's own suffix (a
    `.BIN` input's scan was mirrored as `.BIN`; `scan_path` names it `.bin` since), when `scan` is
    missing and that copy records the same source: the same frame, which a run would otherwise do
    again as "source changed". Returns whether it renamed one."""
    suffix = Path(source).suffix
    earlier = Path(scan).with_suffix(suffix)
    if suffix == Path(scan).suffix or Path(scan).exists() or not earlier.is_file():
        return False
    if recorded_source(earlier) != str(source):
        return False
    os.replace(earlier, scan)  # the sidecar and labels are named by the stem: they stay the frame's
    return True


def remove_copies(scan: Path, copies: list[Path]) -> None:
    """Remove `copies` (`renamed_copies`) of the frame mirrored at `scan`: each `.bin`, and its
    sidecar unless it is also that of `scan`, which exists (names that differ only in the
    suffix's case share one). On a file system that ignores case, a copy that is `scan` itself is
    left."""
    for copy in copies:
        if scan.exists() and copy.exists() and os.path.samefile(scan, copy):
            continue
        copy.unlink(missing_ok=True)
        if sidecar_path(copy) != sidecar_path(scan) or not scan.exists():  # a shared one is the current copy's
            sidecar_path(copy).unlink(missing_ok=True)
            if copy.parent.name == "velodyne":
                mirrored_labels(copy).unlink(missing_ok=True)


def _frame_files(scan: Path) -> list[str]:
    """The files the mirror holds of the frame mirrored at `scan`: the scan, its sidecar and, for an
    odometry scan, its labels when there are any."""
    files = [scan, sidecar_path(scan)]
    if scan.parent.name == "velodyne":
        files.append(mirrored_labels(scan))
    return [str(path) for path in files if path.exists()]


def _scans_by_number(folder: Path) -> dict[int, list[Path]]:
    """The `.bin` files of `folder` by their frame number ({} when it is not a folder)."""
    found: dict[int, list[Path]] = {}
    try:
        entries = list(folder.iterdir())
    except OSError:
        return found
    for entry in entries:
        number = frame_number(entry.name)
        if entry.suffix.lower() == ".bin" and number is not None:  # discovery takes .BIN too
            found.setdefault(number, []).append(entry)
    return found


def labels_out_of_step(scan: Path) -> Path | None:
    """The mirror's label file of an odometry scan when it does not hold one label for each point
    of the scan (`is_complete` is then False), else None."""
    labels = mirrored_labels(scan)
    if Path(scan).parent.name != "velodyne" or not labels.is_file() or not Path(scan).is_file():
        return None
    return labels if labels.stat().st_size != Path(scan).stat().st_size // 4 else None


def is_complete(scan: Path) -> bool:
    """True when the mirrored scan is a whole number of points and its sidecar is a readable .npz
    holding as many rows (none for a frame whose cloud is empty: every point dropped, which the
    other formats hold as empty files too, and which was redone on every run), and its labels,
    when the mirror has them, one for each point (a run killed while it replaced a frame could
    leave the new labels beside the old scan: a trial)."""
    scan, sidecar = Path(scan), sidecar_path(scan)
    if not scan.is_file() or not sidecar.is_file():
        return False
    size = scan.stat().st_size
    if size % 16:
        return False
    if labels_out_of_step(scan) is not None:
        return False
    try:
        return all(shape == (size // 16,) for shape in sidecar_shapes(sidecar).values())
    except (OSError, ValueError, KeyError, zipfile.BadZipFile):
        return False
