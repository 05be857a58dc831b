"""Stage 1, load: find the scans of KITTI raw drives, odometry sequences or plain `.bin` folders,
and read one scan with its timestamp, calibration and pose.

Layouts (what `discover` accepts, `kind` "auto" tells them apart):
- raw: BASE/DATE/DATE_drive_XXXX_sync/velodyne_points/data/NNNNNNNNNN.bin, calibration in
  BASE/DATE/calib_*.txt, timestamps and poses from oxts/ (read through `pykitti.raw`);
- odometry: BASE/sequences/NN/velodyne/NNNNNN.bin with calib.txt and times.txt (both required:
  KITTI's data_odometry_calib.zip), poses from
  BASE/poses/NN.txt, or SemanticKITTI's sequences/NN/poses.txt, when present (read through `pykitti.odometry`);
- bin: a folder of `.bin` scans (KITTI Velodyne format: float32 x, y, z, reflectance per point).
`path` may be the base folder, a date folder, a drive folder, a `sequences` folder, a sequence
folder, a folder of `.bin` files, or one `.bin` file; under a base folder every drive and sequence
is found. Finding the scans and naming them is `stages.discovery` (re-exported here).
"""

from __future__ import annotations

import datetime as dt
import functools
import math
import numbers
import os
import stat as stat_module
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any, Literal

import numpy as np
from pydantic import Field, field_validator, model_validator

from .discovery import (DRIVE_PATTERN, OPEN_END, FrameRef, discover,  # noqa: F401 (the stage's API)
                        bytes_digest, fingerprint_of, odometry_folders_read_as_bin, source_fingerprint)
from .errors import InputError
from .frame import Frame, check_frame_name
from .options import StageOptions, refuse_empty_path, stage_options
from .repeats import repeated_rows
from .ring_snap import scan_rings
from .wording import counted
from .write_kitti import sidecar_path

#: Bytes per point in a KITTI .bin scan (four float32).
POINT_BYTES = 16
#: Default upper bound on points per scan (an HDL-64E scan has about 120,000).
MAX_POINTS = 1_000_000
#: Default range limit (metres). KITTI's Velodyne HDL-64E is specified to 120 m, and the real
#: scans of odometry sequence 00 reach 80 m; a point beyond 200 m is not a return but garbage.
MAX_RANGE_M = 200.0
#: What to do when a KITTI drive or sequence lacks its calibration or timestamps.
MISSING_METADATA_HINT = "to densify the scans alone, give their own folder (.../velodyne or .../velodyne_points/data)"
#: Returns closer than this to the sensor's origin (metres) are not measurements: converters write
#: (0, 0, 0) for missing returns, and inside this radius are only the sensor's housing and the
#: roof it stands on (the nearest returns of the six real scans of odometry sequence 00: 1.29-1.36
#: m). Kept, such points break ring recovery from the point order: each zero point's azimuth
#: atan2(0, 0) = 0 reads as a ring boundary.
MIN_RANGE_M = 0.5
#: A scan file whose share of negative reflectance values exceeds this is refused: no LiDAR
#: returns a negative intensity, while a file of another layout read as x, y, z, reflectance (x, y,
#: z only, 12 bytes a point) puts coordinates there, about half of them negative.
MAX_NEGATIVE_REFLECTANCE_SHARE = 0.01
#: What a KITTI scan file holds, for the messages of files that do not.
LAYOUT_HINT = "a KITTI .bin holds float32 x, y, z, reflectance per point (16 bytes)"
#: How files of other point-cloud formats begin, and their names: such a file read as a KITTI scan
#: gave its header's bytes as points (an .npy's 128 header bytes as 8 points, 2e8 and 7e31 among them).
OTHER_FORMAT_MAGIC = ((b"\x93NUMPY", "a NumPy .npy file (np.load it and give the array to frame_from_points)"),
                      (b"PK\x03\x04", "a zip archive (a NumPy .npz?)"),
                      (b"ply\n", "a PLY file"), (b"ply\r", "a PLY file"),
                      (b"# .PCD", "a PCD file"), (b"VERSION", "a PCD file"), (b"LASF", "a LAS/LAZ file"))
#: Numbers on the one line of a KITTI raw OXTS packet (oxts/data/NNNNNNNNNN.txt).
OXTS_NUMBERS = 30
#: Default share of a scan's points that may lie beyond the range limit and be dropped. A real
#: scan has none; a file that is not a scan (text, random bytes) has most of its "points" there.
#: Returns within `min_range` do not count: organised clouds hold a zero for every missing return.
MAX_OUT_OF_RANGE_SHARE = 0.1


