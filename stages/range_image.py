"""Range-image linear interpolation between LiDAR rings: the standard LiDAR super-resolution
baseline (as in TULIP and earlier range-image upsampling work), used to judge CAD-PU on real scans.

A scan with its ring ids is projected to a range image (rows = rings in id order, columns =
azimuth bins); between every two neighbouring rows, `ratio - 1` new rows are inserted by linear
interpolation of range, azimuth, elevation and reflectance between the two returns. The elevation
is each return's own, as seen from the sensor origin, not its ring's median: KITTI's lasers sit
off the sensor axis, so a ring's elevation seen from the origin drifts with range by more than a
ring spacing (`stages.ring_snap`); the returns' own elevations scored better on real scans than the
ring medians (docs/results.md).

A column is interpolated only where both rings have a return and the two ranges are close enough
to lie on one surface (see `surface_gap_limit`): across a depth edge (a car in front of a wall)
nothing is inserted, so points do not bleed into empty space. Nothing is extrapolated above the
first or below the last ring.

Frames: points are in the sensor frame (x forward, y left, z up, metres); azimuth is
atan2(y, x) and elevation asin(z / range), radians.
"""

from __future__ import annotations

import numbers

from dataclasses import dataclass

import numpy as np

from .ring_kernels import nearest_in_cells, ranges_and_sines

#: Azimuth bins per revolution: the HDL-64E's firings per turn (0.18 degree, `cadpu.synthetic.lidar.HDL64E`).
DEFAULT_COLUMNS = 2000
#: Steepest incidence (from the surface normal) of a surface whose neighbouring returns are joined.
DEFAULT_MAX_INCIDENCE_DEG = 75.0
#: Range difference always tolerated, metres (range noise and small surface relief).
DEFAULT_NOISE_FLOOR = 0.1
#: A scan whose points lie mostly beyond this range (metres; `stages.load.MAX_RANGE_M`, beyond any
#: spinning LiDAR's reach) is not in its sensor's frame: `build_range_image` refuses it. Moved into a
#: map frame, a scan's rings read from the origin were nothing like the sensor's, and snapping
#: dropped 99.7% of the network's points without a word (a library user's trial).
SENSOR_FRAME_MAX_RANGE_M = 200.0


@dataclass(frozen=True)
class RangeImage:
    """A scan's points arranged by ring and azimuth bin.

    Attributes:
        index: (R, W) int64 index into the scan's points of the nearest return in each cell,
            -1 where the cell is empty. Row k is the k-th smallest ring id.
        ring_ids: (R,) the ring ids of the rows, ascending.
        elevation: (R,) float64 median elevation angle of each ring's points, radians.
        range: (N,) float64 distance of every point from the sensor, metres.
        azimuth: (N,) float64 atan2(y, x) of every point, radians in (-pi, pi].
        point_elevation: (N,) float64 asin(z / range) of every point, radians (0 at the origin).
    """

    index: np.ndarray
    ring_ids: np.ndarray
    elevation: np.ndarray
    range: np.ndarray
    azimuth: np.ndarray
    point_elevation: np.ndarray


def _check(points: np.ndarray, rings: np.ndarray, columns: int = 4) -> tuple[np.ndarray, np.ndarray]:
    """Validated (N, `columns`+) float points and (N,) integer rings; ValueError naming what is wrong."""
    if rings is None:  # what scan_rings returns for a scan not stored ring by ring
        raise ValueError("range image: rings is None: the scan's point order shows no laser rings "
                         "(stages.ring_snap.scan_rings returned None, stages.ring_snap.no_rings_reason says why)")
    points = np.asarray(points)
    rings = np.asarray(rings)
    if points.ndim != 2 or points.shape[1] < columns:
        layout = "x, y, z, reflectance" if columns == 4 else "x, y, z"
        raise ValueError(f"range image: points must be (N, {columns}) {layout}, got shape {points.shape}")
    if rings.shape != (len(points),):
        raise ValueError(f"range image: {len(points)} points but rings has shape {rings.shape}")
    if not np.issubdtype(rings.dtype, np.integer):
        raise ValueError(f"range image: ring ids must be integers, got dtype {rings.dtype}")
    if not np.isfinite(points[:, :columns]).all():
        raise ValueError("range image: points hold NaN or infinite values")
    return points, rings


