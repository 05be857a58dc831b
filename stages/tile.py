"""Stage 3, tile: cover every non-ground point of a frame with normalised 256-point patches.

Seeds are spread by farthest point sampling, a patch is the K nearest neighbours of its seed, and
each point is owned by the patch, among those containing it, whose seed is nearest (see
`cadpu.patches.overlapping_patches`). Patches are normalised to the unit sphere, as the network
was trained.
"""

from __future__ import annotations

import time

import numpy as np

from cadpu.patches import overlapping_patches

from .frame import Frame, Tiling


def tile_points(xyz: np.ndarray, patch_size: int = 256, overlap: float = 1.0, seed: int = 0) -> Tiling:
    """Patches over a point set.

    Args:
        xyz: (M, 3) points (sensor frame, metres), M >= patch_size.
        patch_size: points per patch (256, as the network was trained).
        overlap: seeds per covering round relative to the uncovered points (see
            `cadpu.patches.overlapping_patches`); more overlap means patch borders, where
            predictions are weakest, are more often owned by a patch whose centre is nearer.
        seed: start of the farthest point sampling.

    Returns:
        The `Tiling` (indices into `xyz`; each point owned by the patch, among those containing
        it, whose seed is nearest).
    """
    return overlapping_patches(np.asarray(xyz, dtype=np.float64), patch_size, overlap, seed)


def run(frame: Frame, patch_size: int = 256, overlap: float = 1.0, seed: int = 0) -> Frame:
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
        tiling = tile_points(objects, patch_size, overlap, seed)
    return frame.with_(tiling=tiling, notes=notes,
                       timings={**frame.timings, "tile": time.perf_counter() - started})