class Options(StageOptions):
    """Which scans to load and how many points a scan may hold (the pipeline's `input` section).

    path: a raw drive, a raw date folder, a raw base, an odometry base or sequence folder, a folder
        of .bin files, or a base folder with any of these under it.
    kind: "auto" recognises the layout; "raw", "odometry" or "bin" forces it.
    sequences: drive names or sequence ids to take (all when None).
    first_frame / last_frame / step: frame range, last_frame inclusive (None = to the end).
    max_points: a scan with more points is refused as bad input.
    max_range: points farther than this from the sensor (metres) are dropped at load, with a note.
    min_range: points closer than this (metres) are dropped at load, with a note: not returns
        (`MIN_RANGE_M`); 0 keeps them.
    max_out_of_range_share: a scan with a larger share of points beyond `max_range` is refused as
        bad input.
    """

    path: Path | None = None
    kind: Literal["auto", "raw", "odometry", "bin"] = "auto"
    sequences: list[str] | None = None
    first_frame: int = Field(0, ge=0)
    last_frame: int | None = Field(None, ge=0)
    step: int = Field(1, ge=1)
    max_points: int = Field(MAX_POINTS, ge=1)
    max_range: float = Field(MAX_RANGE_M, gt=0)
    min_range: float = Field(MIN_RANGE_M, ge=0)
    max_out_of_range_share: float = Field(MAX_OUT_OF_RANGE_SHARE, ge=0, le=1)

    @field_validator("path", mode="before")
    @classmethod
    def _not_empty(cls, value: object) -> object:
        return refuse_empty_path(value, "input.path")

    @field_validator("sequences", mode="before")
    @classmethod
    def _names_as_text(cls, value: object) -> object:
        """Sequence names as text, one name or a list: YAML reads `[00, 05]` as the integers 0 and
        5, which name the same sequences (digit-only names match without leading zeros)."""
        if isinstance(value, (str, int)) and not isinstance(value, bool):
            value = [value]
        if isinstance(value, list):
            return [str(item) if isinstance(item, int) and not isinstance(item, bool) else item for item in value]
        return value

    @model_validator(mode="after")
    def _check_range(self) -> "Options":
        if self.last_frame is not None and self.last_frame < self.first_frame:
            raise ValueError(
                f"input.last_frame ({self.last_frame}) is before input.first_frame ({self.first_frame})"
            )
        if self.min_range >= self.max_range:
            raise ValueError(f"input.min_range ({self.min_range:g} m) must be below input.max_range "
                             f"({self.max_range:g} m): no point would be kept")
        return self

    def frame_range(self) -> range | None:
        """The selected frame indices as a range, or None for all frames."""
        if self.first_frame == 0 and self.last_frame is None and self.step == 1:
            return None
        stop = (self.last_frame + 1) if self.last_frame is not None else OPEN_END
        return range(self.first_frame, stop, self.step)


# --- reading ------------------------------------------------------------------------------


def read_scan(path: str | Path, max_points: int = MAX_POINTS) -> np.ndarray:
    """Read and validate one KITTI Velodyne .bin scan.

    Returns:
        (N, 4) float32 x, y, z (metres, sensor frame) and reflectance.

    Raises:
        InputError naming the file: missing, empty, size not a multiple of 16 bytes, more than
        `max_points` points, a file of another point-cloud format (`OTHER_FORMAT_MAGIC`: .npy,
        .npz, PLY, PCD, LAS), non-finite values, or negative reflectances (another layout than
        KITTI's: `check_reflectance`).
    """
    return _read_fingerprinted_scan(path, max_points)[0]