def build_range_image(points: np.ndarray, rings: np.ndarray, columns: int = DEFAULT_COLUMNS) -> RangeImage:
    """Project a scan into a range image.

    Args:
        points: (N, 3+) x, y, z (sensor frame, metres), further columns ignored.
        rings: (N,) integer ring id of each point (any ids; rows are their sorted distinct values).
        columns: azimuth bins per revolution; bin c covers azimuths
            [-pi + c * 2 pi / W, -pi + (c + 1) * 2 pi / W).

    Returns:
        The `RangeImage`. Points at the sensor origin (range 0) are left out of the image, and
        where several returns fall in one cell the nearest is kept.

    Raises:
        ValueError: points not (N, 3+) and finite, rings not N integers, columns < 1, or most
            points beyond `SENSOR_FRAME_MAX_RANGE_M` of the origin (not the sensor's frame).
    """
    if columns < 1:
        raise ValueError(f"range image: columns must be >= 1, got {columns}")
    points, rings = _check(points, rings, columns=3)
    xyz = points[:, :3].astype(np.float64)
    distance, sine = ranges_and_sines(xyz)
    far = int(np.count_nonzero(distance > SENSOR_FRAME_MAX_RANGE_M))
    if far > len(distance) / 2:
        raise ValueError(f"range image: {far} of {len(distance)} points lie beyond {SENSOR_FRAME_MAX_RANGE_M:g} m of "
                         "the origin; the scan's rings are read from its sensor, so the points must be in the sensor's "
                         "frame (those of a map or world frame lie far from it)")
    azimuth = np.arctan2(xyz[:, 1], xyz[:, 0])
    ring_ids, row = ring_rows(rings)
    usable = np.flatnonzero(distance > 0)
    point_elevation = np.arcsin(sine)
    row_elevation = group_medians(row[usable], point_elevation[usable], len(ring_ids))
    column = np.floor((azimuth[usable] + np.pi) / (2 * np.pi) * columns).astype(np.int64) % columns
    cell = row[usable] * columns + column
    index = nearest_in_cells(cell, distance, usable, len(ring_ids) * columns)  # nearest return per cell
    return RangeImage(index.reshape(len(ring_ids), columns), ring_ids, row_elevation, distance, azimuth,
                      point_elevation)


def group_medians(group: np.ndarray, values: np.ndarray, groups: int) -> np.ndarray:
    """(groups,) float64 median of the (P,) `values` within each group id of `group` (P,) int64 in
    [0, groups) (the mean of the two middle values for an even count), NaN for an empty group.

    One stable argsort of the ids (fast for a scan's ring ids, stored ring by ring), then a
    partition per group: the two middle values, not a sort of everything."""
    order = np.argsort(group, kind="stable")
    by_group = np.asarray(values, dtype=np.float64)[order]
    counts = np.bincount(group, minlength=groups)
    ends = np.cumsum(counts)
    medians = np.full(groups, np.nan)
    for g in np.flatnonzero(counts):
        count = int(counts[g])
        low, high = (count - 1) // 2, count // 2
        part = np.partition(by_group[ends[g] - count:ends[g]], (low, high))
        medians[g] = 0.5 * (part[low] + part[high])
    return medians


