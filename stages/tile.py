"""Stage 3, tile: cover every non-ground point of a frame with normalised 256-point patches.

Two methods (see `cadpu.patches`):
- "partition" (default): a balanced k-d partition into cells of patch_size / overlap points; a
  cell's patch is the cell plus its nearest outside points; the cell owns its points.
- "fps": seeds spread by farthest point sampling in rounds over the uncovered points, a patch is
  the K nearest neighbours of its seed, each point owned by the containing patch whose seed is
  nearest. On LiDAR scans it needs about twice as many patches for the same overlap.

Patches are normalised to the unit sphere, as the network was trained.

Vertical scale: a spinning LiDAR samples a surface far more densely along a ring than across
rings (KITTI's HDL-64E: 0.18 degree between points of a ring, 0.3-0.5 degree between rings, and
4x that when only every fourth ring is kept). The network spreads a point's copies over its
local tangent plane in proportion to the spacing of its neighbours, so on such rows of points
the copies stay close to their own ring. With `vertical_scale` < 1, z is multiplied by it before
the frame is cut and normalised (the rows move closer together, the patch looks more evenly
sampled) and divided by it again when the patches are put back (`cadpu.patches.keep_owned`),
which stretches the copies across the gaps between rings. Patch radii (`Tiling.scale`) are then
measured in the scaled coordinates.
"""

from __future__ import annotations

import numbers
from dataclasses import replace
from typing import Literal

import numpy as np
from pydantic import Field

from cadpu.patches import overlapping_patches, partitioned_patches

from .errors import InputError
from .frame import Frame, Tiling, stage_inputs
from .options import StageOptions
from .wording import counted


#: The tiling methods `tile_points` knows.
TILING_METHODS = ("partition", "fps")

#: The range of `overlap` (patch points per owned point).
MIN_OVERLAP, MAX_OVERLAP = 1.0, 8.0
#: The largest `vertical_scale`: z stretched 1,000 times already tiles by height alone, and a
#: far larger factor overflowed the scaled coordinates to inf.
MAX_VERTICAL_SCALE = 1000.0
#: The fewest points a patch may hold (the network's neighbourhoods: `Options.patch_size`).
MIN_PATCH_SIZE = 16
#: Coordinates beyond this (metres) are not a scan's or a map's (UTM northings reach 1e7 m): the
#: output's float32 coordinates would be about a metre apart there, and far beyond it the patch
#: geometry breaks down.
MAX_COORDINATE_M = 1e7


class Options(StageOptions):
    """Tiling of the non-ground points into patches (arguments of `tile_points`; how the default
    `vertical_scale` was chosen: docs/results.md)."""

    method: Literal["partition", "fps"] = "partition"
    patch_size: int = Field(256, ge=MIN_PATCH_SIZE)
    overlap: float = Field(1.0, ge=MIN_OVERLAP, le=MAX_OVERLAP)
    seed: int = Field(0, ge=0)
    vertical_scale: float = Field(0.15, gt=0.0, le=MAX_VERTICAL_SCALE)


