"""The record that travels through the stages: one LiDAR scan plus what each stage adds.

`Frame` holds the scan and its provenance; every stage's `run(frame, options)` returns a copy with
its own fields filled in (each stage's docstring lists the fields it reads and adds).
`StitchedCloud` is the output cloud that the stitch stage adds, snap and fill refine, and write writes.
"""

from __future__ import annotations

from dataclasses import MISSING, dataclass, field, replace
from typing import Any, NamedTuple

import numpy as np

from cadpu.patches import PatchCover as Tiling  # patches over a frame's object points

from .discovery import MAX_INDEX, layout_name_problem
from .errors import StageError
from .options import OptionsT, stage_options
from .range_image import RangeImage

__all__ = ["Frame", "StitchedCloud", "Tiling"]


#: More columns than this, and than rows, is taken for a transposed scan (x, y, z, reflectance and
#: the like are a handful of columns; no scan format has this many).
MAX_ATTRIBUTE_COLUMNS = 16


def looks_transposed(shape: tuple[int, ...]) -> bool:
    """Whether a 2-D array of `shape` is a scan given as (columns, points) instead of (points,
    columns): more columns than `MAX_ATTRIBUTE_COLUMNS` and than rows."""
    return len(shape) == 2 and shape[1] > max(MAX_ATTRIBUTE_COLUMNS, shape[0])


def check_frame_name(dataset: str, sequence: str, index: int) -> None:
    """ValueError unless a frame's name maps onto the output layout: `dataset` and `sequence` are
    each one folder name (not empty, not "." or "..", no path separator) that readers of the
    Parquet dataset read (`stages.discovery.layout_name_problem`), `index` is 0 or more
    (file names are the index in 6 digits: OUT/points/DATASET/SEQUENCE/NNNNNN.parquet) and fits
    the int32 `frame` column."""
    for part, value in (("dataset", dataset), ("sequence", sequence)):
        if not isinstance(value, str) or value in ("", ".", "..") or "/" in value or "\\" in value:
            raise ValueError(f"frame {part} {value!r} is not one folder name (the output is "
                             "OUT/points/DATASET/SEQUENCE/NNNNNN.parquet)")
        problem = layout_name_problem(value)
        if problem is not None:
            raise ValueError(f"frame {part} {value!r} {problem} (the output is "
                             "OUT/points/DATASET/SEQUENCE/NNNNNN.parquet)")
    if not isinstance(index, (int, np.integer)) or isinstance(index, bool) or not 0 <= index <= MAX_INDEX:
        # the `frame` column is int32: a larger one was written wrapped (PLY) or failed the write (Parquet)
        raise ValueError(f"frame index must be an integer from 0 to {MAX_INDEX}, got {index!r}")


@dataclass(frozen=True)
class StitchedCloud:
    """The output cloud of one frame (Q points).

    Attributes:
        xyz: (Q, 3) float32, sensor frame, metres.
        reflectance: (Q,) float32.
        generated: (Q,) bool, True for points made by the network or filled in on the ground.
        ground: (Q,) bool, True for ground points (input ones, and those `stages.fill` adds).
        parent: (Q,) int64 index into the frame's input points of the point each came from
            (itself for input points; the upper of the two returns for filled ground points). The
            files hold the row in the scan instead (`Frame.scan_rows`).
        dropped: generated points removed by ring snapping or the range check (not in the cloud).
    """

    xyz: np.ndarray
    reflectance: np.ndarray
    generated: np.ndarray
    ground: np.ndarray
    parent: np.ndarray
    dropped: int = 0

    def __len__(self) -> int:
        return int(self.xyz.shape[0])

    def select(self, keep: np.ndarray, xyz: np.ndarray | None = None, dropped: int = 0) -> "StitchedCloud":
        """The cloud's points where `keep` ((Q,) bool) is True, with `xyz` ((Q, 3), optional) as
        their new positions and `dropped` more points counted as dropped."""
        positions = self.xyz if xyz is None else xyz
        rows = np.flatnonzero(keep)  # one pass over the mask, then a gather per array
        return StitchedCloud(xyz=positions[rows], reflectance=self.reflectance[rows],
                             generated=self.generated[rows], ground=self.ground[rows],
                             parent=self.parent[rows], dropped=self.dropped + dropped)

    def extend(self, other: "StitchedCloud") -> "StitchedCloud":
        """This cloud with `other`'s points appended (dropped counts added)."""
        return StitchedCloud(xyz=np.concatenate([self.xyz, other.xyz]),
                             reflectance=np.concatenate([self.reflectance, other.reflectance]),
                             generated=np.concatenate([self.generated, other.generated]),
                             ground=np.concatenate([self.ground, other.ground]),
                             parent=np.concatenate([self.parent, other.parent]),
                             dropped=self.dropped + other.dropped)