def _read_fingerprinted_scan(path: str | Path, max_points: int) -> tuple[np.ndarray, str, str]:
    """`read_scan`, the scan's `source_fingerprint` from the status of the very file read, taken
    before its bytes (a scan replaced, renamed over, while it is read keeps its old inode open here,
    and one written in place after the status gets a newer time than the recorded one, so a rerun
    redoes it either way), and the `content_digest` of the bytes read."""
    path = Path(path)
    if path.is_dir():
        raise InputError("load", str(path), "is a folder, not a scan (give a .bin file; `discover` lists a folder's scans)")
    real = os.path.realpath(path)
    try:
        if not stat_module.S_ISREG(os.stat(real).st_mode):  # a FIFO would block the open for ever
            raise InputError("load", str(path), "not a regular file, so not a scan")
        with open(real, "rb") as scan:
            status = os.fstat(scan.fileno())
            size = status.st_size
            _check_not_another_format(path, scan.read(max(len(magic) for magic, _ in OTHER_FORMAT_MAGIC)))
            scan.seek(0)
            _check_scan_size(path, size, max_points)
            values = np.fromfile(scan, dtype=np.float32, count=4 * (size // POINT_BYTES))
    except OSError as error:
        raise InputError("load", str(path), f"cannot read scan ({error.strerror})") from None
    if len(values) * 4 != size:  # cut short while it was read
        raise InputError("load", str(path), f"{len(values) * 4} of its {size} bytes read (the file changed while "
                                            "it was read)")
    points = values.reshape(-1, 4)
    bad = ~np.isfinite(points).all(axis=1)
    if bad.any():
        raise InputError("load", str(path), f"{counted(int(bad.sum()), 'point')} with NaN or infinite values "
                                            f"(first at point {int(np.argmax(bad))})")
    check_reflectance(points, str(path))
    return points, fingerprint_of(real, status), bytes_digest(values.data)


def _check_not_another_format(path: Path, head: bytes) -> None:
    """InputError naming `path` when its first bytes `head` are those of another point-cloud format."""
    for magic, name in OTHER_FORMAT_MAGIC:
        if head.startswith(magic):
            raise InputError("load", str(path), f"is {name}, not a KITTI scan ({LAYOUT_HINT})")


def _check_scan_size(path: Path, size: int, max_points: int) -> None:
    """InputError naming `path` when a scan of `size` bytes cannot be a KITTI scan, or holds more
    than `max_points` points."""
    if size == 0:
        raise InputError("load", str(path), "empty scan (0 bytes)")
    if size % POINT_BYTES:
        raise InputError("load", str(path), f"size {size} bytes is not a multiple of {POINT_BYTES} "
                                            "(truncated or not a KITTI .bin scan)")
    count = size // POINT_BYTES
    if count > max_points:
        raise InputError("load", str(path), f"{count} points exceeds the limit of {max_points} "
                                            "(input.max_points)")


def check_reflectance(points: np.ndarray, source: str) -> None:
    """Raise InputError naming `source` when more than MAX_NEGATIVE_REFLECTANCE_SHARE of the (N, 4)
    points have a negative reflectance: another layout read as x, y, z, reflectance."""
    negative = int(np.count_nonzero(points[:, 3] < 0))
    if negative > MAX_NEGATIVE_REFLECTANCE_SHARE * len(points):
        raise InputError("load", source, f"{negative} of {len(points)} points have a negative reflectance: "
                                         f"{LAYOUT_HINT}, and no LiDAR returns a negative intensity "
                                         "(is it x, y, z only, 12 bytes a point, or another layout?)")


def drop_out_of_range(points: np.ndarray, source: str, max_range: float = MAX_RANGE_M,
                      max_share: float = MAX_OUT_OF_RANGE_SHARE,
                      min_range: float = MIN_RANGE_M) -> tuple[np.ndarray, int, int, np.ndarray | None]:
    """Drop the points farther than `max_range` metres from the sensor, and those closer than
    `min_range` (not returns: `MIN_RANGE_M`), keeping the others' order.

    Args:
        points: (N, 4) float32 x, y, z, reflectance, finite, sensor frame, metres.
        source: the file they came from (for the error).

    Returns:
        (the kept points (M, 4), the number dropped beyond `max_range`, the number dropped within
        `min_range`, (M,) int64 row of each kept point among `points`, or None when all are kept).

    Raises:
        InputError naming `source` when more than `max_share` of the points are beyond
        `max_range`: the file is not a scan (points within `min_range` do not count: an organised
        cloud holds a zero for every missing return).
    """
    squared = np.einsum("ij,ij->i", points[:, :3], points[:, :3], dtype=np.float64)
    far, near = squared > max_range**2, squared < min_range**2
    far_count = int(far.sum())
    if far_count > max_share * len(points):
        raise InputError("load", source, f"{far_count} of {len(points)} points are beyond {max_range:g} m, more "
                                         f"than the {max_share:.0%} input.max_out_of_range_share allows: not a "
                                         f"LiDAR scan in its sensor's frame{_units_hint(squared, max_range, max_share)} "
                                         f"({LAYOUT_HINT}; float64 values or "
                                         "another layout read as such are garbage; points of a map or world frame lie "
                                         "far from the sensor). To crop scans to a shorter input.max_range, raise "
                                         "input.max_out_of_range_share too")
    dropped = far | near
    if not dropped.any():
        return points, far_count, 0, None
    rows = np.flatnonzero(~dropped)
    return points[rows], far_count, int(near.sum()), rows


def frame_lines(path: Path) -> int:
    """The non-empty lines of a metadata file that holds one per frame (times, timestamps, poses),
    frame 0 first; 0 when it is missing or unreadable."""
    try:
        with Path(path).open("rb") as lines:
            return sum(1 for line in lines if line.strip())
    except OSError:
        return 0


def _bad_line(path: Path, parse, frames: list[int] | None = None) -> str | None:
    """"line N: 'text'" for the first line of `path` that `parse` (str -> anything) refuses, among
    the lines of `frames` (0-based; None: every line), or None."""
    try:
        lines = path.read_text(errors="replace").splitlines(keepends=True)
    except OSError:
        return None
    for number, line in enumerate(lines, 1):
        if frames is not None and number - 1 not in frames:
            continue
        try:
            parse(line)
        except ValueError:
            return f"line {number}: {line.strip()[:60]!r}"
    return None


def _frame_lines(path: str | Path, frames: list[int] | None) -> list[str]:
    """The lines of a file that holds one per frame, those of `frames` only (all for None), so a
    bad line fails only its own frame: pykitti parsed every line for any frame. IndexError when a
    frame has no line."""
    every = _file_lines(path)
    return list(every) if frames is None else [every[i] for i in frames]


def _file_lines(path: str | Path) -> tuple[str, ...]:
    """Every line of a text file, line ends kept (`readlines`); OSError when it cannot be read.

    Read once per version of the file (its size and modification time), however many frames ask:
    a rerun compares every finished frame's recorded timestamp and pose with the sequence's
    (`frame_metadata`), and each of those reads the same times and poses files."""
    # the inode and change time too: a rewrite of the same size whose time was set back (cp -p,
    # rsync -t) or a coarse clock keeps size and mtime
    return _lines_of_version(str(path), *_version_of(path))


@functools.lru_cache(maxsize=16)
def _lines_of_version(path: str, size: int, mtime_ns: int, inode: int, ctime_ns: int) -> tuple[str, ...]:
    with open(path, encoding="utf-8-sig") as lines:  # a byte-order mark (a Windows editor's) is not text
        return tuple(lines.readlines())


def _raw_timestamp(line: str) -> dt.datetime:
    """A KITTI raw timestamp line ("YYYY-MM-DD HH:MM:SS.nnnnnnnnn") to the microsecond, as pykitti.raw
    reads it (its `line[:-4]` drops the newline and the last three digits), whatever ends the line:
    pykitti's slice took a digit more from a last line without a newline, and failed on CRLF."""
    text = line.strip()
    whole, _, fraction = text.partition(".")
    if fraction and not fraction.isdigit():
        raise ValueError(f"not a KITTI timestamp: {text[:40]!r}")
    return dt.datetime.strptime(whole, "%Y-%m-%d %H:%M:%S") + dt.timedelta(microseconds=int(fraction[:6].ljust(6, "0")))


#: The largest time in seconds an odometry times.txt may give (about 31,700 years): a bigger or
#: non-finite one overflowed Python's timedelta into a traceback (a trial).
MAX_SECONDS = 1e12


def seconds_of(line: str) -> float:
    """A times.txt line as seconds: a finite number of at most `MAX_SECONDS`; ValueError otherwise."""
    value = float(line)
    if not abs(value) <= MAX_SECONDS:  # NaN too
        raise ValueError(f"not a time in seconds: {line.strip()[:40]!r}")
    return value


#: The entries pykitti reads from each calibration file, with their sizes, by dataset.
CALIBRATION_ENTRIES: dict[str, dict[str, dict[str, int]]] = {
    "raw": {"calib_imu_to_velo.txt": {"R": 9, "T": 3}, "calib_velo_to_cam.txt": {"R": 9, "T": 3},
            "calib_cam_to_cam.txt": {**{f"P_rect_0{i}": 12 for i in range(4)},
                                     **{f"R_rect_0{i}": 9 for i in range(4)}}},
    "odometry": {"calib.txt": {**{f"P{i}": 12 for i in range(4)}, "Tr": 12}},
}


def _calibration_problem(folder: Path, entries: dict[str, dict[str, int]]) -> tuple[Path, str] | None:
    """The first calibration file in `folder` (of `entries`: file name -> entry -> numbers) that
    pykitti cannot read as it needs, with what is wrong; None when every file reads."""
    for name, sizes in entries.items():
        path = folder / name
        if path.read_bytes()[:3] == "\ufeff".encode():  # pykitti reads the first name with it: "missing"
            return path, ("starts with a byte-order mark (saved by a Windows editor?), which pykitti reads as part "
                          "of the first entry's name: save it without one")
        numbers: dict[str, int | None] = {}
        for number, line in enumerate(path.read_text(errors="replace").splitlines(), 1):
            if line.strip() and ":" not in line:
                return path, f"line {number} is not 'name: values': {line[:60]!r}"
            key, _, values = line.partition(":")
            try:
                numbers[key] = len([float(value) for value in values.split()])
            except ValueError:
                numbers[key] = None
        for key, size in sizes.items():
            if key not in numbers:
                return path, f"calibration entry {key!r} is missing"
            if numbers[key] != size:
                found = "not numbers" if numbers[key] is None else f"{numbers[key]} numbers"
                return path, f"calibration entry {key!r} holds {found}, not {size}"
    return None


def missing_metadata_error(ref: FrameRef, missing: Path | str, also: tuple[Path | str, ...] = ()) -> InputError:
    """The error of loading `ref` while its metadata file `missing` (a calibration or timestamps
    file) is not there or cannot be read; `also`: others of its files known missing too."""
    others = f"; missing too: {', '.join(map(str, also))}" if also else ""
    return InputError("load", str(missing), f"missing or unreadable {ref.dataset} metadata file "
                                            f"needed for {ref.source}{others} ({MISSING_METADATA_HINT})")


def missing_timestamp_error(ref: FrameRef, timestamps: Path | str) -> InputError:
    """The error of loading `ref` while its timestamps file holds no line for it (a scan copied in
    before its line, in a growing dataset)."""
    return InputError("load", str(timestamps), f"fewer entries than frames: nothing for frame {ref.index} "
                                               f"({ref.source})")


def _metadata_error(ref: FrameRef, error: Exception, calib_folder: Path, timestamps: Path) -> InputError:
    """Turn what pykitti raised while reading `ref`'s metadata into an InputError naming the file."""
    if isinstance(error, ValueError):  # a line that does not parse: a timestamp's?
        parse = _raw_timestamp if ref.dataset == "raw" else seconds_of
        bad = _bad_line(timestamps, parse, [0, ref.index] if ref.dataset == "raw" else [ref.index])
        if bad:
            return InputError("load", str(timestamps), f"not a timestamp at {bad} (needed for {ref.source})")
    missing = getattr(error, "filename", None)
    if missing:
        return missing_metadata_error(ref, missing)
    if isinstance(error, (ValueError, KeyError)):  # a calibration file: which, and what is wrong
        problem = _calibration_problem(calib_folder, CALIBRATION_ENTRIES[ref.dataset])
        if problem:
            return InputError("load", str(problem[0]), f"{problem[1]} (needed for {ref.source})")
        return InputError("load", str(calib_folder), f"cannot read the calibration ({type(error).__name__}: "
                                                     f"{error}), needed for {ref.source}")
    if isinstance(error, IndexError):
        return missing_timestamp_error(ref, timestamps)
    return InputError("load", ref.source, f"bad {ref.dataset} metadata ({type(error).__name__}: {error})")


def _raw_metadata(ref: FrameRef) -> tuple[float | None, dict[str, np.ndarray], np.ndarray | None, str | None]:
    """Timestamp (s since the drive's first frame), calibration, T_world_velodyne and a note
    about the pose (`_raw_pose`) of a raw scan.

    Calibration (BASE/DATE/calib_*.txt) and oxts/timestamps.txt are required; the pose is None
    when the drive has no OXTS packet for this scan, or a bad one (with the note).
    """
    drive_dir = Path(ref.base, ref.date, ref.sequence)
    try:
        # metadata files hold a line per frame of the whole drive: taken by the frame's number (its
        # file name), not by its place among the scans present (a partial download or mirror)
        # and from the drive's own folder: pykitti reads a `_sync` drive unless told (an `_extract`
        # drive's frames were given the sync drive's times, or failed naming a folder not there)
        kind = DRIVE_PATTERN.match(ref.sequence).group(3)  # type: ignore[union-attr]
        data = _raw_metadata_reader()(ref.base, ref.date, ref.drive, frames=[0, ref.index], dataset=kind)
    except (OSError, KeyError, ValueError, IndexError) as error:
        raise _metadata_error(ref, error, Path(ref.base, ref.date), drive_dir / "oxts" / "timestamps.txt") from None
    timestamp = (data.timestamps[1] - data.timestamps[0]).total_seconds()
    calib = {name: np.array(getattr(data.calib, name), dtype=np.float64)  # copies: the parse is shared
             for name in ("T_cam0_velo", "T_cam2_velo", "T_velo_imu", "P_rect_20", "K_cam2")}
    return (timestamp, calib, *_raw_pose(drive_dir / "oxts" / "data", ref.index, calib["T_velo_imu"]))


#: Calibrations parsed by pykitti, by the versions of the files they were read from
#: (`_cached_calibration`); a few dozen date folders or sequences at most in one run.
_CALIBRATIONS: dict[tuple, object] = {}
_CALIBRATIONS_KEPT = 64


def _cached_calibration(reader: object, files: list[Path], load: Callable[[], None]) -> None:
    """Set `reader.calib` as pykitti's `load` parses it from `files`, parsed once per version of the
    files (size, modification and change time, inode), not once per frame: a rerun checks every
    finished frame's metadata, and parsing the calibration was most of that (a trial at scale).
    A file that cannot be stat'ed is left to `load`, which raises as pykitti does."""
    try:
        key = (type(reader).__name__, *((str(path), *_version_of(path)) for path in files))
    except OSError:
        load()
        return
    if key not in _CALIBRATIONS:
        load()
        if len(_CALIBRATIONS) >= _CALIBRATIONS_KEPT:
            _CALIBRATIONS.clear()
        _CALIBRATIONS[key] = reader.calib  # type: ignore[attr-defined]
    reader.calib = _CALIBRATIONS[key]  # type: ignore[attr-defined]


def _version_of(path: Path) -> tuple[int, int, int, int]:
    """What tells one version of a file from another without reading it (as `_file_lines` keys)."""
    stat = Path(path).stat()
    return stat.st_size, stat.st_mtime_ns, stat.st_ino, stat.st_ctime_ns


def _no_file_lists(reader: object) -> None:
    """What pykitti's readers get instead of their file lists: none. Each listed every scan, image
    and packet of the drive or sequence for every frame (a glob of six folders, whose cost grows
    with the drive); the scan is read by its own path (`FrameRef.source`) and the packets by name
    (`_raw_pose`)."""
    for sensor in ("oxts", "cam0", "cam1", "cam2", "cam3", "velo"):
        setattr(reader, f"{sensor}_files", [])


@functools.cache
def _raw_metadata_reader() -> type:
    """pykitti.raw without its OXTS packets: `_raw_pose` reads the frame's own packet by name,
    where pykitti parsed two more by their place in the folder (every packet of the drive, for a
    frame past a missing one). Calibration and timestamps are read as pykitti reads them."""
    import pykitti

    class RawMetadata(pykitti.raw):
        def _get_file_lists(self) -> None:
            _no_file_lists(self)

        def _load_calib(self) -> None:
            files = [Path(self.calib_path, name) for name in CALIBRATION_ENTRIES["raw"]]
            _cached_calibration(self, files, super()._load_calib)

        def _load_oxts(self) -> None:  # pykitti's loader of the packets, called by its __init__
            self.oxts = []

        def _load_timestamps(self) -> None:  # the frames' own lines, parsed as pykitti parses them
            lines = _frame_lines(Path(self.data_path, "oxts", "timestamps.txt"), self.frames)
            self.timestamps = [_raw_timestamp(line) for line in lines]

    return RawMetadata


def _raw_pose(oxts_dir: Path, index: int, velo_to_imu: np.ndarray) -> tuple[np.ndarray | None, str | None]:
    """T_world_velodyne of raw frame `index` from its own OXTS packet (oxts/data/NNNNNNNNNN.txt,
    read by name: pykitti picks packets by their place in the folder, which is another frame's
    when a packet is missing), in the world frame pykitti puts at the first packet it reads:
    frame 0's (the first packet present when frame 0 has none). Returns (the pose, None), or
    (None, a note naming the packet) when the frame has no packet or a packet needed is not 30
    numbers on one line: the pose is metadata the frame's densification does not
    use, so a bad packet leaves it unknown rather than failing the frame (or, frame 0's, every frame).
    """
    from pykitti.utils import load_oxts_packets_and_poses

    own = oxts_dir / f"{index:010d}.txt"
    origin = _origin_packet(oxts_dir)
    if not own.is_file():
        return None, f"pose unknown: no OXTS packet {own}"
    if origin is None:
        return None, f"pose unknown: no OXTS packet in {oxts_dir}"
    try:
        for packet in dict.fromkeys((origin, own)):
            numbers = len(packet.read_text(errors="replace").split())
            if numbers != OXTS_NUMBERS:
                return None, f"pose unknown: {packet} is not an OXTS packet ({numbers} numbers, not {OXTS_NUMBERS})"
        first, this = load_oxts_packets_and_poses([str(origin), str(own)])
        return this.T_w_imu @ np.linalg.inv(velo_to_imu), None  # T_w_velo = T_w_imu @ T_imu_velo
    except OSError as error:  # unreadable, or gone since it was listed
        return None, f"pose unknown: an OXTS packet of {oxts_dir} cannot be read ({error.strerror or error})"
    except (ValueError, TypeError, IndexError) as error:  # 30 words, not all numbers; a singular calibration
        return None, f"pose unknown: an OXTS packet of {oxts_dir} does not read ({type(error).__name__}: {error})"


def _origin_packet(oxts_dir: Path) -> Path | None:
    """The packet whose pose is a raw drive's world origin: frame 0's, else the first present
    (None when the folder holds none). Listed once per version of the folder, not per frame: a
    drive without frame 0's packet listed its whole folder for every frame."""
    origin = oxts_dir / f"{0:010d}.txt"
    if origin.is_file():
        return origin
    try:
        version = oxts_dir.stat().st_mtime_ns
    except OSError:
        return None
    return _first_packet(str(oxts_dir), version)


@functools.lru_cache(maxsize=16)
def _first_packet(oxts_dir: str, mtime_ns: int) -> Path | None:
    return next(iter(sorted(Path(oxts_dir).glob("*.txt"))), None)


@functools.cache
def _odometry_metadata_reader() -> type:
    """pykitti.odometry reading only the frames' own lines of times.txt (`_frame_lines`)."""
    import pykitti

    class OdometryMetadata(pykitti.odometry):
        def _get_file_lists(self) -> None:
            _no_file_lists(self)

        def _load_calib(self) -> None:
            _cached_calibration(self, [Path(self.sequence_path, "calib.txt")], super()._load_calib)

        def _load_timestamps(self) -> None:
            lines = _frame_lines(Path(self.sequence_path, "times.txt"), self.frames)
            self.timestamps = [dt.timedelta(seconds=seconds_of(line)) for line in lines]

        def _load_poses(self) -> None:  # the frames' own lines; a bad one leaves the pose unknown
            path = odometry_poses_file(Path(self.pose_path).parent, self.sequence)  # pose_path: BASE/poses
            self.poses, self.pose_note = [], None
            if path is None:
                return
            try:
                lines: Sequence[str] = _file_lines(path)  # each frame's line, its end kept
            except UnicodeDecodeError:
                lines = path.read_text(errors="replace").splitlines()
            for frame in self.frames:
                numbers = lines[frame].split() if frame < len(lines) else []
                try:
                    values = np.array([float(number) for number in numbers])
                except ValueError:
                    values = np.array([])
                if values.shape != (12,) or not np.isfinite(values).all():
                    self.poses = []
                    self.pose_note = (f"pose unknown: {path} line {frame + 1} is not 12 numbers (a 3 x 4 "
                                      f"T_world_cam0): {lines[frame].rstrip()[:60]!r}" if frame < len(lines) else
                                      f"pose unknown: {path} has no line {frame + 1}")
                    return
                self.poses.append(np.vstack([values.reshape(3, 4), [0.0, 0.0, 0.0, 1.0]]))

    return OdometryMetadata


def odometry_poses_file(base: Path, sequence: str) -> Path | None:
    """The file an odometry sequence's poses (a 3 x 4 T_world_cam0 per line and frame) are read
    from: KITTI's BASE/poses/NN.txt, else SemanticKITTI's BASE/sequences/NN/poses.txt (the same
    form); None when the sequence has neither."""
    for path in (Path(base, "poses", f"{sequence}.txt"), Path(base, "sequences", sequence, "poses.txt")):
        if path.is_file():
            return path
    return None


def _odometry_metadata(ref: FrameRef) -> tuple[float | None, dict[str, np.ndarray], np.ndarray | None, str | None]:
    """Timestamp (times.txt, s), calibration, T_world_velodyne and a note about the pose of an
    odometry scan.

    calib.txt and times.txt (KITTI's data_odometry_calib.zip) are required; the pose comes from
    `odometry_poses_file` (T_world_cam0) combined with Tr, and is None when there is none, or
    (with the note naming it) holds no 12 numbers on the frame's line.
    """
    sequence_dir = Path(ref.base, "sequences", ref.sequence)
    reader = _odometry_metadata_reader()
    try:
        # the frame's own lines, by its number: frame 0's is no part of another frame's time or pose
        # (a bad line 1 of poses/NN.txt left every frame's pose unknown)
        data = reader(ref.base, ref.sequence, frames=[ref.index])
    except (OSError, KeyError, ValueError, IndexError) as error:
        raise _metadata_error(ref, error, sequence_dir, sequence_dir / "times.txt") from None
    timestamp = data.timestamps[0].total_seconds()
    calib = {name: np.array(getattr(data.calib, name), dtype=np.float64)  # copies: the parse is shared
             for name in ("T_cam0_velo", "T_cam2_velo", "P_rect_20", "K_cam2")}
    poses = data.poses
    with np.errstate(over="ignore", invalid="ignore"):  # a product that overflows: unknown, said by `_metadata`
        pose = poses[0] @ calib["T_cam0_velo"] if len(poses) == 1 else None  # T_w_velo
    return timestamp, calib, pose, data.pose_note


def run(ref: FrameRef, options: Options = Options()) -> Frame:
    """The load stage: read the scan of `ref` with its timestamp, calibration, pose and rings.

    Reads: the files `ref` names. Adds (a new `Frame`): points (N, 4) float32, dataset, sequence,
    index, source, timestamp in seconds (raw: since the drive's first frame; odometry: times.txt),
    calib (matrices by pykitti name), pose (4, 4) T_world_velodyne when the dataset provides one
    (raw: oxts; odometry: `odometry_poses_file`; None, with a note naming the file, when it is malformed),
    rings (`stages.ring_snap.scan_rings`). Points beyond `options.max_range`, and within
    `options.min_range` of the sensor, are dropped first (`drop_out_of_range`), then points that
    repeat an earlier one's x, y, z (`stages.repeats`), each with a note saying how many.

    Raises:
        InputError naming the file that is bad or missing, or not a scan.
        TypeError: `ref` is not a FrameRef (`discover` finds them), or `options` not this stage's.
    """
    if not isinstance(ref, FrameRef):
        raise TypeError(f"load.run takes a stages.load.FrameRef (stages.load.discover finds them), got "
                        f"{type(ref).__qualname__} {ref!r:.80}; for one scan file, stages.load.scan_points reads "
                        "its points and frame_from_points makes a Frame of them")
    options = stage_options(options, Options, "load")
    points, fingerprint, digest = _read_fingerprinted_scan(ref.source, options.max_points)
    timestamp, calib, pose, pose_note = _metadata(ref)
    # read_scan checked the points as frame_from_points would (and they are this frame's own)
    frame = _frame(points, ref.source, ref.dataset, ref.sequence, ref.index, **_range_limits(options),
                   timestamp=timestamp, source=ref.source, source_fingerprint=fingerprint, source_digest=digest,
                   calib=calib, pose=pose)
    return frame.with_note(pose_note) if pose_note else frame


def _metadata(ref: FrameRef) -> tuple[float | None, dict[str, np.ndarray], np.ndarray | None, str | None]:
    """Timestamp, calibration, pose and pose note of `ref`'s dataset (none for a plain .bin folder).
    A pose with a non-finite value (a NaN in an OXTS packet or in calib.txt's Tr) is unknown, with
    a note: it was written into the files' records as NaN, which strict JSON readers refuse (a trial)."""
    if ref.dataset == "raw":
        timestamp, calib, pose, note = _raw_metadata(ref)
        made_from = f"the OXTS packets of {Path(ref.base, ref.date, ref.sequence, 'oxts', 'data')} and the calibration"
    elif ref.dataset == "odometry":
        timestamp, calib, pose, note = _odometry_metadata(ref)
        made_from = (f"{odometry_poses_file(Path(ref.base), ref.sequence)} and "
                     f"{Path(ref.base, 'sequences', ref.sequence, 'calib.txt')}")
    else:
        return None, {}, None, None
    if pose is not None and not np.isfinite(pose).all():
        pose, note = None, f"pose unknown: {made_from} give non-finite values for it"
    return timestamp, calib, pose, note


def frame_metadata(ref: FrameRef) -> tuple[float | None, np.ndarray | None]:
    """The timestamp (s) and pose (4, 4 T_world_velodyne) `run` would give `ref`'s frame, without
    reading its scan: what a rerun compares with those a finished frame recorded (a corrected
    times.txt, oxts/ or poses/ file). (None, None) for a plain .bin folder.

    Raises:
        InputError naming the metadata file that is bad or missing, as `run` does.
    """
    timestamp, pose, _ = frame_metadata_noted(ref)
    return timestamp, pose


def frame_metadata_noted(ref: FrameRef) -> tuple[float | None, np.ndarray | None, str | None]:
    """`frame_metadata` with the note `run` adds when the pose cannot be read ("pose unknown: ...",
    naming the file: a damaged poses line, a missing or bad OXTS packet), None when there is none.
    A pose that is None without a note is one the dataset does not give (no poses file)."""
    timestamp, _, pose, note = _metadata(ref)
    return timestamp, pose, note


#: Units a scan's coordinates are sometimes given in, by how many of them make a metre, smallest first.
SMALLER_UNITS = {"decimetres": 10.0, "centimetres": 100.0, "millimetres": 1000.0}


def _units_hint(squared: np.ndarray, max_range: float, max_share: float) -> str:
    """", or its coordinates are in a unit smaller than metres ..." when the scan whose points'
    squared ranges are `squared` would pass the range check read in one of `SMALLER_UNITS` (the
    first, the fewest per metre, that does: a scan in millimetres that reaches only 20 m passes
    read in centimetres too, and is named so); "" otherwise."""
    for unit, per_metre in SMALLER_UNITS.items():
        if (squared > (max_range * per_metre) ** 2).mean() <= max_share:  # the share that would stay too far
            return (f", or its coordinates are in a unit smaller than metres: divided by {per_metre:g} (in {unit}) "
                    f"they would lie within {max_range:g} m; kitti-pu takes metres, as KITTI's scans are")
    return ""


def scan_points(source: str | Path, options: Options | Mapping[str, Any] = Options()) -> np.ndarray:
    """A scan's points as `run` loads them, without the frame: read (`read_scan`), checked, and
    with the points out of range and the repeated ones dropped (`frame_from_points`); for tools that take whole scans
    (the 16-to-64-beam evaluation, fine-tuning). `options`: the input section, or a mapping of its
    keys, as `run` takes it.

    Returns:
        (N, 4) float32 x, y, z, reflectance, sensor frame, metres, in stored order.

    Raises:
        InputError naming the file, as `run` does.
    """
    options = stage_options(options, Options, "load")
    return frame_from_points(read_scan(source, options.max_points), source=str(source),
                             **_range_limits(options)).points


def _range_limits(section: Options) -> dict[str, float]:
    """The arguments of `frame_from_points` that the input section sets: what load keeps of a scan."""
    return {"max_range": section.max_range, "max_out_of_range_share": section.max_out_of_range_share,
            "min_range": section.min_range}


def frame_from_points(points: np.ndarray, dataset: str = "bin", sequence: str = "points", index: int = 0,
                      max_range: float = MAX_RANGE_M, max_out_of_range_share: float = MAX_OUT_OF_RANGE_SHARE,
                      min_range: float = MIN_RANGE_M, **provenance: object) -> Frame:
    """A frame from a scan already in memory, checked as `run` checks a scan from a file: its
    points finite, those beyond `max_range` metres or within `min_range` of the sensor dropped
    with a note (the scan refused when more than `max_out_of_range_share` of them lie beyond
    `max_range`: `drop_out_of_range`), and so are points repeating an earlier one's x, y, z
    (`stages.repeats`); its rings read from the point order of the rest.

    Args:
        points: (N, 4) float32 x, y, z, reflectance in the sensor frame (metres), in their stored
            order, N >= 1 (other float types and integers are converted; integers with a note).
        dataset, sequence, index: the frame's name (`Frame.key`).
        provenance: further `Frame` fields (`PROVENANCE_FIELDS`: timestamp, source, calib, pose, ...).

    Raises:
        InputError("load", source, reason), naming `provenance["source"]` or "points in memory",
        for a wrong shape, no points, a NaN, infinite or float32-overflowing value, negative
        reflectances (another layout: `check_reflectance`), a scan mostly out of range, or a name
        that does not map onto the output layout (`stages.frame.check_frame_name`).
    """
    source = str(provenance.get("source") or "points in memory")
    given = np.asarray(points)
    if given.dtype.kind not in "fiu":  # booleans, strings, objects: not coordinates
        raise InputError("load", source, f"expected numbers (x, y, z, reflectance), got an array of {given.dtype}")
    with np.errstate(over="ignore"):
        points = np.array(given, dtype=np.float32)  # a copy: the frame must not change with the caller's array
    if points.ndim != 2 or points.shape[1] != 4:
        raise InputError("load", source, f"expected an (N, 4) array of x, y, z, reflectance, got shape {points.shape}")
    if not len(points):
        raise InputError("load", source, "no points")
    bad = ~np.isfinite(points).all(axis=1)
    if bad.any():
        what = "values beyond float32's range" if np.isfinite(given[bad]).all() else "NaN or infinite values"
        raise InputError("load", source, f"{counted(int(bad.sum()), 'point')} with {what} "
                                         f"(first at point {int(np.argmax(bad))})")
    check_reflectance(points, source)
    _check_provenance(provenance, source)
    frame = _frame(points, source, dataset, sequence, index, max_range, max_out_of_range_share, min_range,
                   **provenance)
    if given.dtype.kind in "iu":  # a scan's points are never whole metres: rounded somewhere before this
        # (a trial's scan as int32 lost 97% of its points as repeats, and the notes named only that)
        frame = frame.with_note(f"the points came as integers ({given.dtype}): whole metres at best, so many "
                                "repeat each other; give the scan's float32 values as read, before any rounding")
    return frame


#: The `Frame` fields `frame_from_points` takes besides the name and the range limits.
PROVENANCE_FIELDS = ("timestamp", "source", "source_fingerprint", "source_digest", "calib", "pose")


def _check_provenance(provenance: Mapping[str, object], source: str) -> None:
    """InputError unless every key names a provenance field of a `Frame` (`PROVENANCE_FIELDS`;
    another was a bare TypeError of the Frame's constructor), a timestamp given is a finite number
    of seconds and a pose a finite (4, 4) matrix: what the files record of them (a NaN was written
    as "NaN", and a timestamp "abc" failed only at the write stage)."""
    unknown = sorted(set(provenance) - set(PROVENANCE_FIELDS))
    if unknown:
        raise InputError("load", source, f"unknown frame field(s) {', '.join(unknown)}; frame_from_points takes "
                                         f"{', '.join(PROVENANCE_FIELDS)} besides the name")
    timestamp, pose = provenance.get("timestamp"), provenance.get("pose")
    if timestamp is not None and (isinstance(timestamp, bool) or not isinstance(timestamp, numbers.Real)
                                  or not math.isfinite(timestamp)):
        raise InputError("load", source, f"timestamp must be a finite number of seconds (or None), got {timestamp!r}")
    if pose is not None:
        matrix = np.asarray(pose)
        if matrix.shape != (4, 4) or matrix.dtype.kind not in "fiu" or not np.isfinite(matrix).all():
            raise InputError("load", source, "pose must be a finite (4, 4) matrix (the sensor's pose in the world "
                                             f"frame) or None, got {matrix.dtype} {matrix.shape}")


#: How the note of a frame read from a scan kitti-pu densified begins (`densified_by_kitti_pu`).
DENSIFIED_NOTE = "load: a scan kitti-pu densified"


def read_from_densified_scan(frame: Frame) -> bool:
    """Whether `frame` was read from a scan kitti-pu densified (its load note says so): why it has
    no rings, which the snap and fill stages' notes then say."""
    return any(note.startswith(DENSIFIED_NOTE) for note in frame.notes)


def densified_by_kitti_pu(source: object) -> Path | None:
    """The `kitti` format's sidecar of a scan file when there is one (`stages.write_kitti`): the
    scan is then kitti-pu's own output, its generated points after the scan's returns. Their order
    can still pass for rings (the demo drive's densified scans read as 256 rings, and snapping
    dropped 95% of the new points), so a second pass reads no rings from such a scan.

    Args:
        source: the scan's path (a `Frame`'s source), or None for points in memory.

    Returns:
        The sidecar's path, or None.
    """
    if not source:
        return None
    sidecar = sidecar_path(Path(str(source)))
    return sidecar if sidecar.is_file() else None


def _frame(points: np.ndarray, named: str, dataset: str, sequence: str, index: int, max_range: float,
           max_out_of_range_share: float, min_range: float, **provenance: object) -> Frame:
    """`frame_from_points` for (N, 4) float32 points of the caller's own (not shared), N >= 1,
    finite and with their reflectances checked, as `read_scan` returns them; `named` is what the
    errors name (the source file, or "points in memory")."""
    try:
        check_frame_name(dataset, sequence, index)
    except ValueError as error:
        raise InputError("load", named, str(error)) from None
    points, far, near, rows = drop_out_of_range(points, named, max_range, max_out_of_range_share, min_range)
    if not len(points):
        raise InputError("load", named, f"no points between {min_range:g} and {max_range:g} m of the sensor")
    repeated = repeated_rows(points[:, :3])
    repeats = int(np.count_nonzero(repeated))
    if repeats:  # each upsampled once, as one point (stages.repeats says why)
        kept = np.flatnonzero(~repeated)
        points, rows = points[kept], (kept if rows is None else rows[kept])
    sidecar = densified_by_kitti_pu(provenance.get("source"))
    frame = Frame(points=points, dataset=dataset, sequence=sequence, index=index,
                  rings=None if sidecar else scan_rings(points), scan_rows=rows, **provenance)  # type: ignore[arg-type]
    if sidecar:
        frame = frame.with_note(f"{DENSIFIED_NOTE} ({sidecar} beside it): its generated points are not in KITTI's "
                                "ring order, so no laser rings are read from it")
    total = far + near + repeats + len(points)
    if far:
        frame = frame.with_note(f"{counted(far, 'point')} beyond {max_range:g} m dropped at load "
                                f"({far / total:.2%} of the scan)")
    if near:
        frame = frame.with_note(f"{counted(near, 'point')} within {min_range:g} m of the sensor (not returns, e.g. zeros "
                                f"written for missing ones) dropped at load ({near / total:.2%} of the scan)")
    if repeats:
        frame = frame.with_note(f"{counted(repeats, 'point')} repeating an earlier point's x, y, z dropped at load "
                                f"({repeats / total:.2%} "
                                "of the scan): each place is upsampled once")
    return frame
