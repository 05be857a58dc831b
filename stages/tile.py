"""Stage 3, tile: cover every non-ground point of a frame with normalised 256-point patches.

Two methods (see `cadpu.patches`):
- "partition" (default): a balanced k-d partition into cells of patch_size / overlap points; a
  cell's patch is the cell plus its nearest outside points; the cell owns its points.
- "fps": seeds spread by farthest point sampling in rounds over the uncovered points, a patch is
  the K nearest neighbours of its seed, each point owned by the containing patch whose seed is
  nearest. On LiDAR scans it needs about twice as many patches for the same overlap.

Patches are normalised to the unit sphere, as the network was trained.
"""

from __future__ import annotations

import time

import numpy as np

from cadpu.patches import overlapping_patches, partitioned_patches

from .frame import Frame, Tiling


#: The tiling methods `tile_points` knows.
METHODS = ("partition", "fps")


def tile_points(xyz: np.ndarray, patch_size: int = 256, overlap: float = 1.0, seed: int = 0,
                method: str = "partition") -> Tiling:
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
        method: one of METHODS.

    Returns:
        The `Tiling` (indices into `xyz`, and the patch owning each point, which contains it).
    """
    xyz = np.asarray(xyz, dtype=np.float64)
    if method == "partition":
        return partitioned_patches(xyz, patch_size, overlap)
    if method == "fps":
        return overlapping_patches(xyz, patch_size, overlap, seed)
    raise ValueError(f"tile: unknown method {method!r}; expected one of {METHODS}")


def run(frame: Frame, patch_size: int = 256, overlap: float = 1.0, seed: int = 0,
        method: str = "partition") -> Frame:
    """Tile the frame's object (non-ground) points.

    A frame with fewer than `patch_size` object points gets no tiling and a note saying so (its
    points pass through unchanged); that is not an error.

    Returns:
        The frame with `tiling` set (or None) and timings["tile"].
    """
    started = time.perf_counter()
    objects = frame.points[:, :3] if frame.ground is None else frame.points[~frame.ground, :3]
    tiling, notes = None, frame.notes
    if len(objects) < patch_size:
        notes = (*notes, f"tile: {len(objects)} object points, fewer than one patch of {patch_size}: "
                         "not upsampled")
    else:
        tiling = tile_points(objects, patch_size, overlap, seed, method)
    return frame.with_(tiling=tiling, notes=notes,
                       timings={**frame.timings, "tile": time.perf_counter() - started})
