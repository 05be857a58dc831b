"""Densify the ground between laser rings, where the network does not go.

The pipeline cuts patches from the non-ground points only (`stages.tile`), so without this step the
ground of an output scan keeps the sensor's ring spacing while everything on it is r times denser.
The ground is the one part of a scan where a straight line between two returns of neighbouring
rings is the surface, so it is filled geometrically, in the range image:

- rings are ordered by elevation, and every two returns that are neighbours in an azimuth column,
  both labelled ground, are joined when the line between them rises or falls by at most
  `MAX_SLOPE_DEG` (a kerb or a step between them is not bridged). The range-image rule of
  `stages.range_image.surface_gap_limit` is not used: it refuses surfaces seen at more than 75
  degrees from their normal, which is all the ground beyond about 6 m from a car-roof sensor;
- between them, r - 1 points are put where the rays of the r - 1 virtual rings cross the straight
  line from one return to the other: virtual ring k at elevation e_a + (e_b - e_a) k / r, from the
  two returns' own elevations (the virtual rings of `stages.ring_snap`), so a flat ground gets
  points exactly on it, at the ring spacing a denser laser column would give;
- azimuth and reflectance are interpolated along the same line.

Nothing is put across a step, where a ring has no ground return, or beyond the top and bottom
rings.

Frames: sensor frame, x forward, y left, z up, metres; azimuth atan2(y, x), elevation
asin(z / range), radians.
"""

from __future__ import annotations

import numbers
from dataclasses import dataclass

import numpy as np
from numba import njit

from .range_image import RangeImage
from .wording import counted

#: Steepest line between two ground returns that is filled, degrees from horizontal. Roads are
#: flatter (a 10 % grade is 5.7 degrees); a 15 cm kerb between returns under 1 m apart is steeper.
MAX_SLOPE_DEG = 8.0


@dataclass(frozen=True)
class GroundFill:
    """Points inserted between ground returns (M of them).

    Attributes:
        xyz: (M, 3) float32, sensor frame, metres.
        reflectance: (M,) float32, interpolated between the two returns.
        parent: (M,) int64 index into the scan's points of the upper return of each point's pair.
    """

    xyz: np.ndarray
    reflectance: np.ndarray
    parent: np.ndarray

    def __len__(self) -> int:
        return int(self.xyz.shape[0])


def fill_ground(points: np.ndarray, ground: np.ndarray, image: RangeImage, ratio: int,
                max_slope_deg: float = MAX_SLOPE_DEG) -> GroundFill:
    """Insert `ratio - 1` points between every two neighbouring ground returns of one column.

    Args:
        points: (N, 4) scan, x, y, z (sensor frame, metres), reflectance, in the order `image`
            indexes. ground: (N,) bool ground labels (`stages.ground`).
        image: the scan's range image (`stages.range_image.build_range_image`).
        ratio: ring gaps per real gap (the upsampling ratio r >= 1; 1 inserts nothing).
        max_slope_deg: steepest line between two returns that is filled, degrees in [0, 90).

    Returns:
        The `GroundFill`, pairs in (ring, column) order, the points of a pair from the upper ring down.

    Raises:
        ValueError: `points` not (N, 4) finite, `image` not of these N points, `ground` not (N,) bool,
            ratio < 1, or a slope outside [0, 90).
    """
    points = np.asarray(points)
    if points.ndim != 2 or points.shape[1] != 4:
        raise ValueError(f"fill_ground: points must be (N, 4) x, y, z, reflectance, got shape {points.shape}")
    if not np.isfinite(points).all():  # a NaN reflectance was copied into the fill points (a trial)
        bad = int((~np.isfinite(points)).any(axis=1).sum())
        raise ValueError(f"fill_ground: points hold {counted(bad, 'point')} with NaN or infinite values")
    if not isinstance(image, RangeImage):  # None when the scan had no rings: an AttributeError before
        raise ValueError(f"fill_ground: image must be the scan's RangeImage (stages.range_image.build_range_image), "
                         f"got {type(image).__name__}")
    if len(image.range) != len(points):
        raise ValueError(f"fill_ground: the range image is of a scan of {len(image.range)} points, not of these "
                         f"{len(points)} (build it with build_range_image(points, rings))")
    ground = np.asarray(ground)
    if ground.shape != (len(points),) or ground.dtype != bool:
        raise ValueError(f"fill_ground: ground must be ({len(points)},) bool, got {ground.dtype} {ground.shape}")
    if isinstance(ratio, bool) or not isinstance(ratio, numbers.Integral) or ratio < 1:
        # a fractional ratio gave xyz and parents of different lengths
        raise ValueError(f"fill_ground: ratio must be a whole number >= 1, got {ratio!r}")
    if not 0.0 <= max_slope_deg < 90.0:
        raise ValueError(f"fill_ground: max_slope_deg must be in [0, 90), got {max_slope_deg}")
    xyz = np.asarray(points)[:, :3].astype(np.float64)
    planar_distance = np.hypot(xyz[:, 0], xyz[:, 1])
    upper, lower = _ground_pairs(xyz, planar_distance, ground, image, max_slope_deg)
    if ratio == 1 or len(upper) == 0:
        return GroundFill(np.zeros((0, 3), np.float32), np.zeros(0, np.float32), np.zeros(0, np.int64))
    t = np.arange(1, ratio, dtype=np.float64) / ratio  # (ratio-1,)
    elevation_a, elevation_b = image.point_elevation[upper], image.point_elevation[lower]
    elevation = elevation_a[:, None] + (elevation_b - elevation_a)[:, None] * t  # the virtual rings' rays
    turn = np.angle(np.exp(1j * (image.azimuth[lower] - image.azimuth[upper])))  # wrapped into (-pi, pi]
    reflectance = np.asarray(points)[:, 3].astype(np.float64)
    azimuth, planar, height, shade = _along_segments(xyz, planar_distance, reflectance, upper, lower, t,
                                                     np.cos(elevation), np.sin(elevation), image.azimuth, turn)
    inserted = _to_xyz(planar * np.cos(azimuth), planar * np.sin(azimuth), height)
    return GroundFill(xyz=inserted, reflectance=shade.reshape(-1).astype(np.float32),
                      parent=np.repeat(upper, ratio - 1).astype(np.int64))


