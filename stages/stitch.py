"""Stage 5, stitch: put the upsampled patches back into the sensor frame as one point cloud.

For every object point, the points generated from it in the patch that owns it are kept (a mask
over all generated points: linear time, no sampling over the whole frame). Generated points take
their parent's reflectance. Ground points are re-attached unchanged.

`run` also puts the generated points on virtual laser rings when asked (`stages.ring_snap`), and
then drops those whose range does not fit the two real returns around them in their azimuth
column (`ring_snap.fits_ring_ranges`); and it fills the ground between the rings when asked
(`stages.ground_fill`). The scan's rings are read from its point order; a frame whose order shows
none is left unsnapped, unfiltered and unfilled, with a note.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from cadpu.patches import keep_owned
from cadpu.range_image import RangeImage, build_range_image

from . import ring_snap
from .frame import Frame
from .ground_fill import fill_ground as fill_ground_between_rings

#: The note of a frame whose point order shows no laser rings when snapping or ground filling was asked for.
NO_RINGS_NOTE = ("stitch: the point order shows no laser rings; generated points not snapped to rings nor "
                 "range-checked, ground not filled (for such scans: -c configs/unordered_scans.yaml)")


@dataclass(frozen=True)
class StitchedCloud:
    """The output cloud of one frame (Q points).

    Attributes:
        xyz: (Q, 3) float32, sensor frame, metres.
        reflectance: (Q,) float32.
        generated: (Q,) bool, True for points made by the network or filled in on the ground.
        ground: (Q,) bool, True for ground points (input ones, and those `stages.ground_fill` adds).
        parent: (Q,) int64 index into the frame's input points of the point each came from
            (itself for input points; the upper of the two returns for filled ground points).
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


def stitch(frame: Frame, keep_ground: bool = True, keep_input: bool = True) -> StitchedCloud:
    """Assemble the frame's output cloud.

    Args:
        frame: a frame through `stages.upsample` (or one without tiling: its points pass through).
        keep_ground: re-attach the ground points (unchanged).
        keep_input: keep the input object points besides the generated ones (points of patches
            that were not upsampled are kept either way).

    Returns:
        The `StitchedCloud`: input object points (if kept), then generated points, then ground.
    """
    points = frame.points
    ground_mask = frame.ground if frame.ground is not None else np.zeros(len(points), dtype=bool)
    object_index = np.flatnonzero(~ground_mask)
    ground_index = np.flatnonzero(ground_mask)
    parts_xyz, parts_parent, parts_generated = [], [], []
    upsampled = frame.tiling is not None and frame.upsampled is not None and frame.parents is not None
    passing = object_index
    if upsampled and not keep_input:  # only the points of patches left out by `stages.upsample`
        done = np.zeros(len(frame.tiling.scale), dtype=bool)
        done[slice(None) if frame.upsampled_patches is None else frame.upsampled_patches] = True
        passing = object_index[~done[frame.tiling.owner]]
    parts_xyz.append(points[passing, :3])
    parts_parent.append(passing)
    parts_generated.append(np.zeros(len(passing), dtype=bool))
    if upsampled:
        xyz, source = keep_owned(frame.tiling, frame.upsampled, frame.parents, frame.upsampled_patches)
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


def run(frame: Frame, keep_ground: bool = True, keep_input: bool = True,
        snap_to_rings: bool = False, range_tolerance: float | None = None,
        fill_ground: bool = False, ratio: int | None = None) -> tuple[Frame, StitchedCloud]:
    """The stitch stage: `stitch`, then (optionally) `snap_generated` and the ground fill.

    Args:
        frame: a frame through `stages.upsample`, its `points` in their stored (ring) order.
        keep_ground, keep_input: see `stitch`.
        snap_to_rings: move the generated points onto virtual rings between the scan's rings.
        range_tolerance: with `snap_to_rings`, also drop generated points whose range does not
            fit the real returns above and below them, with this tolerance in metres
            (`ring_snap.fits_ring_ranges`); None keeps them.
        fill_ground: with `keep_ground`, add r - 1 points between neighbouring ground returns of
            each azimuth column (`stages.ground_fill`), flagged generated and ground.
        ratio: the upsampling ratio r (None: read from the frame's upsampled patches; a frame
            without any then gets no ground fill).

    Returns:
        The frame (with a note when the point order shows no rings to snap to or fill between)
        and its output cloud.
    """
    cloud = stitch(frame, keep_ground=keep_ground, keep_input=keep_input)
    frame_ratio = upsampling_ratio(frame)
    ratio = ratio or frame_ratio
    snap = snap_to_rings and bool(cloud.generated.any())
    fill = fill_ground and ratio is not None and ratio > 1 and bool(cloud.ground.any())
    if not (snap or fill):
        return frame, cloud
    rings = ring_snap.scan_rings(frame.points)
    if rings is None:
        return frame.with_(notes=frame.notes + (NO_RINGS_NOTE,)), cloud
    image = build_range_image(frame.points, rings)
    if snap:
        cloud = _snap(cloud, frame, rings, image, frame_ratio, range_tolerance)
    if fill:
        cloud = _add_ground_fill(cloud, frame, image, ratio)
    return frame, cloud


