"""Stage 8, write: per frame, one Parquet file (pyarrow), one binary PLY (numpy; Open3D reads it) and/or
a KITTI `.bin` in a mirror of the input's layout (`stages.write_kitti`), as `Options.formats` asks.

Layout under the output folder:

    points/DATASET/SEQUENCE/NNNNNN.parquet
    ply/DATASET/SEQUENCE/NNNNNN.ply
    kitti/...  (see stages.write_kitti)

Columns: x, y, z, reflectance (float32, sensor frame, metres), generated, ground (bool),
parent (int64: the row, in the input scan, of the point each point came from), frame (int32), dataset and
sequence (string). Every file is written under a temporary name in `OUT/.tmp/` and renamed into
place, so a reader or a crash never sees a half-written file, and no reader of `points/` ever sees
a temporary (`stages.temporaries`; `sweep_stale_temporaries` removes those a killed writer left).
A frame whose cloud holds a NaN or an infinite value is refused (`NonFiniteOutputError`), never
written. Each file records the fingerprint of the scan it came from (`stored_source`,
`source_changed`).

Why `dataset` and `sequence` are columns in each file and the folders are not named
`dataset=.../sequence=...` (Hive style): readers infer a Hive folder's value types from the names,
so pandas, pyarrow and Dask turned the odometry sequence "00" into the integer 0 (and Dask into
NaN beside a raw drive's name); a `_common_metadata` schema is ignored by pandas and pyarrow; and
a column that is both in the file and in a Hive folder name makes pandas, pyarrow and Dask refuse
the folder ("incompatible types"). With plain folder names and the columns in the files, pandas,
pyarrow.dataset, Dask and DuckDB all read `OUT/points` as one table with `sequence` "00" a
string, with their plain calls (tests/stages/test_readers.py).
"""

from __future__ import annotations

import dataclasses
import json
import numbers
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from collections.abc import Mapping
from typing import TYPE_CHECKING, Any, Literal

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
from pydantic import Field, field_validator

from .discovery import source_fingerprint
from .errors import StageError
from .frame import Frame, StitchedCloud, check_frame_name, stage_inputs
from .options import StageOptions, refuse_empty_path
from .ply_format import PLY_PROPERTIES, PLY_ROW_BYTES, ply_header, ply_is_complete, ply_rows
from .temporaries import TEMPORARY_DIR, TEMPORARY_MAX_AGE_S, replace_atomically, sweep, temporary_name

if TYPE_CHECKING:
    import pandas as pd

from . import write_kitti

#: Every output format; `DEFAULT_FORMATS` are those written unless `output.formats` says otherwise.
FORMATS = ("parquet", "ply", "kitti")
DEFAULT_FORMATS = ("parquet", "ply")
#: Every column is non-nullable (a point always has every value), so the Parquet columns are
#: REQUIRED and the writer encodes no definition levels (docs/results.md, "Write").
SCHEMA = pa.schema([pa.field(name, kind, nullable=False) for name, kind in (
    ("x", pa.float32()), ("y", pa.float32()), ("z", pa.float32()), ("reflectance", pa.float32()),
    ("generated", pa.bool_()), ("ground", pa.bool_()), ("parent", pa.int64()), ("frame", pa.int32()),
    ("dataset", pa.string()), ("sequence", pa.string()),
)])
#: Columns with min/max statistics: those a reader selects frames of a folder by. Every frame's
#: coordinates span the whole scan and every frame holds both values of each flag, so statistics
#: of the other columns would prune nothing and cost write time.
STATISTICS_COLUMNS = ["frame", "dataset", "sequence"]

#: File metadata key (Parquet) and PLY header comment holding `source_fingerprint` of the scan.
SOURCE_KEY = "source_fingerprint"
#: The key of the record that holds the sha256 of the scan's bytes (`Frame.source_digest`; absent
#: for a frame made in memory, and in files written before 2026-11-27).
SOURCE_DIGEST_KEY = "source_sha256"
#: Record key holding the output settings its config hash stands for, as JSON (`pipeline.chain.provenance`).
CONFIG_KEY = "config"
#: The PLY header comment that holds a frame's record (`frame_record`) as JSON.
RECORD_COMMENT = "kitti_pu_record"


