"""Statistics of one 64-ring scan stored in KITTI order, the same on real and simulated scans
(used by `bench/sim_vs_real.py`, which defines each printed row).

Every function takes points (N, 4) float x, y, z, reflectance in the sensor frame (metres) and the
ring of every point as `stages.rings.recover_rings` finds it from the point order alone, so real
and simulated scans go through the same code. Where a class is needed, `PLANAR`, `ROUGH` and the
ground groups name SemanticKITTI classes; simulated labels are mapped onto them by
`cadpu.synthetic.street.SEMANTIC_KITTI`.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from cadpu.synthetic import street
from stages import ring_snap

#: SemanticKITTI classes (lower 16 bits of a .label entry).
ROAD, PARKING, SIDEWALK, OTHER_GROUND, LANE_MARKING, TERRAIN = 40, 44, 48, 49, 60, 72
BUILDING, VEGETATION, TRUNK, CAR, POLE = 50, 70, 71, 10, 80
#: Surfaces flat at the scale of a few firings: where range noise is measured.
PLANAR = (ROAD, PARKING, SIDEWALK, LANE_MARKING, BUILDING)
GROUND = (ROAD, PARKING, SIDEWALK, OTHER_GROUND, LANE_MARKING, TERRAIN)
#: Horizontal range bands (metres) of the per-band rows.
BANDS = ((0.0, 10.0), (10.0, 20.0), (20.0, 40.0), (40.0, 200.0))
#: One firing's azimuth step (degrees): the median step between consecutive returns of a ring in the
#: six real scans and the simulator's 360 / 2000.
FIRING_DEG = 0.18


def kitti_labels(sim_labels: np.ndarray) -> np.ndarray:
    """(N,) SemanticKITTI class of every simulated point (`cadpu.synthetic.street.SEMANTIC_KITTI`)."""
    return street.SEMANTIC_KITTI[sim_labels].astype(np.int64)


def horizontal_range(points: np.ndarray) -> np.ndarray:
    """(N,) distance from the sensor's vertical axis, metres."""
    return np.hypot(points[:, 0].astype(np.float64), points[:, 1].astype(np.float64))