def upsampling_ratio(frame: Frame) -> int | None:
    """Generated points per patch point of the frame's upsampled patches (None: none upsampled)."""
    if frame.upsampled is None or frame.tiling is None:
        return None
    return frame.upsampled.shape[1] // frame.tiling.point_index.shape[1]


def snap_generated(cloud: StitchedCloud, frame: Frame,
                   range_tolerance: float | None = None) -> tuple[StitchedCloud, str | None]:
    """Put the cloud's generated points on the virtual rings of the frame's scan.

    The ratio r (virtual ring gaps per real gap) is the frame's upsampling ratio. Generated points
    outside the scan's rings (above the top or below the bottom ring of their azimuth) are
    dropped, and so are those whose range does not fit the returns above and below them when a
    `range_tolerance` (metres) is given (and then the points of a ring gap on one surface are spread
    over its virtual rings, `ring_snap.snap_and_check`); input and ground points are untouched.

    Args:
        cloud: the frame's stitched cloud. frame: the frame it came from (its `points` in stored
            order, its `tiling` and `upsampled` filled in). range_tolerance: see `run`.

    Returns:
        The snapped cloud, and None, or (when the frame's point order shows no rings, see
        `ring_snap.scan_rings`) the cloud unchanged and `NO_RINGS_NOTE`.
    """
    rings = ring_snap.scan_rings(frame.points)
    if rings is None:
        return cloud, NO_RINGS_NOTE
    image = build_range_image(frame.points, rings)
    return _snap(cloud, frame, rings, image, upsampling_ratio(frame), range_tolerance), None


def _snap(cloud: StitchedCloud, frame: Frame, rings: np.ndarray, image: RangeImage, ratio: int,
          range_tolerance: float | None) -> StitchedCloud:
    """`snap_generated` on a scan whose rings and range image are known."""
    tables = ring_snap.ring_tables(frame.points, rings, image=image)
    generated = np.flatnonzero(cloud.generated)
    if range_tolerance is None:
        snapped, inside = ring_snap.snap_to_virtual_rings(cloud.xyz[generated], tables.elevation, ratio)
    else:
        snapped, inside = ring_snap.snap_and_check(cloud.xyz[generated], tables, ratio, range_tolerance)
    xyz = cloud.xyz.copy()
    xyz[generated] = snapped
    keep = np.ones(len(cloud), dtype=bool)
    keep[generated[~inside]] = False
    return StitchedCloud(xyz=xyz[keep], reflectance=cloud.reflectance[keep], generated=cloud.generated[keep],
                         ground=cloud.ground[keep], parent=cloud.parent[keep],
                         dropped=cloud.dropped + int((~inside).sum()))


def _add_ground_fill(cloud: StitchedCloud, frame: Frame, image: RangeImage, ratio: int) -> StitchedCloud:
    """The cloud with the ground fill of the frame's scan appended (generated and ground)."""
    filled = fill_ground_between_rings(frame.points, frame.ground, image, ratio)
    count = len(filled)
    return StitchedCloud(xyz=np.concatenate([cloud.xyz, filled.xyz]),
                         reflectance=np.concatenate([cloud.reflectance, filled.reflectance]),
                         generated=np.concatenate([cloud.generated, np.ones(count, dtype=bool)]),
                         ground=np.concatenate([cloud.ground, np.ones(count, dtype=bool)]),
                         parent=np.concatenate([cloud.parent, filled.parent]), dropped=cloud.dropped)
