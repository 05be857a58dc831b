"""Stage 6, snap: put the generated points of the stitched cloud on virtual laser rings between the
scan's real rings, and drop those whose range does not fit the real returns around them.

The geometry is `stages.ring_snap`'s; this module is the stage around it. A frame whose point
order shows no rings (`Frame.rings` is None) passes through with a note.
"""

from __future__ import annotations

import numbers
from typing import Literal

import numpy as np
from pydantic import Field

from .range_image import build_range_image

from . import ring_snap
from .errors import StageError
from .frame import Frame, StitchedCloud, stage_inputs
from .load import read_from_densified_scan
from .options import StageOptions
from .wording import counted

#: The note of a frame read from a scan kitti-pu densified (the load stage's note says so).
DENSIFIED_NO_RINGS_NOTE = ("snap: no laser rings read from a densified scan; generated points not snapped to rings "
                           "nor range-checked")


#: A frame whose snapping drops more than this share of the generated points gets a note: a point
#: order that only looks like rings drops nearly all of them (docs/results.md, "Ring order").
MOST_DROPPED_SHARE = 0.9

#: What becomes of generated points across depth edges (`Options.depth_edges`).
DepthEdges = Literal["half-gap", "drop"]
DEPTH_EDGE_RULES: tuple[str, ...] = DepthEdges.__args__


class Options(StageOptions):
    """Ring snapping and the range check.

    enabled: move every generated point, at its azimuth and range, onto the nearest of the r - 1
        virtual laser rings between the two real rings it lies between, and drop generated points
        above the top or below the bottom ring (`ring_snap.snap_to_virtual_rings`). Needs the scan
        in its stored ring-by-ring order (KITTI's).
    range_tolerance: with snapping, also drop generated points whose range does not fit the two
        real returns above and below them in their azimuth column, give or take this many metres,
        and spread the points of a ring gap on one surface over its virtual rings
        (`ring_snap.snap_and_check`); None does neither. How it was chosen: docs/results.md.
    depth_edges: with the range check, what becomes of generated points in a ring gap whose two
        returns lie on different surfaces (a depth edge, or vegetation): "half-gap" keeps those
        near either return in the half of the gap beside it, "drop" drops them all
        (`ring_snap.fits_ring_ranges`). How it was chosen: docs/results.md.
    depth_edge_max_range: with "half-gap", keep such points only within this range of the sensor
        (metres; None: at any range). A ring gap's height grows with range, and with it the part of
        the gap where which surface a ray hits is a guess. How it was chosen: docs/results.md.
    """

    enabled: bool = True
    range_tolerance: float | None = Field(0.05, ge=0)
    depth_edges: DepthEdges = "half-gap"
    depth_edge_max_range: float | None = Field(None, gt=0)


def snap_cloud(cloud: StitchedCloud, points: np.ndarray, rings: np.ndarray, ratio: int,
               range_tolerance: float | None = 0.05, image: object | None = None,
               depth_edges: DepthEdges = "half-gap", depth_edge_max_range: float | None = None) -> StitchedCloud:
    """The cloud with its generated points on the virtual rings of the scan (input and ground
    points untouched); points outside the rings or failing the range check are dropped and counted.

    Args:
        cloud: a stitched cloud of the scan. points: (N, 4) the scan in stored order, sensor frame.
        rings: (N,) ring id of each scan point. ratio: virtual ring gaps per real gap (r).
        range_tolerance: metres, or None for no range check (see `Options`).
        image: the scan's `RangeImage` over `rings` when already built.
        depth_edges: "half-gap" or "drop" (see `Options`).
        depth_edge_max_range: metres, or None (see `Options`).

    Returns:
        The cloud without the generated points dropped, its `dropped` raised by their count. The
        cloud must be of this scan, in its frame and units (metres): the generated points of
        another cloud fit no ring, and most are dropped without an error (`run` notes it when more
        than `MOST_DROPPED_SHARE` of them are; this function only counts them).
    """
    if ratio is None or isinstance(ratio, bool) or not isinstance(ratio, numbers.Integral) or ratio < 2:
        # 1 passed here and failed in the ring kernels, which need a virtual ring between two real ones
        raise ValueError(f"snap_cloud: needs the upsampling ratio r, a whole number >= 2, got {ratio!r}")
    if depth_edges not in DEPTH_EDGE_RULES:
        raise ValueError(f"snap: depth_edges must be one of {DEPTH_EDGE_RULES}, got {depth_edges!r}")
    if depth_edge_max_range is not None and not depth_edge_max_range > 0:
        raise ValueError(f"snap: depth_edge_max_range must be > 0 metres or None, got {depth_edge_max_range}")
    try:
        tables = ring_snap.ring_tables(points, rings, image=image)  # type: ignore[arg-type]
    except ValueError as error:  # said by the range image it builds: the caller called snap_cloud
        raise ValueError(f"snap_cloud: {error}") from None
    generated = _as_slice(np.flatnonzero(cloud.generated))  # stitch puts them in one block
    if range_tolerance is None:
        snapped, inside = ring_snap.snap_to_virtual_rings(cloud.xyz[generated], tables.elevation, ratio)
    else:
        snapped, inside = ring_snap.snap_and_check(cloud.xyz[generated], tables, ratio, range_tolerance,
                                                   across_edges=depth_edges == "half-gap",
                                                   across_within=np.inf if depth_edge_max_range is None
                                                   else depth_edge_max_range)
    xyz = cloud.xyz.copy()
    xyz[generated] = snapped
    keep = np.ones(len(cloud), dtype=bool)
    keep[generated] = inside
    return cloud.select(keep, xyz=xyz, dropped=int(len(inside) - np.count_nonzero(inside)))