@njit(cache=True, nogil=True)
def _along_segments(xyz: np.ndarray, planar_distance: np.ndarray, reflectance: np.ndarray, upper: np.ndarray,
                    lower: np.ndarray, t: np.ndarray, ray_planar: np.ndarray, ray_up: np.ndarray,
                    azimuth: np.ndarray, turn: np.ndarray) -> tuple:  # pragma: no cover - compiled
    """For each pair p (upper[p] -> lower[p]) and virtual ring k: where the ray of elevation
    cosine/sine ray_planar[p, k], ray_up[p, k] crosses the segment between the two returns, in the
    column's vertical plane (horizontal distance, height), as the fraction u along the segment
    (t[k] where the ray runs parallel to it, clipped to [0, 1]); returns (P, K) float64 azimuth,
    horizontal distance, height and reflectance there, each interpolated linearly by u."""
    pairs, rings = ray_planar.shape
    out_azimuth = np.empty((pairs, rings), np.float64)
    out_planar = np.empty((pairs, rings), np.float64)
    out_height = np.empty((pairs, rings), np.float64)
    out_shade = np.empty((pairs, rings), np.float64)
    for p in range(pairs):
        a, b = upper[p], lower[p]
        planar_a, height_a = planar_distance[a], xyz[a, 2]
        segment_planar, segment_up = planar_distance[b] - planar_a, xyz[b, 2] - height_a
        for k in range(rings):
            denominator = segment_planar * ray_up[p, k] - segment_up * ray_planar[p, k]
            numerator = planar_a * ray_up[p, k] - height_a * ray_planar[p, k]
            u = -numerator / denominator if abs(denominator) > 1e-12 else t[k]
            u = min(max(u, 0.0), 1.0)
            out_azimuth[p, k] = azimuth[a] + turn[p] * u
            out_planar[p, k] = planar_a + segment_planar * u
            out_height[p, k] = height_a + segment_up * u
            out_shade[p, k] = reflectance[a] + (reflectance[b] - reflectance[a]) * u
    return out_azimuth, out_planar, out_height, out_shade


@njit(cache=True, nogil=True)
def _to_xyz(x: np.ndarray, y: np.ndarray, z: np.ndarray) -> np.ndarray:  # pragma: no cover - compiled
    """(P * K, 3) float32 points from (P, K) float64 coordinates, row by row."""
    pairs, rings = x.shape
    out = np.empty((pairs * rings, 3), np.float32)
    for p in range(pairs):
        for k in range(rings):
            row = p * rings + k
            out[row, 0], out[row, 1], out[row, 2] = x[p, k], y[p, k], z[p, k]
    return out


def _ground_pairs(xyz: np.ndarray, planar_distance: np.ndarray, ground: np.ndarray, image: RangeImage,
                  max_slope_deg: float) -> tuple[np.ndarray, np.ndarray]:
    """(P,) upper and (P,) lower point indices of the ground returns to join: neighbours in
    elevation order in one azimuth column, both ground, the line between them no steeper than
    `max_slope_deg`."""
    order = np.argsort(-np.nan_to_num(image.elevation, nan=-np.inf), kind="stable")  # top ring first
    index = image.index[order]
    upper, lower = index[:-1].reshape(-1), index[1:].reshape(-1)
    both = (upper >= 0) & (lower >= 0)
    upper, lower = upper[both], lower[both]
    rise = np.abs(xyz[upper, 2] - xyz[lower, 2])
    run = np.abs(planar_distance[upper] - planar_distance[lower])
    joined = ground[upper] & ground[lower] & (rise <= run * np.tan(np.radians(max_slope_deg)))
    return upper[joined], lower[joined]