class Options(StageOptions):
    """Where and in which formats the frames are written.

    dir: the output folder (layout in the module docstring).
    formats: any of `FORMATS`, at least one ("parquet" and "ply" by default); a comma-separated
        string ("parquet,kitti") is accepted too.
    """

    dir: Path = Path("kitti-pu-out")
    formats: list[Literal["parquet", "ply", "kitti"]] = Field(default_factory=lambda: list(DEFAULT_FORMATS))

    @field_validator("dir", mode="before")
    @classmethod
    def _not_empty(cls, value: object) -> object:
        return refuse_empty_path(value, "output.dir")

    @field_validator("formats", mode="before")
    @classmethod
    def _split_formats(cls, value: Any) -> Any:
        return split_formats(value)

    @field_validator("formats")
    @classmethod
    def _check_formats(cls, value: list[str]) -> list[str]:
        if not value:
            raise ValueError(f"output.formats must name at least one of {', '.join(map(repr, FORMATS))}")
        return list(dict.fromkeys(value))


def split_formats(value: Any) -> Any:
    """A comma-separated format list ("parquet,ply") as its names; anything else as it is."""
    if isinstance(value, str):  # "parquet" is one format, not seven letters
        return [part.strip() for part in value.split(",") if part.strip()]
    return value


#: The folders under an output folder that hold frames, by format (`output_paths`).
DATA_FOLDERS = {"parquet": "points", "ply": "ply", "kitti": "kitti"}


def data_folders(out_dir: Path) -> list[Path]:
    """The folders of an output folder that hold its frames, one per format (`DATA_FOLDERS`)."""
    return [Path(out_dir) / name for name in DATA_FOLDERS.values()]


def output_paths(out_dir: Path, dataset: str, sequence: str, index: int,
                 formats: tuple[str, ...] = DEFAULT_FORMATS, source: str = "") -> dict[str, Path]:
    """Where the frame's files go, by format name (`source`, the input scan's path, names the
    `kitti` mirror's file; without it the mirror's file is named by `index`).

    Raises:
        ValueError when the name does not map onto the layout (`stages.frame.check_frame_name`),
        or the `kitti` format is asked for a dataset the mirror has no layout for (not one of
        `write_kitti.LAYOUTS`: such frames took the bin layout, where frames of two datasets with
        one sequence name overwrote each other's copy).
    """
    check_frame_name(dataset, sequence, index)
    formats = split_formats(formats)
    if "kitti" in formats and dataset not in write_kitti.LAYOUTS:
        raise ValueError(f"the kitti format mirrors KITTI's layouts ({', '.join(write_kitti.LAYOUTS)}); frame dataset "
                         f"{dataset!r} has none (name a frame made in memory with one of them, or write parquet/ply)")
    out_dir = Path(out_dir)
    paths = {
        "parquet": out_dir / DATA_FOLDERS["parquet"] / dataset / sequence / f"{index:06d}.parquet",
        "ply": out_dir / DATA_FOLDERS["ply"] / dataset / sequence / f"{index:06d}.ply",
        "kitti": write_kitti.scan_path(out_dir, dataset, sequence, index, source),
    }
    unknown = set(formats) - set(paths)
    if unknown:
        raise ValueError(f"unknown output format(s) {sorted(unknown)}; known: {list(paths)}")
    return {name: paths[name] for name in formats}


#: The folder beside `points/` where `kitti-pu preview` puts a frame's picture (never inside the
#: data folders, where readers would take it for data).
PREVIEW_DIR = "preview"


def preview_path(out_dir: Path, dataset: str, sequence: str, index: int) -> Path:
    """Where a frame's preview picture goes: OUT/preview/DATASET/SEQUENCE/NNNNNN.png."""
    return Path(out_dir) / PREVIEW_DIR / dataset / sequence / f"{index:06d}.png"


class NonFiniteOutputError(StageError):
    """A frame's output cloud holds NaN or infinite values (e.g. from diverged weights): refused."""


def temporary_path(out_dir: Path, final_name: str) -> Path:
    """Where this process writes the temporary of an output file named `final_name` (`OUT/.tmp/`)."""
    return Path(out_dir) / TEMPORARY_DIR / temporary_name(final_name)