def _as_slice(index: np.ndarray) -> np.ndarray | slice:
    """`index` ((K,) ascending int64) as the slice it spans when it is one run of consecutive
    numbers (a view instead of a gather), else itself."""
    if len(index) and index[-1] - index[0] + 1 == len(index):
        return slice(int(index[0]), int(index[-1]) + 1)
    return index


def range_image_of(frame: Frame) -> Frame:
    """The frame with its range image over its rings built (kept as it is when already there)."""
    if frame.range_image is not None or frame.rings is None:
        return frame
    return frame.with_(range_image=build_range_image(frame.points, frame.rings))


def run(frame: Frame, options: Options = Options()) -> Frame:
    """The snap stage.

    Reads: cloud, points, rings, ratio, range_image (built when absent). Adds: cloud (snapped,
    its `dropped` count raised), range_image; a note when the frame has no rings.

    Raises:
        StageError("snap", ...) when the frame has no cloud (the stitch stage has not run), or when
        the fill stage has run on it (snapping would move and drop the filled ground points).
    """
    frame, options = stage_inputs(frame, options, Options, "snap")
    if options.enabled and frame.cloud is None:
        raise StageError("snap", frame.source or frame.key, "the frame has no stitched cloud (run stages.stitch first)")
    if not options.enabled or not frame.cloud.generated.any():
        return frame
    if (frame.cloud.generated & frame.cloud.ground).any():  # only the fill stage makes these
        raise StageError("snap", frame.source or frame.key, "the cloud holds filled ground points (stages.fill has "
                                                            "run): snap comes before fill, which fills between the "
                                                            "scan's own ground returns")
    frame.check_fields("snap")
    if frame.ratio is None:
        raise StageError("snap", frame.source or frame.key, "the frame has no upsampling ratio (run stages.upsample "
                                                            "first)")
    if frame.rings is None:
        return frame.with_note(DENSIFIED_NO_RINGS_NOTE if read_from_densified_scan(frame) else
                               f"snap: {ring_snap.no_rings_reason(frame.points)}; generated points not snapped to "
                               "rings nor range-checked")
    frame = range_image_of(frame)
    snapped = snap_cloud(frame.cloud, frame.points, frame.rings, frame.ratio, options.range_tolerance,
                         frame.range_image, options.depth_edges, options.depth_edge_max_range)
    generated, dropped = int(np.count_nonzero(frame.cloud.generated)), snapped.dropped - frame.cloud.dropped
    frame = frame.with_stage_result(cloud=snapped)
    if dropped > MOST_DROPPED_SHARE * generated:
        frame = frame.with_note(f"snap: {dropped} of {counted(generated, 'generated point')} "
                                f"({dropped / generated:.0%}) dropped, "
                                "outside the scan's rings or off the ranges of the returns around them; is the "
                                "scan stored in KITTI's ring order, in the sensor's frame (x forward, z up)? (for "
                                "other orders: -c unordered_scans, or snap.enabled false in a library call)")
    return frame
