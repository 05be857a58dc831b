"""A simulated Velodyne HDL-64E and the ring structure of KITTI scans.

The simulated sensor has 64 beams evenly spaced in elevation from +2.0 to -24.8 degrees (the
HDL-64E's field of view as KITTI documents it) and `azimuth_steps` firings per revolution. Rays are
cast against a `cadpu.street.Scene` with Open3D's ray-casting scene; returns carry range noise and
a reflectance from the surface class and the angle of incidence.

Point order follows real KITTI .bin files (checked on sequence 00): ring by ring from the top beam
(+2 degrees) down, and within a ring counter-clockwise with azimuth atan2(y, x) starting just
above 0, through +-180 degrees, back to just below 0. So a new ring starts where the azimuth wraps
from negative to non-negative, which `recover_rings` uses.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .street import REFLECTIVITY, Scene

BEAMS = 64
ELEVATION_TOP_DEG = 2.0
ELEVATION_BOTTOM_DEG = -24.8
MOUNT_HEIGHT = 1.73


@dataclass(frozen=True)
class ScanResult:
    """One simulated scan: points (N, 4) float32 x, y, z, reflectance in the sensor frame;
    ring (N,) int16 beam index (0 = top); labels (N,) int32 semantic class of the surface hit."""

    points: np.ndarray
    ring: np.ndarray
    labels: np.ndarray


def beam_elevations() -> np.ndarray:
    """(64,) beam elevation angles in radians, top beam first."""
    return np.radians(np.linspace(ELEVATION_TOP_DEG, ELEVATION_BOTTOM_DEG, BEAMS))


def simulate_scan(scene: Scene, pose: np.ndarray, seed: int = 0, azimuth_steps: int = 2000,
                  max_range: float = 120.0, range_noise: float = 0.02) -> ScanResult:
    """Cast one revolution of the simulated HDL-64E from `pose` into `scene`.

    Args:
        scene: the world, metres. pose: (4, 4) sensor-to-world transform (z up).
        seed: seed of the range and reflectance noise and the per-ring start jitter.
        azimuth_steps: firings per revolution (about 2000 at 10 Hz for the HDL-64E).

    Returns:
        The `ScanResult` in KITTI point order; rays that hit nothing within `max_range` are dropped.
    """
    from .o3d import o3d

    rng = np.random.default_rng(seed)
    elevation = beam_elevations()
    # Each ring starts slightly above azimuth 0 and turns counter-clockwise, like KITTI's.
    start = rng.uniform(0.0, 2 * np.pi / azimuth_steps, BEAMS)
    azimuth = start[:, None] + np.arange(azimuth_steps)[None, :] * (2 * np.pi / azimuth_steps)
    azimuth = np.where(azimuth > np.pi, azimuth - 2 * np.pi, azimuth)
    cos_el = np.cos(elevation)[:, None]
    directions = np.stack([cos_el * np.cos(azimuth), cos_el * np.sin(azimuth),
                           np.broadcast_to(np.sin(elevation)[:, None], azimuth.shape)], -1).reshape(-1, 3)
    rotation, origin = pose[:3, :3], pose[:3, 3]
    world_directions = directions @ rotation.T
    rays = np.c_[np.broadcast_to(origin, world_directions.shape), world_directions].astype(np.float32)

    raycaster = o3d.t.geometry.RaycastingScene()
    raycaster.add_triangles(o3d.core.Tensor(scene.vertices.astype(np.float32)),
                            o3d.core.Tensor(scene.triangles.astype(np.uint32)))
    hits = raycaster.cast_rays(o3d.core.Tensor(rays))
    distance = hits["t_hit"].numpy().astype(np.float64)
    triangle = hits["primitive_ids"].numpy().astype(np.int64)
    normals = hits["primitive_normals"].numpy().astype(np.float64)
    keep = np.isfinite(distance) & (distance < max_range)
    distance = distance[keep] + rng.normal(scale=range_noise, size=int(keep.sum()))
    local = directions[keep] * distance[:, None]
    labels = scene.labels[triangle[keep]]
    incidence = np.abs((normals[keep] * world_directions[keep]).sum(1))
    reflectance = np.clip(REFLECTIVITY[labels] * (0.5 + 0.5 * incidence) + rng.normal(scale=0.03, size=len(labels)),
                          0.0, 0.99)
    ring = np.repeat(np.arange(BEAMS, dtype=np.int16), azimuth_steps)[keep]
    points = np.c_[local, reflectance].astype(np.float32)
    return ScanResult(points, ring, labels.astype(np.int32))


def recover_rings(points: np.ndarray) -> np.ndarray:
    """Ring (laser) index of every point of a scan stored in KITTI order.

    A ring starts where the azimuth wraps from negative to non-negative near 0 degrees; a wrap
    counts only after the ring has passed the +-180 degree side, so jitter around 0 (or around the
    seam at +-180 degrees) does not split a ring. Gives 64 rings on each of the six real scans
    of KITTI odometry sequence 00 in ../shared/data.

    Args:
        points: (N, 3+) in KITTI order.

    Returns:
        (N,) int64 ring numbers 0, 1, ... (0 = the first ring stored, the top beam in KITTI).
    """
    azimuth = np.arctan2(points[:, 1], points[:, 0])
    step = np.diff(azimuth)
    # near 0 only: -180 -> +180 jitter at the seam behind the sensor is not a new ring
    wraps = np.flatnonzero((azimuth[:-1] < 0) & (azimuth[1:] >= 0) & (np.abs(step) < np.pi / 2)) + 1
    half_turns = np.flatnonzero((azimuth[:-1] > np.pi / 2) & (azimuth[1:] < -np.pi / 2)) + 1
    starts = [0]
    for wrap in wraps:
        # accept the wrap if a half turn happened since the last ring start
        passed = np.searchsorted(half_turns, wrap) - np.searchsorted(half_turns, starts[-1] + 1)
        if passed > 0:
            starts.append(int(wrap))
    ring = np.zeros(len(points), dtype=np.int64)
    ring[np.asarray(starts[1:], dtype=np.int64)] = 1
    return np.cumsum(ring)


def keep_rings(points: np.ndarray, rings: np.ndarray, every: int = 4, offset: int = 0) -> np.ndarray:
    """The points of rings offset, offset + every, ... (64 -> 16 beams with every = 4)."""
    return points[(rings - offset) % every == 0]
