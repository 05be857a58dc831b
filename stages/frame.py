"""The record that travels through the stages: one LiDAR scan plus what each stage adds."""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from cadpu.patches import PatchCover as Tiling  # patches over a frame's object points

__all__ = ["Frame", "Tiling"]


@dataclass(frozen=True)
class Frame:
    """One scan and its provenance; stages return a copy with their own fields filled in.

    Attributes:
        points: (N, 4) float32 x, y, z, reflectance in the sensor (Velodyne) frame, metres, z up.
        dataset: "raw", "odometry" or "bin".
        sequence: drive name (raw, e.g. "2011_09_26_drive_0001_sync"), sequence id
            (odometry, e.g. "00") or folder name (bin).
        index: frame index within the drive or sequence.
        timestamp: seconds since the first frame of the drive/sequence, or None when unknown.
        source: path of the file the points were read from.
        calib: calibration matrices by name (e.g. "T_cam0_velo"), empty when the dataset has none.
        pose: (4, 4) float64 sensor pose in the world/odometry frame, or None when unknown.
        ground: (N,) bool, True for ground points (added by `stages.ground`).
        tiling: patches over the non-ground points (added by `stages.tile`).
        upsampled: (P, K*r, 3) float32 normalised generated points (added by `stages.upsample`).
        parents: (P, K*r) int64, slot (0..K-1) of the patch point each generated point came from.
        upsampled_patches: (S,) int64, the tiling's patches that `upsampled` and `parents` hold,
            row by row, when only S of them were upsampled; None means all of them, in order.
        timings: seconds spent per stage name.
        notes: non-fatal remarks by stages (e.g. "fewer than 256 object points: not upsampled").
    """

    points: np.ndarray
    dataset: str
    sequence: str
    index: int
    timestamp: float | None = None
    source: str = ""
    calib: dict[str, np.ndarray] = field(default_factory=dict)
    pose: np.ndarray | None = None
    ground: np.ndarray | None = None
    tiling: Tiling | None = None
    upsampled: np.ndarray | None = None
    parents: np.ndarray | None = None
    upsampled_patches: np.ndarray | None = None
    timings: dict[str, float] = field(default_factory=dict)
    notes: tuple[str, ...] = ()

    @property
    def key(self) -> str:
        """A name unique within a run: dataset/sequence/index."""
        return f"{self.dataset}/{self.sequence}/{self.index:06d}"

    def with_(self, **changes: Any) -> "Frame":
        """Return a copy with the given fields replaced."""
        return replace(self, **changes)