def tile_points(xyz: np.ndarray, patch_size: int = 256, overlap: float = 1.0, seed: int = 0,
                method: str = "partition", vertical_scale: float = 0.15) -> Tiling:
    """Patches over a point set.

    Args:
        xyz: (M, 3) points (sensor frame, metres), M >= patch_size.
        patch_size: points per patch (256, as the network was trained).
        overlap: >= 1, how much patches overlap. "partition": patch points per owned point (1:
            cells of at most 256 points, each patch its cell plus the nearest outside points up
            to 256; 4/3: cells of at most 192). "fps": seeds per covering round
            relative to the uncovered points. More overlap gives more patches, and patch borders,
            where predictions are weakest, are less often the owners' points.
        seed: start of the farthest point sampling ("fps" only).
        method: one of TILING_METHODS.
        vertical_scale: > 0, factor z is multiplied by before tiling (see the module docstring);
            1 tiles the points as they are.

    Returns:
        The `Tiling` (indices into `xyz`, and the patch owning each point, which contains it),
        with `axis_scale` (1, 1, vertical_scale).
    """
    if method not in TILING_METHODS:
        raise ValueError(f"tile: unknown method {method!r}; expected one of {TILING_METHODS}")
    if not MIN_OVERLAP <= overlap <= MAX_OVERLAP:  # as `Options` bounds it: more makes thousands of patches
        raise ValueError(f"tile: overlap must be in [{MIN_OVERLAP:g}, {MAX_OVERLAP:g}], got {overlap}")
    if not 0 < vertical_scale <= MAX_VERTICAL_SCALE:
        raise ValueError(f"tile: vertical_scale must be > 0 and at most {MAX_VERTICAL_SCALE:g}, got {vertical_scale}")
    if isinstance(patch_size, bool) or not isinstance(patch_size, numbers.Integral) or patch_size < MIN_PATCH_SIZE:
        raise ValueError(f"tile: patch_size must be a whole number of at least {MIN_PATCH_SIZE}, got {patch_size!r}")
    if isinstance(seed, bool) or not isinstance(seed, numbers.Integral) or seed < 0:
        # numpy's refusal of a negative one was taken, below, for a fault of the scan's
        raise ValueError(f"tile: seed must be a whole number of at least 0, got {seed!r}")
    given = np.asarray(xyz)
    if given.dtype.kind not in "fiu":  # booleans and strings converted silently to coordinates
        raise ValueError(f"tile: xyz must hold real numbers (x, y, z in metres), got an array of {given.dtype}")
    xyz = given.astype(np.float64, copy=False)
    if xyz.ndim != 2 or xyz.shape[1] != 3:
        raise ValueError(f"tile: xyz must be an (M, 3) array of x, y, z, got shape {xyz.shape} "
                         "(give points[:, :3] of an (N, 4) scan)")
    if not np.isfinite(xyz).all():
        raise ValueError(f"tile: xyz holds {counted(int((~np.isfinite(xyz).all(axis=1)).sum()), 'point')} with NaN or "
                         "infinite coordinates")
    if len(xyz) and (farthest := float(np.abs(xyz).max())) > MAX_COORDINATE_M:
        raise ValueError(f"tile: a coordinate of {farthest:.3g} m, beyond {MAX_COORDINATE_M:g} m: not metres in a "
                         "sensor or map frame")
    axis_scale = np.array([1.0, 1.0, vertical_scale])
    scaled = xyz * axis_scale
    try:
        if method == "partition":
            cover = partitioned_patches(scaled, patch_size, overlap)
        else:
            cover = overlapping_patches(scaled, patch_size, overlap, seed)
    except ValueError as error:  # too few points, an overlap out of range: said by cadpu.patches
        raise ValueError(f"tile: {error}") from None
    return replace(cover, axis_scale=axis_scale)


#: How the note of a frame with too few object points to tile begins (`left_untiled`).
UNTILED_NOTE_START = "tile: not upsampled: "


def left_untiled(frame: Frame) -> bool:
    """Whether the tile stage ran on `frame` and left it without patches (too few object points)."""
    return frame.tiling is None and any(note.startswith(UNTILED_NOTE_START) for note in frame.notes)


def run(frame: Frame, options: Options = Options()) -> Frame:
    """The tile stage: cut the frame's object (non-ground) points into patches (`tile_points`).

    Reads: points, ground (all points are objects when None, with a note: the ground stage has not
    run). Adds: tiling (None, with a note, when there are fewer object points than one patch: they
    pass through unchanged, not an error).
    """
    frame, options = stage_inputs(frame, options, Options, "tile")
    frame.check_fields("tile")
    if frame.ground is None:
        objects = frame.points[:, :3]
        frame = frame.with_note("tile: no ground labels (stages.ground has not run): every point tiled as an object")
    else:
        objects = frame.points[~frame.ground, :3]
    if len(objects) < options.patch_size:
        return frame.with_stage_result(tiling=None).with_note(
            f"{UNTILED_NOTE_START}{counted(len(objects), 'object point')}, fewer than one patch of {options.patch_size}")
    try:
        tiling = tile_points(objects, options.patch_size, options.overlap, options.seed, options.method,
                             options.vertical_scale)
    except ValueError as error:  # coordinates no sensor gives: the frame's, named, not a bug of the chain's
        raise InputError("tile", frame.source or frame.key, str(error).removeprefix("tile: ")) from None
    return frame.with_stage_result(tiling=tiling)
