"""Put generated points on virtual laser rings between the scan's real rings.

A rotating LiDAR samples a surface along cones of fixed elevation, one per laser. Densifying a scan
r-fold is, for a sensor user, the scan an r-times denser laser column would have taken: its points
lie on r - 1 new cones between every two neighbouring real ones. The network does not know the
sensor (its patches are normalised), so its points scatter in elevation; this module moves each
generated point, at its own azimuth and range, to the elevation of the nearest virtual ring.

The elevation of every ring is read per azimuth column from the scan itself (the returns of that
ring in that column, or in the nearest column that has one), not from a global table: KITTI's
lasers sit off the sensor axis, so a ring's elevation seen from the origin drifts by more than a
ring spacing between near and far returns (measured on odometry sequence 00: ring 0 at +4.1
degrees within 8 m and +2.4 beyond 15 m).

Points above the top ring or below the bottom ring of their column have no virtual ring and are
reported as outside; nothing is extrapolated past the scan's field of view (the rule of the
range-image baseline, `cadpu.range_image`).

Measured effect on the 16-to-64-beam evaluation: `kitti-pu eval-kitti` with
`--set stitch.snap_to_rings=false` and without (README, "Measured quality on real KITTI scans").

Frames: sensor frame, x forward, y left, z up, metres; azimuth atan2(y, x), elevation
asin(z / range), radians.
"""

from __future__ import annotations

import numpy as np

from cadpu.lidar import recover_rings
from cadpu.range_image import DEFAULT_COLUMNS, build_range_image

#: A point order showing more rings than this is not a ring-by-ring scan (lasers of the largest
#: spinning LiDARs: 128).
MAX_RINGS = 256
#: ... nor is one whose rings average fewer returns than this (a shuffled scan "wraps" every
#: second point).
MIN_POINTS_PER_RING = 50
#: Generated points snapped per block (bounds the (rings, block) work arrays to a few MB).
BLOCK = 65_536


def scan_rings(points: np.ndarray) -> np.ndarray | None:
    """Ring ids of a scan stored ring by ring (KITTI order), or None when its order shows no rings.

    Args:
        points: (N, 3+) scan in its stored order, sensor frame.

    Returns:
        (N,) int64 ring ids (`cadpu.lidar.recover_rings`), or None when the order yields fewer than
        2 rings, more than `MAX_RINGS`, or fewer than `MIN_POINTS_PER_RING` points per ring on
        average (e.g. a shuffled or azimuth-sorted scan).
    """
    rings = recover_rings(points)
    count = int(rings.max()) + 1 if len(rings) else 0
    if count < 2 or count > MAX_RINGS or len(rings) < MIN_POINTS_PER_RING * count:
        return None
    return rings


def ring_elevation_table(points: np.ndarray, rings: np.ndarray, columns: int = DEFAULT_COLUMNS) -> np.ndarray:
    """Elevation of every ring in every azimuth column, rings ordered top to bottom.

    Args:
        points: (N, 3+) scan, sensor frame, metres. rings: (N,) integer ring ids.
        columns: azimuth bins per revolution (bin c covers [-pi + c 2pi/W, -pi + (c+1) 2pi/W)).

    Returns:
        (R, W) float64 radians: row k is the ring with the k-th highest median elevation; a cell
        holds the elevation of that ring's nearest return in the column, or, where the column has
        none, of the ring's return in the nearest column (round the circle) that has one.
    """
    image = build_range_image(points, rings, columns)
    xyz = np.asarray(points)[:, :3].astype(np.float64)
    elevation = np.arcsin(np.clip(xyz[:, 2] / np.maximum(image.range, 1e-12), -1.0, 1.0))
    table = np.where(image.index >= 0, elevation[np.maximum(image.index, 0)], np.nan)
    table = np.stack([_fill_round(row) for row in table])
    order = np.argsort(-image.elevation, kind="stable")  # top ring first
    return table[order]


def _fill_round(row: np.ndarray) -> np.ndarray:
    """(W,) values with NaNs replaced by the value of the nearest finite cell, circularly."""
    known = np.flatnonzero(np.isfinite(row))
    if len(known) == 0 or len(known) == len(row):
        return row
    cells = np.arange(len(row))
    after = np.searchsorted(known, cells) % len(known)
    next_cell, previous_cell = known[after], known[after - 1]
    to_previous = (cells - previous_cell) % len(row)
    to_next = (next_cell - cells) % len(row)
    return np.where(to_previous <= to_next, row[previous_cell], row[next_cell])


def snap_to_virtual_rings(xyz: np.ndarray, table: np.ndarray, factor: int) -> tuple[np.ndarray, np.ndarray]:
    """Move points to the elevation of the nearest of the factor - 1 virtual rings between the two
    real rings they lie between, keeping their azimuth and range.

    Between real rings with elevations e_top > e_bottom in the point's column, the virtual rings
    are at e_top + (e_bottom - e_top) * j / factor, j = 1 .. factor - 1; a point on or next to a
    real ring goes to the nearest virtual one (the real ring is already sampled by the scan).

    Args:
        xyz: (Q, 3) points, sensor frame, metres.
        table: (R, W) ring elevations per azimuth column, top ring first (`ring_elevation_table`).
        factor: virtual ring gaps per real gap (the upsampling ratio r >= 2).

    Returns:
        (Q, 3) float32 snapped points, and (Q,) bool: False for points above the top ring or below
        the bottom ring of their column (returned unmoved; callers drop them).
    """
    if factor < 2:
        raise ValueError(f"ring snapping: factor must be >= 2, got {factor}")
    if table.ndim != 2 or len(table) < 2:
        raise ValueError(f"ring snapping: need an elevation table of at least 2 rings, got shape {table.shape}")
    xyz = np.asarray(xyz, dtype=np.float64)
    snapped = xyz.astype(np.float32)
    inside = np.zeros(len(xyz), dtype=bool)
    columns = table.shape[1]
    for start in range(0, len(xyz), BLOCK):
        block = xyz[start:start + BLOCK]
        distance = np.linalg.norm(block, axis=1)
        azimuth = np.arctan2(block[:, 1], block[:, 0])
        elevation = np.arcsin(np.clip(block[:, 2] / np.maximum(distance, 1e-12), -1.0, 1.0))
        column = np.floor((azimuth + np.pi) / (2 * np.pi) * columns).astype(np.int64) % columns
        ring_elevations = table[:, column]  # (R, B)
        above = (ring_elevations > elevation).sum(axis=0)  # rings above the point = the gap it is in
        between = (above > 0) & (above < len(table)) & (distance > 0)
        gap = np.clip(above, 1, len(table) - 1)
        points = np.arange(len(block))
        top, bottom = ring_elevations[gap - 1, points], ring_elevations[gap, points]
        span = top - bottom
        fraction = np.divide(top - elevation, span, out=np.zeros_like(span), where=span > 0)
        step = np.clip(np.round(fraction * factor), 1, factor - 1)
        new_elevation = top - span * step / factor
        horizontal = np.cos(new_elevation) * distance
        moved = np.stack([horizontal * np.cos(azimuth), horizontal * np.sin(azimuth),
                          np.sin(new_elevation) * distance], axis=1)
        snapped[start:start + BLOCK][between] = moved[between].astype(np.float32)
        inside[start:start + BLOCK] = between
    return snapped, inside
