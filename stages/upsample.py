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


def run(frame: Frame, upsampler: PatchUpsampler) -> Frame:
    """Upsample every patch of the frame in batches.

    Returns:
        The frame with `upsampled` (P, K*r, 3) float32 and `parents` (P, K*r) int64 set, and
        timings["upsample"]; unchanged (bar the timing) when the frame has no tiling.
    """
    started = time.perf_counter()
    if frame.tiling is None:
        return frame.with_(timings={**frame.timings, "upsample": 0.0})
    points, parents = upsampler.upsample_patches(frame.tiling.normalized)
    return frame.with_(upsampled=points, parents=parents,
                       timings={**frame.timings, "upsample": time.perf_counter() - started})