def sweep_stale_temporaries(out_dir: Path, max_age_s: float = TEMPORARY_MAX_AGE_S) -> list[Path]:
    """Remove the temporaries under `out_dir` that no running writer will rename (a writer killed
    on this host, anything untouched for `max_age_s` seconds, names of earlier versions); safe
    while another run writes into `out_dir`. Returns the paths removed."""
    return sweep(Path(out_dir), max_age_s) if Path(out_dir).is_dir() else []


#: The largest parent a PLY file holds (its int32 `parent` property).
PLY_MAX_PARENT = np.iinfo(np.int32).max


#: The numpy kinds of a cloud's columns that the writers take (`check_cloud`).
CLOUD_COLUMN_KINDS = {"xyz": "f", "reflectance": "f", "generated": "b", "ground": "b", "parent": "iu"}


def check_cloud(cloud: StitchedCloud, frame: Frame | None = None, path: Path | None = None) -> None:
    """Refuse a cloud no writer may write: what every writer checks before it writes anything.

    Args:
        cloud: the stitched cloud. frame: the frame it belongs to (named in the errors, and its
            point count bounds the parents); path: the file named instead when there is no frame.

    Raises:
        StageError("write", ...) unless xyz is (Q, 3) and the other columns (Q,), numpy arrays of
        floats (xyz, reflectance), bool (generated, ground) and integers (parent), and every
        parent is an index (0 to 2**31 - 1, what the PLY's int32 holds; below the frame's point
        count when a frame with points is given). NonFiniteOutputError when x, y, z or reflectance
        is NaN or infinite as written, in float32 (a float64 value beyond float32's range becomes
        infinite there).
    """
    where = (frame.source or frame.key) if frame is not None else str(path)
    count = len(cloud.xyz) if np.ndim(cloud.xyz) == 2 else -1
    shapes = {"xyz": np.shape(cloud.xyz), "reflectance": np.shape(cloud.reflectance),
              "generated": np.shape(cloud.generated), "ground": np.shape(cloud.ground),
              "parent": np.shape(cloud.parent)}
    expected = {"xyz": (count, 3), **{name: (count,) for name in shapes if name != "xyz"}}
    wrong = [f"{name} {shape}" for name, shape in shapes.items() if shape != expected[name]]
    if wrong:
        raise StageError("write", where, f"the cloud's arrays must be xyz (Q, 3) and (Q,) columns; got {', '.join(wrong)}")
    # a list failed as an AttributeError inside the checks below, and generated values 0/7 were
    # written into a column documented as 0 or 1 (a library user's trial)
    columns = {name: getattr(cloud, name) for name in CLOUD_COLUMN_KINDS}
    wrong = [f"{name} {values.dtype if isinstance(values, np.ndarray) else type(values).__name__}"
             for name, values in columns.items()
             if not isinstance(values, np.ndarray) or values.dtype.kind not in CLOUD_COLUMN_KINDS[name]]
    if wrong:
        raise StageError("write", where, "the cloud's columns must be numpy arrays, xyz and reflectance of floats, "
                                         f"generated and ground of bool, parent of integers; got {', '.join(wrong)}")
    if count and int(np.min(cloud.parent)) < 0:
        raise StageError("write", where, "the cloud's parent column holds a negative index")
    # parents index the frame's points (a frame written from stored files holds none: `pipeline.export`)
    limit = len(frame.points) if frame is not None and len(frame.points) else PLY_MAX_PARENT + 1
    if count and (largest := int(np.max(cloud.parent))) >= limit:
        beyond = f"the frame's {limit} points" if limit <= PLY_MAX_PARENT else "what a file's int32 parent holds"
        raise StageError("write", where, f"the cloud's parent column holds {largest}, beyond {beyond}")
    with np.errstate(over="ignore"):
        # min and max are NaN when any value is, and infinite when any is (after the cast, when any
        # is out of float32's range): two passes, no temporaries
        if all(np.isfinite(np.float32(values.min())) and np.isfinite(np.float32(values.max()))
               for values in (cloud.xyz, cloud.reflectance) if values.size):
            return
        bad = (~np.isfinite(cloud.xyz.astype(np.float32)).all(axis=1)
               | ~np.isfinite(cloud.reflectance.astype(np.float32)))
    scan = f"; scan {frame.source or 'in memory'}" if frame is not None else ""
    raise NonFiniteOutputError("write", frame.key if frame is not None else where,
                               f"{int(bad.sum())} of {len(cloud)} output points have non-finite values in float32 "
                               f"(first at row {int(np.argmax(bad))}{scan}): nothing written (from the chain: are the "
                               "network's weights finite?)")


