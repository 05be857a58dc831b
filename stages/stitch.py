"""Stage 5, stitch: put the upsampled patches back into the sensor frame as one point cloud.

For every object point, the points generated from it in the patch that owns it are kept (a mask
over all generated points: linear time, no sampling over the whole frame). Generated points take
their parent's reflectance. Ground points are re-attached unchanged. The next stages refine the
cloud: `stages.snap` puts the generated points on virtual laser rings, `stages.fill` fills the
ground between the rings.
"""

from __future__ import annotations

import numpy as np

from cadpu.patches import keep_owned

from .errors import StageError
from .frame import Frame, StitchedCloud, stage_inputs
from .options import StageOptions
from .tile import left_untiled

__all__ = ["Options", "StitchedCloud", "run", "stitch", "stitch_points"]


class Options(StageOptions):
    """What goes into the output cloud besides the generated points.

    keep_ground: re-attach the ground points (unchanged).
    keep_input: keep the input object points besides the generated ones (points of patches that
        were not upsampled are kept either way).
    """

    keep_ground: bool = True
    keep_input: bool = True


def stitch(frame: Frame, keep_ground: bool = True, keep_input: bool = True) -> StitchedCloud:
    """Assemble the frame's output cloud (`stitch_points` of its fields).

    Args:
        frame: a frame through `stages.upsample` (or one without tiling: its points pass through).
        keep_ground, keep_input: see `Options`.

    Returns:
        The `StitchedCloud`: input object points (if kept), then generated points, then ground.

    Raises:
        TypeError: `frame` is not a Frame.
    """
    if not isinstance(frame, Frame):  # an AttributeError deep inside before (a trial)
        raise TypeError(f"stitch: takes a stages.frame.Frame, got {type(frame).__name__}")
    points = frame.points
    ground_mask = frame.ground if frame.ground is not None else np.zeros(len(points), dtype=bool)
    upsampled = frame.tiling is not None and frame.upsampled is not None and frame.parent_slots is not None
    if not upsampled:
        return stitch_points(points, ground_mask, keep_ground=keep_ground)
    kept = None
    if not keep_input:  # only the points of patches left out by `stages.upsample`
        done = np.zeros(len(frame.tiling.scale), dtype=bool)
        done[slice(None) if frame.upsampled_patches is None else frame.upsampled_patches] = True
        kept = np.flatnonzero(~done[frame.tiling.owner])
    xyz, source = keep_owned(frame.tiling, frame.upsampled, frame.parent_slots, frame.upsampled_patches)
    return stitch_points(points, ground_mask, xyz, source, keep_ground=keep_ground, kept_objects=kept)


def stitch_points(points: np.ndarray, ground: np.ndarray, xyz: np.ndarray | None = None,
                  source: np.ndarray | None = None, keep_ground: bool = True,
                  kept_objects: np.ndarray | None = None) -> StitchedCloud:
    """A scan's output cloud from arrays: its object points, then the generated ones, then (with
    `keep_ground`) its ground points; every point's reflectance is its parent's.

    Args:
        points: (N, 4) the scan's x, y, z, reflectance, sensor frame, metres (as load keeps them:
            `stages.load.scan_points`).
        ground: (N,) bool, True for ground points (`stages.ground.segment(points).mask`).
        xyz: (M, 3) generated points, sensor frame, metres (`cadpu.patches.keep_owned`'s first
            result), or None for none.
        source: (M,) the object point each came from, an index into `points[~ground]`
            (`keep_owned`'s second result).
        keep_ground: re-attach the ground points.
        kept_objects: indices into `points[~ground]` of the object points to keep (default: all).

    Returns:
        The `StitchedCloud` (float32 xyz and reflectance; `parent` indexes `points`).

    Raises:
        ValueError naming the argument whose shape or values do not fit the others.
    """
    points, ground = np.asarray(points), np.asarray(ground)
    if points.ndim != 2 or points.shape[1] < 4:
        raise ValueError(f"stitch_points: points must be an (N, 4) array of x, y, z, reflectance, got shape {points.shape}")
    if ground.shape != (len(points),) or ground.dtype != bool:
        raise ValueError(f"stitch_points: ground must be an ({len(points)},) bool mask, got {ground.dtype} {ground.shape}")
    object_index = np.flatnonzero(~ground)
    if xyz is None:
        xyz, source = np.zeros((0, 3), np.float32), np.zeros(0, np.int64)
    xyz, source = np.asarray(xyz), np.asarray(source)
    if xyz.ndim != 2 or xyz.shape[1] != 3 or source.shape != (len(xyz),) or source.dtype.kind not in "iu":
        raise ValueError(f"stitch_points: xyz must be (M, 3) and source (M,) integers, got {xyz.shape} and "
                         f"{source.dtype} {source.shape}")
    if len(source) and (source.min() < 0 or source.max() >= len(object_index)):
        raise ValueError(f"stitch_points: source must index the {len(object_index)} object points "
                         f"(points[~ground]), got values {source.min()} to {source.max()}")
    passing = object_index if kept_objects is None else object_index[np.asarray(kept_objects, dtype=np.int64)]
    ground_index = np.flatnonzero(ground) if keep_ground else np.zeros(0, np.int64)
    parent = np.concatenate([passing, object_index[source], ground_index]).astype(np.int64)
    n_objects = len(passing) + len(xyz)
    stacked = np.concatenate([points[passing, :3], xyz, points[ground_index, :3]]).astype(np.float32)
    generated = np.zeros(len(parent), dtype=bool)
    generated[len(passing):n_objects] = True
    flags = np.zeros(len(parent), dtype=bool)
    flags[n_objects:] = True
    return StitchedCloud(xyz=stacked, reflectance=points[parent, 3].astype(np.float32), generated=generated,
                         ground=flags, parent=parent)


def run(frame: Frame, options: Options = Options()) -> Frame:
    """The stitch stage (`stitch` with `options`).

    Reads: points, ground, tiling, upsampled, parent_slots, upsampled_patches. Adds: cloud.

    Raises:
        StageError("stitch", ...) when the tile stage has not run on the frame, or it has patches
        but the upsample stage has not run.
    """
    frame, options = stage_inputs(frame, options, Options, "stitch")
    frame.check_fields("stitch")
    if frame.tiling is None and not left_untiled(frame):  # it returned the input alone, silently
        raise StageError("stitch", frame.source or frame.key, "the frame has no patches (run stages.tile and "
                                                             "stages.upsample first)")
    if frame.tiling is not None and frame.upsampled is None:
        raise StageError("stitch", frame.source or frame.key, "the frame's patches are not upsampled "
                                                             "(run stages.upsample first)")
    return frame.with_stage_result(cloud=stitch(frame, options.keep_ground, options.keep_input))