def ring_cones(points: np.ndarray, rings: np.ndarray, blocks: tuple[range, ...] = (range(0, 32), range(32, 64)),
               iterations: int = 4) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Each ring's cone z = h_block + rho * tan(elevation_ring): a laser at height h_block on the
    sensor's axis sweeping a cone of fixed elevation; h shared by the rings of a block.

    Every return of a ring lies on its cone, whatever it hits, so the fit needs no labels. Least
    squares over all returns with rho > 3 m, refitted `iterations` times without residuals above
    3 robust standard deviations of the ring.

    Returns:
        elevation (64,) degrees, offset (64,) metres (h of the ring's block), residual (64,) robust
        standard deviation (1.4826 MAD) of z about the cone, metres. NaN for a ring without returns.
    """
    rho, z = horizontal_range(points), points[:, 2].astype(np.float64)
    elevation, offset, residual = (np.full(64, np.nan) for _ in range(3))
    use = (rho > 3.0) & (rings < 64)
    for block in blocks:
        inside = use & np.isin(rings, block)
        h = 0.0
        for _ in range(iterations + 1):
            r, zz, k = rho[inside], z[inside], rings[inside]
            s_rr, s_r, s_rz = (np.bincount(k, w, minlength=64) for w in (r * r, r, r * zz))
            with np.errstate(invalid="ignore", divide="ignore"):
                a, b = s_rz / s_rr, s_r / s_rr
            u = r * b[k] - 1.0  # z - rho * t_k(h) = (z - rho a_k) + h (rho b_k - 1)
            h = -np.sum((zz - r * a[k]) * u) / np.sum(u * u)
            slope = a - h * b
            res = z - h - rho * slope[np.minimum(rings, 63)]
            for ring in block:
                m = inside & (rings == ring)
                if m.any():
                    residual[ring] = 1.4826 * np.median(np.abs(res[m]))
            inside = use & np.isin(rings, block) & (np.abs(res) <= 3 * residual[np.minimum(rings, 63)] + 1e-3)
        elevation[list(block)] = np.degrees(np.arctan(slope[list(block)]))
        offset[list(block)] = h
    return elevation, offset, residual


#: Seconds per revolution (10 Hz) and the rotation's direction: the sweep runs clockwise seen from
#: above, and the scan is de-skewed to the moment the sensor faces forward (azimuth 0), so a return
#: at azimuth phi (radians) was fired `-phi / (2 pi) * SWEEP_PERIOD` seconds from that moment.
SWEEP_PERIOD = 0.1


def undo_motion(points: np.ndarray, speed: float) -> np.ndarray:
    """(N, 4) `points` moved back to where the sensor was when each was fired, for a sensor moving
    straight forward (+x) at `speed` m/s: a de-skewed scan's rings are cones again (`ring_cones`)."""
    out = np.array(points, dtype=np.float64)
    phi = np.arctan2(out[:, 1], out[:, 0])
    out[:, 0] -= speed * (-phi / (2 * np.pi) * SWEEP_PERIOD)
    return out


def ego_speed(points: np.ndarray, rings: np.ndarray, top: float = 20.0) -> float:
    """Forward speed (m/s) that makes the lower block's rings best fit cones (`ring_cones`), by a grid
    over 0 .. `top` m/s in 1 m/s steps refined by a parabola through the best three. The lower
    rings see the road near the car, where a shift of the firing position changes elevation most."""
    step = 1.0
    grid = np.arange(0.0, top + step / 2, step)
    cost = np.array([np.nanmedian(ring_cones(undo_motion(points, v), rings, blocks=(range(32, 64),))[2][32:])
                     for v in grid])
    i = int(np.clip(np.argmin(cost), 1, len(grid) - 2))
    c0, c1, c2 = cost[i - 1:i + 2]
    curvature = c0 - 2 * c1 + c2
    shift = 0.5 * (c0 - c2) / curvature if curvature > 0 else 0.0
    return float(grid[i] + step * np.clip(shift, -1.0, 1.0))


def consecutive(rings: np.ndarray, points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Azimuth step (degrees, forward, in (-180, 180]) from each point to the next of the same ring,
    the index of the first point of the pair, and the pair's mean horizontal range (metres)."""
    azimuth = np.degrees(np.arctan2(points[:, 1].astype(np.float64), points[:, 0].astype(np.float64)))
    step = np.mod(np.diff(azimuth) + 180.0, 360.0) - 180.0
    first = np.flatnonzero(rings[1:] == rings[:-1])
    rho = horizontal_range(points)
    return step[first], first, 0.5 * (rho[first] + rho[first + 1])


def range_noise(points: np.ndarray, rings: np.ndarray, labels: np.ndarray, ring_groups: int = 8
                ) -> tuple[np.ndarray, np.ndarray]:
    """Range noise on planar surfaces, from the second difference of range along a ring.

    For three consecutive returns of a ring, each step between 0.5 and 1.5 firings, all three on a
    `PLANAR` class and their ranges within 3 % of each other, d2 = r0 - 2 r1 + r2: on a flat surface
    the geometric part is below 0.1 mm at these steps, so sigma = 1.4826 MAD(d2) / sqrt(6).

    Returns:
        per ring group (ring_groups,) and per range band (len(BANDS),) sigma in metres (NaN where
        fewer than 50 triplets).
    """
    r = np.linalg.norm(points[:, :3].astype(np.float64), axis=1)
    step, first, rho = consecutive(rings, points)
    ok = (step > 0.5 * FIRING_DEG) & (step < 1.5 * FIRING_DEG)
    pair_start = np.zeros(len(points), dtype=bool)
    pair_start[first[ok]] = True
    i = np.flatnonzero(pair_start[:-1] & pair_start[1:])  # i, i + 1, i + 2 are two good steps
    planar = np.isin(labels, PLANAR)
    i = i[planar[i] & planar[i + 1] & planar[i + 2]]
    r0, r1, r2 = r[i], r[i + 1], r[i + 2]
    i = i[(np.maximum(r0, r2) - np.minimum(r0, r2) < 0.03 * r1) & (np.abs(r1 - r0) < 0.03 * r1)]
    d2 = r[i] - 2 * r[i + 1] + r[i + 2]

    def sigma(mask: np.ndarray) -> float:
        return float(1.4826 * np.median(np.abs(d2[mask])) / np.sqrt(6)) if mask.sum() >= 50 else np.nan

    group = rings[i + 1] * ring_groups // 64
    band_rho = horizontal_range(points)[i + 1]
    return (np.array([sigma(group == g) for g in range(ring_groups)]),
            np.array([sigma((band_rho >= lo) & (band_rho < hi)) for lo, hi in BANDS]))


def missing_returns(points: np.ndarray, rings: np.ndarray) -> np.ndarray:
    """Per range band (len(BANDS),): the share of firings without a return inside surfaces.

    Between two consecutive returns of a ring whose ranges are within 5 % of each other (one
    surface), the firings in between (round(step / 0.18 degree) - 1, steps up to 10 firings) had no
    return; the share is missing / (missing + returns) over those pairs, banded by the pair's mean
    horizontal range. A firing is 0.18 degree (`FIRING_DEG`).
    """
    step, first, rho = consecutive(rings, points)
    r = np.linalg.norm(points[:, :3].astype(np.float64), axis=1)
    same = (np.abs(r[first + 1] - r[first]) < 0.05 * r[first]) & (step > 0) & (step < 10.5 * FIRING_DEG)
    missing = np.maximum(np.rint(step / FIRING_DEG) - 1, 0)
    out = []
    for lo, hi in BANDS:
        m = same & (rho >= lo) & (rho < hi)
        out.append(missing[m].sum() / max(missing[m].sum() + m.sum(), 1))
    return np.array(out)


def half_steps(points: np.ndarray, rings: np.ndarray) -> float:
    """Share of steps between consecutive returns of a ring below 0.7 of a firing (0.126 degree):
    returns closer in azimuth than the firing rate, which a sensor firing on a fixed grid cannot give."""
    step, _, _ = consecutive(rings, points)
    step = step[step > -10]
    return float(np.mean(step < 0.7 * FIRING_DEG))


def crossing_columns(points: np.ndarray, rings: np.ndarray, ratio: int = 4) -> float:
    """Share of the azimuth columns of the scan's 1-in-`ratio` rings (what the pipeline's ring
    snapping sees; `stages.ring_snap.ring_tables`, 2000 columns) in which some ring's elevation,
    seen from the origin, lies above that of the ring stored before it: rings that cross there."""
    kept = (rings % ratio) == 0
    table = ring_snap.ring_tables(points[kept], rings[kept] // ratio).elevation
    step = np.diff(table, axis=0)
    return float(np.mean(np.any(np.where(np.isfinite(step), step, 0.0) > 0, axis=0)))


def ring_range_bias(points: np.ndarray, rings: np.ndarray, k: int = 24) -> np.ndarray:
    """Each laser's range bias on walls, relative to its neighbours: (64,) metres, NaN where a ring
    has too few wall points.

    For every point 5-30 m out and above z = -1 m, the plane of the other rings' points among its
    k nearest neighbours; where that plane is flat (surface variation under 0.005) and near
    vertical (|normal z| under 0.3), the point's distance from it is taken as delta_ring * (n . b),
    b the beam's direction (|n . b| at least 0.3): a bias along the beam. delta per ring is the
    least-squares fit over its points, with at least 20 of them at |n . b| = 0.3 or the
    equivalent. No labels needed. A range noise of sd sigma alone gives deltas of about
    sigma / sqrt(points of the ring).
    """
    xyz = points[:, :3].astype(np.float64)
    rho = horizontal_range(points)
    candidates = np.flatnonzero((rho > 5.0) & (rho < 30.0) & (xyz[:, 2] > -1.0))
    _, index = cKDTree(xyz).query(xyz[candidates], k=k)
    weight = (rings[index] != rings[candidates][:, None]).astype(np.float64)  # the other rings only
    count = weight.sum(axis=1)
    keep = count >= 8
    candidates, index, weight, count = candidates[keep], index[keep], weight[keep], count[keep]
    centre = np.einsum("nk,nki->ni", weight, xyz[index]) / count[:, None]
    offset = (xyz[index] - centre[:, None, :]) * np.sqrt(weight)[..., None]
    eigenvalues, eigenvectors = np.linalg.eigh(np.einsum("nki,nkj->nij", offset, offset))
    normal = eigenvectors[:, :, 0]
    wall = (eigenvalues[:, 0] / np.maximum(eigenvalues.sum(axis=1), 1e-12) < 0.005) & (np.abs(normal[:, 2]) < 0.3)
    beam = xyz[candidates] / np.linalg.norm(xyz[candidates], axis=1, keepdims=True)
    lever = np.einsum("ni,ni->n", normal, beam)
    wall &= np.abs(lever) >= 0.3
    residual = np.einsum("ni,ni->n", xyz[candidates] - centre, normal)
    ring = rings[candidates][wall]
    numerator = np.bincount(ring, residual[wall] * lever[wall], minlength=64)[:64]
    denominator = np.bincount(ring, lever[wall] ** 2, minlength=64)[:64]
    bias = np.full(64, np.nan)
    enough = denominator >= 20 * 0.3**2
    bias[enough] = numerator[enough] / denominator[enough]
    return bias


def surface_variation(points: np.ndarray, k: int = 16) -> np.ndarray:
    """(N,) lambda_min / (lambda_1 + lambda_2 + lambda_3) of the covariance of each point's k nearest
    neighbours (itself included): 0 on a plane, up to 1/3 on isotropic scatter."""
    xyz = points[:, :3].astype(np.float64)
    _, index = cKDTree(xyz).query(xyz, k=k)
    neighbours = xyz[index] - xyz[index].mean(axis=1, keepdims=True)
    eig = np.linalg.eigvalsh(np.einsum("nki,nkj->nij", neighbours, neighbours))
    return eig[:, 0] / np.maximum(eig.sum(axis=1), 1e-12)


def band_shares(rho: np.ndarray) -> np.ndarray:
    """(len(BANDS),) share of points in each horizontal range band."""
    return np.array([np.mean((rho >= lo) & (rho < hi)) for lo, hi in BANDS])