def with_scan_rows(cloud: StitchedCloud, frame: Frame) -> StitchedCloud:
    """The cloud with each `parent` turned from an index into the frame's points into the row of
    that point in the scan (`Frame.scan_rows`), as the files hold it: a user joins the output to
    the scan's rows (or SemanticKITTI's per-row labels) by it."""
    if frame.scan_rows is None:
        return cloud
    return dataclasses.replace(cloud, parent=np.asarray(frame.scan_rows, dtype=np.int64)[cloud.parent])


def frame_record(cloud: StitchedCloud, frame: Frame, metadata: Mapping[str, str]) -> dict[str, str]:
    """What every file of a frame records about it: dataset, sequence, frame, timestamp, pose (the
    frame's `Frame.pose`, the Velodyne's 4 x 4 pose in the drive's or sequence's world frame, as a
    JSON list of 4 rows; "" when unknown), source path, fingerprint (`SOURCE_KEY`) and, for a
    scan read from a file, the digest of its bytes (`SOURCE_DIGEST_KEY`), point
    counts (input_points, points, generated_points, ground_points, ground_filled_points, and
    dropped_points: generated points snapping dropped), plus the run's `metadata` (config hash,
    model checksum, run id, ...). The Parquet file holds it as key-value metadata, the PLY header
    as JSON in comment lines (`RECORD_COMMENT`), the KITTI sidecar as a JSON string;
    `stored_record` reads it back from any of them."""
    # the scan as it was read (`Frame.source_fingerprint`): one replaced since must not be recorded
    # as the one these points came from; a frame made in memory has its file's state now
    fingerprint = frame.source_fingerprint or (source_fingerprint(frame.source) if frame.source else "")
    info = {
        "dataset": frame.dataset, "sequence": frame.sequence, "frame": str(frame.index),
        **metadata_record(frame.timestamp, frame.pose), "source": frame.source,
        "input_points": str(len(frame.points)), "points": str(len(cloud)),
        "generated_points": str(int(np.count_nonzero(cloud.generated))),
        "ground_points": str(int(np.count_nonzero(cloud.ground))),
        "ground_filled_points": str(int(np.count_nonzero(cloud.generated & cloud.ground))),
        "dropped_points": str(int(cloud.dropped)),
        SOURCE_KEY: fingerprint, **({SOURCE_DIGEST_KEY: frame.source_digest} if frame.source_digest else {}),
        **metadata,
    }
    return {key: str(value) for key, value in info.items()}


def to_table(cloud: StitchedCloud, frame: Frame, metadata: Mapping[str, str],
             record: Mapping[str, str] | None = None) -> pa.Table:
    """The frame's Arrow table as `write_parquet` writes it, with its file metadata: `record`, or
    `frame_record(cloud, frame, metadata)` when it is not given.

    Its columns are those of `SCHEMA`, except that dataset and sequence, one value each, are
    dictionary arrays of that value: the writer then stores their dictionary pages as they are
    instead of hashing every row's string, and the file reads back as `SCHEMA` (`write_parquet`).
    """
    n = len(cloud)
    columns = [cloud.xyz[:, 0], cloud.xyz[:, 1], cloud.xyz[:, 2], cloud.reflectance, cloud.generated,
               cloud.ground, cloud.parent, np.full(n, frame.index, dtype=np.int32)]
    arrays = [pa.array(np.ascontiguousarray(c), type=field.type) for c, field in zip(columns, SCHEMA)]
    first = pa.array(np.zeros(n, np.int32))
    arrays += [pa.DictionaryArray.from_arrays(first, pa.array([frame.dataset], pa.string())),
               pa.DictionaryArray.from_arrays(first, pa.array([frame.sequence], pa.string()))]
    schema = pa.schema([field.with_type(array.type) for field, array in zip(SCHEMA, arrays)],
                       metadata=dict(record) if record is not None else frame_record(cloud, frame, metadata))
    return pa.Table.from_arrays(arrays, schema=schema)