def ring_rows(rings: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The sorted distinct ring ids (R,) and the row (N,) int64 of each point among them, as
    `np.unique(rings, return_inverse=True)` gives them; by counting when the ids are small
    non-negative integers (KITTI's 0..63), without a sort."""
    rings = np.asarray(rings)
    if len(rings) and np.issubdtype(rings.dtype, np.integer) and 0 <= rings.min() and rings.max() < 65_536:
        present = np.bincount(rings) > 0
        ring_ids = np.flatnonzero(present).astype(rings.dtype)
        rows = np.cumsum(present) - 1
        return ring_ids, rows[rings].astype(np.int64)
    ring_ids, row = np.unique(rings, return_inverse=True)
    return ring_ids, row.reshape(-1).astype(np.int64)


def surface_gap_limit(nearer_range: np.ndarray, elevation_step: np.ndarray,
                      max_incidence_deg: float = DEFAULT_MAX_INCIDENCE_DEG,
                      noise_floor: float = DEFAULT_NOISE_FLOOR) -> np.ndarray:
    """Largest range difference (metres) between returns of two rings that still counts as one
    surface.

    Two rays `elevation_step` apart that hit a plane at incidence theta (from its normal) differ in
    range by about range * step * tan(theta); joining returns only up to `max_incidence_deg` keeps
    walls, cars and the near road, and refuses depth edges, whose jumps are larger.

    Args:
        nearer_range: (...) the smaller of the two ranges, metres.
        elevation_step: (...) elevation difference of the two rings, radians (sign ignored).
        max_incidence_deg: steepest incidence joined, degrees in [0, 90).
        noise_floor: difference always tolerated, metres.

    Returns:
        (...) float64 limit in metres.
    """
    if not 0.0 <= max_incidence_deg < 90.0:
        raise ValueError(f"max_incidence_deg must be in [0, 90), got {max_incidence_deg}")
    slope = np.tan(np.radians(max_incidence_deg))
    return np.asarray(nearer_range) * np.abs(elevation_step) * slope + noise_floor


def interpolate_rings(points: np.ndarray, rings: np.ndarray, ratio: int = 4, columns: int = DEFAULT_COLUMNS,
                      max_incidence_deg: float = DEFAULT_MAX_INCIDENCE_DEG,
                      noise_floor: float = DEFAULT_NOISE_FLOOR) -> np.ndarray:
    """Densify a scan by inserting `ratio - 1` interpolated rings between neighbouring rings.

    Args:
        points: (N, 4) x, y, z (sensor frame, metres), reflectance, e.g. a 16-ring KITTI scan.
        rings: (N,) integer ring ids (from `stages.rings.recover_rings`, on the scan itself or on the
            scan it was thinned from: only the order of the distinct ids matters).
        ratio: rows per original row gap (4 turns 16 rings into 61); 1 returns the input.
        columns: azimuth bins of the range image.
        max_incidence_deg, noise_floor: when two returns count as one surface
            (`surface_gap_limit`).

    Returns:
        (M, 4) float32: the N input points unchanged, followed by the inserted points (x, y, z,
        reflectance linearly interpolated between the two returns).

    Raises:
        ValueError: wrong shapes, non-integer ring ids, non-finite values, ratio < 1.
    """
    points, rings = _check(points, rings)
    if isinstance(ratio, bool) or not isinstance(ratio, numbers.Integral) or ratio < 1:
        # 2.5 inserted points at 0.4 and 0.8 of each gap, as no ring count describes
        raise ValueError(f"interpolate_rings: ratio must be a whole number >= 1, got {ratio!r}")
    kept = points[:, :4].astype(np.float32)
    if ratio == 1 or len(points) == 0:
        return kept
    image = build_range_image(points, rings, columns)
    upper, lower = image.index[:-1], image.index[1:]  # (R-1, W): each row with the next one
    step = np.diff(image.elevation)[:, None]  # (R-1, 1)
    both = (upper >= 0) & (lower >= 0) & np.isfinite(step)
    near = np.minimum(image.range[upper], image.range[lower])
    gap = np.abs(image.range[upper] - image.range[lower])
    joined = both & (gap <= surface_gap_limit(near, np.nan_to_num(step), max_incidence_deg, noise_floor))
    pair_row, pair_col = np.nonzero(joined)
    a, b = upper[pair_row, pair_col], lower[pair_row, pair_col]
    t = np.arange(1, ratio, dtype=np.float64)[None, :] / ratio  # (1, ratio-1)
    distance = _lerp(image.range[a], image.range[b], t)
    elevation = _lerp(image.point_elevation[a], image.point_elevation[b], t)
    turn = np.angle(np.exp(1j * (image.azimuth[b] - image.azimuth[a])))  # wrapped into (-pi, pi]
    azimuth = image.azimuth[a][:, None] + turn[:, None] * t
    reflectance = _lerp(points[a, 3].astype(np.float64), points[b, 3].astype(np.float64), t)
    flat = np.cos(elevation) * distance
    inserted = np.stack([flat * np.cos(azimuth), flat * np.sin(azimuth), np.sin(elevation) * distance,
                         reflectance], axis=-1).reshape(-1, 4)
    return np.concatenate([kept, inserted.astype(np.float32)])


def _lerp(start: np.ndarray, end: np.ndarray, t: np.ndarray) -> np.ndarray:
    """(P, T) values start + (end - start) * t for (P,) ends and (1, T) fractions."""
    return start[:, None] + (end - start)[:, None] * t