@dataclass(frozen=True)
class Frame:
    """One scan and its provenance; stages return a copy with their own fields filled in.

    Attributes:
        points: (N, 4) float32 x, y, z, reflectance in the sensor (Velodyne) frame, metres, z up.
        dataset: "raw", "odometry" or "bin".
        sequence: drive name (raw, e.g. "2011_09_26_drive_0001_sync"), sequence id
            (odometry, e.g. "00") or folder name (bin).
        index: frame index within the drive or sequence.
        timestamp: seconds since the first frame of the drive/sequence, or None when unknown.
        source: path of the file the points were read from.
        source_fingerprint: `stages.discovery.source_fingerprint` of `source` as it was when read
            (from the open file, before its bytes), "" for points given in memory.
        source_digest: `stages.discovery.content_digest` of the bytes read from `source`, "" for
            points given in memory: a rerun tells by it a scan moved or touched from a new one.
        calib: calibration matrices by name (e.g. "T_cam0_velo"), empty when the dataset has none.
        pose: (4, 4) float64 sensor pose in the world/odometry frame, or None when unknown.
        rings: (N,) int64 laser ring of each point, read from the stored point order when the
            scan is stored ring by ring (KITTI's order), else None (added by `stages.load`).
        scan_rows: (N,) int64 row in the scan (the file, or the array given to `stages.load`) of
            each point, when load dropped points out of range; None when it kept every row, in
            order (added by `stages.load`). The written `parent` columns are scan rows.
        ground: (N,) bool, True for ground points (added by `stages.ground`).
        tiling: patches over the non-ground points (added by `stages.tile`).
        upsampled: (S, K*r, 3) float32 normalised generated points (added by `stages.upsample`).
        parent_slots: (S, K*r) int64, slot (0..K-1) in its patch of the point each generated
            point came from (added by `stages.upsample`).
        upsampled_patches: (S,) int64, the tiling's patches that `upsampled` and `parent_slots`
            hold, row by row; None means all of them, in order.
        ratio: the upsampling ratio r of the frame (added by `stages.upsample`, also when no
            patch was upsampled).
        cloud: the output cloud (added by `stages.stitch`, refined by `stages.snap` and `stages.fill`).
        range_image: the scan's range image over its rings, built by the first stage that needs it
            (`stages.snap` or `stages.fill`) and kept for the next.
        outputs: files written, by format name (added by `stages.write`).
        timings: seconds spent per stage name (filled by `pipeline.chain`).
        notes: non-fatal remarks by stages (e.g. "fewer than 256 object points: not upsampled").
    """

    points: np.ndarray
    dataset: str
    sequence: str
    index: int
    timestamp: float | None = None
    source: str = ""
    source_fingerprint: str = ""
    source_digest: str = ""
    calib: dict[str, np.ndarray] = field(default_factory=dict)
    pose: np.ndarray | None = None
    rings: np.ndarray | None = None
    scan_rows: np.ndarray | None = None
    ground: np.ndarray | None = None
    tiling: Tiling | None = None
    upsampled: np.ndarray | None = None
    parent_slots: np.ndarray | None = None
    upsampled_patches: np.ndarray | None = None
    ratio: int | None = None
    cloud: StitchedCloud | None = None
    range_image: RangeImage | None = None
    outputs: dict[str, str] = field(default_factory=dict)
    timings: dict[str, float] = field(default_factory=dict)
    notes: tuple[str, ...] = ()

    @property
    def key(self) -> str:
        """A name unique within a run: dataset/sequence/index."""
        return f"{self.dataset}/{self.sequence}/{self.index:06d}"

    def with_(self, **changes: Any) -> "Frame":
        """Return a copy with the given fields replaced."""
        return replace(self, **changes)

    def with_stage_result(self, **changes: Any) -> "Frame":
        """Return a copy with a stage's fields replaced and every field a later stage adds
        (STAGE_OUTPUTS) cleared, with those stages' notes: they were made from what the stage now
        replaces (the ground stage run again on a frame already upsampled leaves no patches or
        upsampled points of the old labels behind for stitch to misplace)."""
        first = next((i for i, group in enumerate(STAGE_OUTPUTS) if not changes.keys().isdisjoint(group.fields)),
                     len(STAGE_OUTPUTS))
        later = STAGE_OUTPUTS[first + 1:]
        stale = {name: _stage_field_default(name) for group in later for name in group.fields if name not in changes}
        prefixes = tuple(f"{stage}: " for group in later for stage in group.stages)
        stale["notes"] = tuple(note for note in self.notes if not note.startswith(prefixes))
        return replace(self, **stale, **changes)

    def with_note(self, note: str) -> "Frame":
        """Return a copy with `note` added to `notes`."""
        return replace(self, notes=(*self.notes, note))

    def check_fields(self, stage: str) -> None:
        """StageError(`stage`, ...) saying what `mismatched_fields` finds, if anything."""
        if (mismatch := self.mismatched_fields()) is not None:
            raise StageError(stage, self.source or self.key, mismatch)

    def mismatched_fields(self) -> str | None:
        """What is wrong with the frame's points (not (N, 4)), its per-point fields (ground, rings,
        scan_rows: one value per point; ground bool, the others integers) and its upsampled patches
        (`parent_slots` shaped as `upsampled`'s points), or None: fields set by hand for one scan and
        used with another's points."""
        if np.ndim(self.points) != 2 or np.shape(self.points)[1] != 4:
            return (f"frame.points has shape {np.shape(self.points)}, not (N, 4) x, y, z, reflectance "
                    "(stages.load.frame_from_points checks an array and makes a frame of it)")
        count = len(self.points)
        for name in ("ground", "rings", "scan_rows"):
            shape = np.shape(getattr(self, name)) if getattr(self, name) is not None else (count,)
            if shape != (count,):
                return f"frame.{name} has shape {shape}, not ({count},) for the frame's {count} points"
        kinds = {name: np.asarray(getattr(self, name)).dtype for name in ("ground", "rings", "scan_rows")
                 if getattr(self, name) is not None}
        if "ground" in kinds and kinds["ground"] != np.bool_:
            # a 0/1 integer mask inverted to -1/-2 and indexed the last two points (a trial)
            return (f"frame.ground holds {kinds['ground']}, not bool: a mask, True for ground points (for 0/1 "
                    "labels, pass labels.astype(bool))")
        for name in ("rings", "scan_rows"):
            if name in kinds and kinds[name].kind not in "iu":
                return f"frame.{name} holds {kinds[name]}, not whole numbers (an integer array)"
        if self.upsampled is not None and self.parent_slots is not None \
                and np.shape(self.parent_slots) != np.shape(self.upsampled)[:2]:
            return (f"frame.parent_slots has shape {np.shape(self.parent_slots)}, not the "
                    f"{np.shape(self.upsampled)[:2]} of frame.upsampled's points")
        return None