#: Parquet encodings: the floats byte-stream-split (their bytes grouped by significance before
#: compression: smaller and faster to compress), parent delta-encoded (neighbours' parents are
#: close). The rest plain, dataset and sequence dictionary-encoded.
COLUMN_ENCODINGS = {"x": "BYTE_STREAM_SPLIT", "y": "BYTE_STREAM_SPLIT", "z": "BYTE_STREAM_SPLIT",
                    "reflectance": "BYTE_STREAM_SPLIT", "parent": "DELTA_BINARY_PACKED"}
#: pyarrow's "lz4" is Parquet's LZ4_RAW codec: files as small as with zstd at the levels used
#: before, written faster (docs/results.md, "Write: LZ4_RAW, one page per column").
COMPRESSION = "lz4"


def write_parquet(cloud: StitchedCloud, frame: Frame, path: str | Path, metadata: Mapping[str, str] | None = None,
                  temporary_dir: Path | None = None, record: Mapping[str, str] | None = None) -> None:
    """Write the frame's Parquet file atomically (its temporary in `temporary_dir`, default beside it)
    at `path`, a file path (str or Path). `metadata`: the run's provenance (`pipeline.chain.provenance`:
    tool version, config hash, model checksum, ...), kept in the file's record; none by default,
    as for a cloud made by library calls. The `parent` column holds `cloud.parent` as given: the
    pipeline's files hold scan rows there (`with_scan_rows`).

    LZ4_RAW (`COMPRESSION`) over `COLUMN_ENCODINGS`; dictionary encoding only for dataset and
    sequence (it gains nothing on coordinates and costs 3x the write time); statistics only for
    `STATISTICS_COLUMNS`; the writer takes a row group's rows in one batch instead of 1,024 at a
    time (its per-batch work is most of the time of the flag and constant columns). The Arrow schema is not stored in the file (its
    dictionary columns would read back as dictionaries): every column's Parquet type reads back as
    `SCHEMA` says, and the file metadata is added as key-value metadata, as pyarrow stores a table's.
    Each page carries a CRC-32 of its bytes, which readers that ask (`stages.stored.read_cloud`,
    `kitti-pu info --verify`) check: a byte changed on disk decompresses without error otherwise.

    Raises:
        StageError / NonFiniteOutputError naming the frame for a cloud `check_cloud` refuses, or
        naming `path` when it is a folder; nothing is written then.
    """
    path = Path(path)
    check_cloud(cloud, frame)
    if path.is_dir():
        raise StageError("write", str(path), "is a folder; give the Parquet file's path")
    _write_parquet(cloud, frame, path, metadata or {}, temporary_dir, record)


def _write_parquet(cloud: StitchedCloud, frame: Frame, path: Path, metadata: Mapping[str, str],
                   temporary_dir: Path | None, record: Mapping[str, str] | None) -> None:
    """`write_parquet` of a cloud `check_cloud` has passed."""
    table = to_table(cloud, frame, metadata, record)

    def write(temporary: Path) -> None:
        with pq.ParquetWriter(temporary, table.schema, compression=COMPRESSION,
                              use_dictionary=["dataset", "sequence"], column_encoding=COLUMN_ENCODINGS,
                              write_statistics=STATISTICS_COLUMNS, store_schema=False,
                              write_batch_size=max(table.num_rows, 1), write_page_checksum=True) as writer:
            writer.write_table(table)
            writer.add_key_value_metadata(table.schema.metadata)

    replace_atomically(path, write, temporary_dir)


