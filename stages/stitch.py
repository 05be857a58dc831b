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

__all__ = ["Options", "StitchedCloud", "run", "stitch"]


class Options(StageOptions):
    """What goes into the output cloud besides the generated points.

    keep_ground: re-attach the ground points (unchanged).
    keep_input: keep the input object points besides the generated ones (points of patches that
        were not upsampled are kept either way).
    """

    keep_ground: bool = True
    keep_input: bool = True


def stitch(frame: Frame, keep_ground: bool = True, keep_input: bool = True) -> StitchedCloud:
    """Assemble the frame's output cloud.

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
    object_index = np.flatnonzero(~ground_mask)
    ground_index = np.flatnonzero(ground_mask)
    parts_xyz, parts_parent, parts_generated = [], [], []
    upsampled = frame.tiling is not None and frame.upsampled is not None and frame.parent_slots is not None
    passing = object_index
    if upsampled and not keep_input:  # only the points of patches left out by `stages.upsample`
        done = np.zeros(len(frame.tiling.scale), dtype=bool)
        done[slice(None) if frame.upsampled_patches is None else frame.upsampled_patches] = True
        passing = object_index[~done[frame.tiling.owner]]
    parts_xyz.append(points[passing, :3])
    parts_parent.append(passing)
    parts_generated.append(np.zeros(len(passing), dtype=bool))
    if upsampled:
        xyz, source = keep_owned(frame.tiling, frame.upsampled, frame.parent_slots, frame.upsampled_patches)
        parts_xyz.append(xyz)
        parts_parent.append(object_index[source])
        parts_generated.append(np.ones(len(xyz), dtype=bool))
    n_objects = sum(len(p) for p in parts_xyz)
    if keep_ground:
        parts_xyz.append(points[ground_index, :3])
        parts_parent.append(ground_index)
        parts_generated.append(np.zeros(len(ground_index), dtype=bool))
    xyz = np.concatenate(parts_xyz).astype(np.float32) if parts_xyz else np.zeros((0, 3), np.float32)
    parent = np.concatenate(parts_parent).astype(np.int64)
    ground = np.zeros(len(parent), dtype=bool)
    ground[n_objects:] = keep_ground
    return StitchedCloud(xyz=xyz, reflectance=points[parent, 3].astype(np.float32),
                         generated=np.concatenate(parts_generated), ground=ground, parent=parent)


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
