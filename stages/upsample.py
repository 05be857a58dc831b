"""Stage 4, upsample: run a frame's normalised patches through CAD-PU (`cadpu.inference.Upsampler`)."""

from __future__ import annotations

import time
from typing import Protocol

import numpy as np

from .frame import Frame


class PatchUpsampler(Protocol):
    """What this stage needs of a model: `cadpu.inference.Upsampler` provides it."""

    ratio: int

    def upsample_patches(self, patches: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(B, K, 3) float32 normalised patches -> (B, K*r, 3) points, (B, K*r) int64 parent slots."""
        ...


def run(frame: Frame, upsampler: PatchUpsampler, max_patch_radius: float | None = None) -> Frame:
    """Upsample the frame's patches in batches.

    Args:
        frame: a frame through `stages.tile`.
        upsampler: the model.
        max_patch_radius: patches whose radius (`tiling.scale`: metres, in the tiled coordinates,
            whose z may be scaled, see `stages.tile`) exceeds this are not upsampled; their points
            pass through as they are. 256 points that far apart are scattered returns (far away,
            or foreground and background mixed), between which there is no surface to recover.
            None upsamples every patch.

    Returns:
        The frame with `upsampled` (S, K*r, 3) float32, `parents` (S, K*r) int64 and
        `upsampled_patches` (S,) int64 (which patches of the tiling those rows are) set, a note
        when patches were left out, and timings["upsample"]; unchanged (bar the timing) when the
        frame has no tiling.
    """
    started = time.perf_counter()
    if frame.tiling is None:
        return frame.with_(timings={**frame.timings, "upsample": 0.0})
    tiling, notes = frame.tiling, frame.notes
    chosen = np.arange(len(tiling.scale))
    if max_patch_radius is not None:
        chosen = np.flatnonzero(tiling.scale <= max_patch_radius)
        if len(chosen) < len(tiling.scale):
            notes = (*notes, f"upsample: {len(tiling.scale) - len(chosen)} of {len(tiling.scale)} patches wider "
                             f"than {max_patch_radius:g} m not upsampled")
    if len(chosen):
        points, parents = upsampler.upsample_patches(tiling.normalized[chosen])
    else:
        width = tiling.normalized.shape[1] * upsampler.ratio
        points, parents = np.zeros((0, width, 3), np.float32), np.zeros((0, width), np.int64)
    return frame.with_(upsampled=points, parents=parents, upsampled_patches=chosen, notes=notes,
                       timings={**frame.timings, "upsample": time.perf_counter() - started})