def write_ply(cloud: StitchedCloud, path: str | Path, frame_index: int = 0, comments: tuple[str, ...] = (),
              temporary_dir: Path | None = None) -> None:
    """Write a binary little-endian PLY atomically: float32 positions and reflectance, uint8 (0/1)
    generated and ground flags, int32 parent and frame (`PLY_PROPERTIES`: PLY has no bool and no
    64-bit integer; Open3D's tensor API reads them as named attributes), with one header comment
    line per item of `comments`.

    Written with numpy (header and rows in one buffer, the rows packed by `ply_rows`), so a failing
    write (a full disk) raises one OSError instead of Open3D's line per vertex.

    `path` is a file path (str or Path); `frame_index` the frame column's value (0 to 2**31 - 1:
    the PLY's int32); each comment one line of at most `PLY_COMMENT_LINE` characters (Open3D's
    reader aborts the process on a longer header line; `ply_comment_lines` splits a longer value).

    Raises:
        StageError / NonFiniteOutputError naming `path` for a cloud `check_cloud` refuses, a frame
        index beyond int32, a comment with a line break or too long, or a `path` that is a
        folder; nothing is written then.
    """
    path = Path(path)
    check_cloud(cloud, path=path)
    if isinstance(frame_index, bool) or not isinstance(frame_index, numbers.Integral) \
            or not 0 <= frame_index <= PLY_MAX_PARENT:
        raise StageError("write", str(path), f"frame_index must be a whole number from 0 to {PLY_MAX_PARENT} "
                                             f"(the PLY's int32 frame column), got {frame_index!r}")
    for comment in comments:
        if not isinstance(comment, str) or "\n" in comment or "\r" in comment or len(comment) > PLY_COMMENT_LINE:
            raise StageError("write", str(path), f"each PLY comment must be one line of text of at most "
                                                 f"{PLY_COMMENT_LINE} characters (Open3D's reader fails on longer header "
                                                 f"lines; ply_comment_lines splits a value), got {comment!r:.80}")
    if path.is_dir():
        raise StageError("write", str(path), "is a folder; give the PLY file's path")
    _write_ply(cloud, path, frame_index, comments, temporary_dir)


def _write_ply(cloud: StitchedCloud, path: Path, frame_index: int, comments: tuple[str, ...],
               temporary_dir: Path | None) -> None:
    """`write_ply` of a cloud `check_cloud` has passed (`ply_rows` packs it unchecked)."""
    header = ["ply", "format binary_little_endian 1.0", *(f"comment {c}" for c in comments),
              f"element vertex {len(cloud)}", *(f"property {kind} {name}" for name, kind, _ in PLY_PROPERTIES),
              "end_header"]
    head = ("\n".join(header) + "\n").encode("ascii")
    buffer = np.empty(len(head) + len(cloud) * PLY_ROW_BYTES, np.uint8)
    buffer[:len(head)] = np.frombuffer(head, np.uint8)
    ply_rows(cloud, frame_index, buffer[len(head):])

    def write(temporary: Path) -> None:
        with open(temporary, "wb") as stream:
            stream.write(buffer.data)

    replace_atomically(path, write, temporary_dir)


def write_frame(cloud: StitchedCloud, frame: Frame, out_dir: Path, metadata: dict[str, str],
                formats: tuple[str, ...] = DEFAULT_FORMATS, record: Mapping[str, str] | None = None) -> dict[str, Path]:
    """Write the frame in every requested format; returns the paths written.

    `record` is what the files record about the frame (default: `frame_record(cloud, frame,
    metadata)`); given, as when a stored frame is written in another format (`pipeline.export`),
    it is kept as it is.

    The formats are written side by side in threads (pyarrow and numpy's file writes release the
    GIL): the stage then takes about as long as its slowest format.

    Raises:
        StageError("write", path, reason) when a file cannot be written. The frame's files are
        then all removed, so a frame is either complete in every format or absent.
        StageError("write", frame) when the cloud's arrays have wrong shapes or a negative parent,
        or the frame's name does not map onto the output layout; nothing is written then.
        NonFiniteOutputError (a StageError) naming the frame when the cloud holds NaN or
        infinite values; nothing is written then.
    """
    try:
        paths = output_paths(out_dir, frame.dataset, frame.sequence, frame.index, formats, frame.source)
    except ValueError as error:
        raise StageError("write", frame.source or "frame", str(error)) from None
    check_cloud(cloud, frame)  # once, for every format
    cloud = with_scan_rows(cloud, frame)
    temporary_dir = Path(out_dir) / TEMPORARY_DIR
    record = dict(record) if record is not None else frame_record(cloud, frame, metadata)
    fingerprint = record.get(SOURCE_KEY, "")
    ply_comments = (ply_comment_lines(SOURCE_KEY, fingerprint) if fingerprint else ()) + ply_comment_lines(
        RECORD_COMMENT, json.dumps(record))

    def atomic(path: Path, write: Callable[[Path], None]) -> None:
        replace_atomically(path, write, temporary_dir)

    writers: dict[str, Callable[[Path], None]] = {
        # the record computed once above (a stat of the scan, a pass over the flags) serves every format
        "parquet": lambda path: _write_parquet(cloud, frame, path, metadata, temporary_dir, record),
        "ply": lambda path: _write_ply(cloud, path, frame.index, ply_comments, temporary_dir),
        "kitti": lambda path: write_kitti.write_kitti(cloud, frame, path, atomic, record),
    }
    with ThreadPoolExecutor(max_workers=len(paths)) as pool:
        futures = {name: pool.submit(writers[name], path) for name, path in paths.items()}
    failures = {name: future.exception() for name, future in futures.items() if future.exception()}
    if not failures:
        return paths
    remove_outputs(paths)
    name, error = next(iter(failures.items()))
    if not isinstance(error, (OSError, pa.ArrowException)):
        raise error
    reason = getattr(error, "strerror", None) or error
    raise StageError("write", str(paths[name]), f"cannot write frame {frame.key} ({reason})") from None


