"""Stage 7, fill: put r - 1 points between neighbouring ground returns of each azimuth column.

The network densifies only the non-ground points; this fills the ground between the laser rings
(the geometry is `stages.ground_fill`'s). A frame whose point order shows no rings passes through
with a note.
"""

from __future__ import annotations

import numpy as np

from . import ring_snap
from .errors import StageError
from .frame import Frame, StitchedCloud, stage_inputs
from .ground_fill import fill_ground
from .load import read_from_densified_scan
from .options import StageOptions
from .snap import range_image_of

#: The note of a frame read from a scan kitti-pu densified (the load stage's note says so).
DENSIFIED_NO_RINGS_NOTE = "fill: no laser rings read from a densified scan; ground not filled"


class Options(StageOptions):
    """The ground fill.

    enabled: with `stitch.keep_ground`, put r - 1 points between every two neighbouring ground
        returns of an azimuth column, on the virtual rings, along the line between them
        (`stages.ground_fill`). Needs the scan's ring order.
    """

    enabled: bool = True


def run(frame: Frame, options: Options = Options()) -> Frame:
    """The fill stage.

    Reads: cloud, points, ground, rings, ratio, range_image (built when absent). Adds: cloud (the
    filled points appended, flagged generated and ground), range_image; a note when the frame has
    no rings.

    A frame whose cloud already holds filled ground points (generated and ground: nothing else
    makes them) is returned as it is, so running the stage twice adds nothing.

    Raises:
        StageError("fill", ...) when the frame has no cloud (the stitch stage has not run) or no
        upsampling ratio (the upsample stage has not run: how many virtual rings to fill is unknown).
    """
    frame, options = stage_inputs(frame, options, Options, "fill")
    cloud = frame.cloud
    ratio = frame.ratio
    if not options.enabled:
        return frame
    if cloud is None:
        raise StageError("fill", frame.source or frame.key, "the frame has no stitched cloud (run stages.stitch first)")
    if ratio is None:
        raise StageError("fill", frame.source or frame.key, "the frame has no upsampling ratio (run stages.upsample "
                                                            "first)")
    if ratio <= 1 or not cloud.ground.any() or (cloud.generated & cloud.ground).any():
        return frame
    frame.check_fields("fill")
    if frame.ground is None:
        raise StageError("fill", frame.source or frame.key, "the frame has no ground labels (run stages.ground first)")
    if frame.rings is None:
        return frame.with_note(DENSIFIED_NO_RINGS_NOTE if read_from_densified_scan(frame) else
                               f"fill: {ring_snap.no_rings_reason(frame.points)}; ground not filled")
    frame = range_image_of(frame)
    filled = fill_ground(frame.points, frame.ground, frame.range_image, ratio)
    count = len(filled)
    added = StitchedCloud(xyz=filled.xyz, reflectance=filled.reflectance, generated=np.ones(count, dtype=bool),
                          ground=np.ones(count, dtype=bool), parent=filled.parent)
    return frame.with_stage_result(cloud=cloud.extend(added))