class StageOutputs(NamedTuple):
    """The fields some stages add to a frame, and the names those stages start their notes with."""

    stages: tuple[str, ...]
    fields: tuple[str, ...]


#: What each stage adds, in chain order (ground, tile, upsample, stitch/snap/fill, write).
STAGE_OUTPUTS: tuple[StageOutputs, ...] = (
    StageOutputs(("ground",), ("ground",)), StageOutputs(("tile",), ("tiling",)),
    StageOutputs(("upsample",), ("upsampled", "parent_slots", "upsampled_patches", "ratio")),
    StageOutputs(("stitch", "snap", "fill"), ("cloud",)), StageOutputs(("write",), ("outputs",)))


def _stage_field_default(name: str) -> Any:
    """The value a new Frame holds in field `name`."""
    spec = Frame.__dataclass_fields__[name]
    return spec.default_factory() if spec.default is MISSING else spec.default  # type: ignore[misc]


def stage_inputs(frame: Any, options: Any, kind: type[OptionsT], stage: str) -> tuple[Frame, OptionsT]:
    """A stage's `run` arguments, checked: the frame, and `options` as `kind` (`stage_options`).

    Raises:
        TypeError: `frame` is not a Frame (naming the stage and how to make one), or `options` is
            neither `kind` nor a mapping of its keys.
        ValueError: a mapping with an unknown key or a bad value.
    """
    if not isinstance(frame, Frame):
        raise TypeError(f"{stage}.run takes a stages.frame.Frame, got {type(frame).__module__}."
                        f"{type(frame).__qualname__} (stages.load.frame_from_points makes one from an array, "
                        "stages.load.run from a file's FrameRef)")
    return frame, stage_options(options, kind, stage)