#: The most characters of a value on one PLY comment line. Open3D's PLY reader (rply) takes header
#: lines of up to 1,024 characters and aborts the whole process on a longer one, and a frame's
#: record, which holds its source path twice, outgrows that under a deep folder.
PLY_COMMENT_CHUNK = 900
#: The most characters of a whole comment `write_ply` takes (a key, a space and a chunk fit).
PLY_COMMENT_LINE = 1000
#: Marks a comment line that continues the value of the line before (`ply_comment_lines`).
CONTINUED = "+"


def ply_comment_lines(key: str, value: str) -> tuple[str, ...]:
    """`KEY VALUE` as PLY comment texts of at most `PLY_COMMENT_CHUNK` characters of value each:
    the first `KEY PART`, the rest `KEY+ PART` (`_ply_comments` joins them)."""
    parts = [value[i:i + PLY_COMMENT_CHUNK] for i in range(0, len(value), PLY_COMMENT_CHUNK)] or [""]
    return (f"{key} {parts[0]}", *(f"{key}{CONTINUED} {part}" for part in parts[1:]))


def _ply_comments(path: Path) -> dict[str, str]:
    """The `comment KEY VALUE` lines of a PLY header, by KEY, with the continuation lines of each
    value joined (`ply_comment_lines`); {} without a header."""
    header = ply_header(path)
    lines = header[1] if header else []
    comments: dict[str, str] = {}
    for line in lines:
        if not line.startswith("comment "):
            continue
        key, _, value = line[len("comment "):].partition(" ")
        if key.endswith(CONTINUED) and key[:-len(CONTINUED)] in comments:
            comments[key[:-len(CONTINUED)]] += value
        else:
            comments[key] = value
    return comments


def remove_outputs(paths: dict[str, Path]) -> None:
    """Remove a frame's files (`output_paths`; a KITTI scan with its sidecar), those that exist."""
    for name, path in paths.items():
        if name == "kitti":
            write_kitti.remove(path)
        elif Path(path).is_file():  # not what a failed rename left in its place (a folder)
            Path(path).unlink()


def stored_record(paths: dict[str, Path]) -> dict[str, str]:
    """The record (`frame_record`) of a frame's stored files, from the first of them that holds
    one: the Parquet metadata, the PLY header, the KITTI sidecar. {} when none is there or
    readable. Files of earlier versions may hold only part of it (a PLY header only the source
    fingerprint)."""
    for name, path in paths.items():
        try:
            if name == "parquet":
                raw = pq.read_metadata(path).metadata or {}
                record = {k.decode(): v.decode() for k, v in raw.items() if not k.startswith(b"ARROW")}
            elif name == "ply":
                comments = _ply_comments(path)
                record = json.loads(comments[RECORD_COMMENT]) if RECORD_COMMENT in comments else (
                    {SOURCE_KEY: comments[SOURCE_KEY]} if SOURCE_KEY in comments else {})
            else:
                record = write_kitti.stored_record(path)
        except (OSError, ValueError, pa.ArrowException):
            continue
        if record:
            return record
    return {}


def stored_source(paths: dict[str, Path]) -> str | None:
    """The scan fingerprint (`stages.discovery.source_fingerprint`) a frame's files were written
    from (`stored_record`); None when the files are missing, unreadable or do not record one
    (written by an earlier version, or from points in memory)."""
    return stored_record(paths).get(SOURCE_KEY) or None


def source_changed(paths: dict[str, Path], fingerprint: str) -> bool:
    """True unless the frame's files record exactly `fingerprint` (a `FrameRef.fingerprint`): the
    scan was replaced, edited, moved, is another file, or the files do not say which scan they
    came from. A resumed run redoes such a frame instead of skipping it."""
    return fingerprint_differs(stored_source(paths), fingerprint)


def metadata_record(timestamp: float | None, pose: np.ndarray | None) -> dict[str, str]:
    """A frame's timestamp (s) and pose (4 x 4) as its files record them: "timestamp" as the float's
    repr, "pose" as a JSON list of 4 rows; "" for either when unknown."""
    return {"timestamp": "" if timestamp is None else repr(float(timestamp)),
            "pose": "" if pose is None else json.dumps(np.asarray(pose, dtype=np.float64).tolist())}


#: How far a recorded timestamp (s) or pose entry (m; rotation entries) may be from the current one
#: and still match: the same numbers computed again with another numpy or CPU may differ in their
#: last bits, which for a raw pose's translation (Mercator metres near 4e6) are 5e-10 m each. A
#: micrometre or a microsecond is far below any correction of a pose or time.
METADATA_TOLERANCE = 1e-6


def metadata_change(stored: Mapping[str, str], current: Mapping[str, str]) -> str | None:
    """"timestamp changed" or "pose changed" when a frame's stored record (`stored_record`) holds
    another timestamp or pose than `current` (`metadata_record` of the frame's metadata now), else
    None. A record of an earlier version that lacks either field is not evidence of a change, nor
    is a field `current` lacks (the dataset's file for it cannot be read now)."""
    for key in ("timestamp", "pose"):
        if key not in stored or key not in current:
            continue
        before, now = stored[key], current.get(key, "")
        if before == now:
            continue
        try:
            same = (before != "" and now != "" and np.allclose(np.asarray(json.loads(before), dtype=np.float64),
                                                             np.asarray(json.loads(now), dtype=np.float64),
                                                             rtol=0.0, atol=METADATA_TOLERANCE))
        except (ValueError, TypeError):  # not numbers (a record edited by hand): not the same
            same = False
        if not same:
            return f"{key} changed"
    return None


def fingerprint_differs(stored: str | None, fingerprint: str) -> bool:
    """True unless `stored` (what a frame's files record, `stored_source`) is exactly `fingerprint`."""
    return stored is None or not fingerprint or json.loads(stored) != json.loads(fingerprint)


def is_complete(paths: dict[str, Path]) -> bool:
    """True when every file exists and reads back (Parquet footer; PLY header and size)."""
    for name, path in paths.items():
        if not path.is_file():
            return False
        try:
            if name == "parquet":
                pq.read_metadata(path)
            elif name == "kitti":
                if not write_kitti.is_complete(path):
                    return False
            elif not ply_is_complete(path):
                return False
        except (OSError, ValueError, pa.ArrowException):  # ValueError: a header that is not a PLY's
            return False
    return True


def read_frame(path: Path) -> "pd.DataFrame":
    """A frame's Parquet file as a pandas DataFrame (the columns of `SCHEMA`, one row a point)."""
    return pq.read_table(path).to_pandas()


def run(frame: Frame, options: Options = Options(), metadata: Mapping[str, str] | None = None) -> Frame:
    """The write stage: write the frame's cloud in every format of `options` (`write_frame`).

    Args:
        frame: a frame with its `cloud`. options: folder and formats.
        metadata: run-level file metadata (model checksum, config hash, tool version, ...).

    Reads: cloud, dataset, sequence, index, timestamp, source, points. Adds: outputs (path by
    format name).

    Raises:
        StageError("write", path, reason) when a file cannot be written (nothing of the frame is
        left behind then), or when the frame has no cloud.
    """
    frame, options = stage_inputs(frame, options, Options, "write")
    if frame.cloud is None:
        raise StageError("write", frame.source or frame.key, "the frame has no stitched cloud (run stages.stitch first)")
    paths = write_frame(frame.cloud, frame, options.dir, metadata=dict(metadata or {}),
                        formats=tuple(options.formats))
    return frame.with_(outputs={name: str(path) for name, path in paths.items()})
