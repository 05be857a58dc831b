"""Stage 2, ground: label every point of a scan ground or not.

Methods (by name, `segment(points, method, params)`):
- "patchwork" (default): zone-based local plane fitting over a concentric polar grid, in the
  Patchwork family (Lim et al. 2021; Lee et al. 2022), pure numpy and vectorised over all bins;
- "ransac": one plane through Open3D's RANSAC `segment_plane`;
- "patchworkpp": Patchwork++ itself through the optional `pypatchworkpp` package
  (`pip install "kitti-pu[patchwork]"`).

Assumptions: points are in the sensor frame (x forward, y left, z up, metres), the sensor is
roughly level and mounted above the ground it drives on (KITTI: 1.73 m; estimated from each scan);
ground is what a vehicle could drive or walk on: road, parking, sidewalks and kerbs (raised
15-20 cm), terrain. Everything else, including low obstacles and points below the road
(multi-path reflections), is not ground.

The default method, per scan:
1. sensor height: the median lowest-point level of the bins of the innermost zone;
2. per bin of the concentric zone model (rings of range x sectors of azimuth, coarser far
   away), seeds = points near the bin's lowest-point representative (LPR: median of its lowest
   points), then `iterations` rounds of PCA plane fitting, each keeping points within
   `distance_threshold` of the plane;
3. a bin's plane is accepted as ground when it is upright (normal within 45 degrees of z) and
   continuous with the ground found closer to the sensor: its height at the bin's centre is within
   `max_step` of the inner neighbour's plane extrapolated there (so ramps and slopes pass, kerbs
   pass, car roofs and walls do not). Rings are processed from the sensor outwards.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from .errors import InputError
from .frame import Frame

METHODS = ("patchwork", "ransac", "patchworkpp")


@dataclass(frozen=True)
class PatchworkParams:
    """Parameters of the default method (metres, unless stated).

    Attributes:
        min_range, max_range: points outside this horizontal range are not ground (the ego
            vehicle, and beyond what the zone model covers).
        zone_edges: range at which each zone starts, plus the outer edge of the last.
        rings_per_zone, sectors_per_zone: bins of each zone.
        lpr_points: lowest points per bin whose median is its lowest-point representative.
        seed_margin: seeds are points within this height above the LPR (and `seed_margin_below`
            below it, so reflections under the road are not seeds).
        candidate_band: points higher than this above their bin's LPR are never ground (skipped
            early, for speed; covers the height a ramp gains across the widest bin).
        distance_threshold: point-to-plane distance of ground points.
        iterations: plane refits per bin.
        min_points: bins with fewer points get no plane of their own; their points are judged
            against the plane of the nearest inner ground bin.
        uprightness: minimum z component of a ground plane's unit normal.
        max_step: largest height difference between a bin's plane and the inner ground
            extrapolated to it.
        sensor_height: prior of the sensor height, used when a scan has too few near points.
        sensor_height_bounds: estimates outside these bounds fall back to the prior.
    """

    min_range: float = 2.7
    max_range: float = 80.0
    zone_edges: tuple[float, ...] = (2.7, 12.3625, 22.025, 41.35, 80.0)
    rings_per_zone: tuple[int, ...] = (2, 4, 4, 4)
    sectors_per_zone: tuple[int, ...] = (16, 32, 54, 32)
    lpr_points: int = 20
    seed_margin: float = 0.3
    seed_margin_below: float = 0.3
    candidate_band: float = 2.0
    distance_threshold: float = 0.125
    iterations: int = 3
    min_points: int = 10
    uprightness: float = 0.707
    max_step: float = 0.35
    sensor_height: float = 1.73
    sensor_height_bounds: tuple[float, float] = (0.5, 3.0)


@dataclass(frozen=True)
class RansacParams:
    """Parameters of the single-plane RANSAC method (Open3D `segment_plane`)."""

    distance_threshold: float = 0.2
    ransac_n: int = 3
    num_iterations: int = 200
    seed: int = 0


@dataclass(frozen=True)
class PatchworkppParams:
    """Parameters passed to Patchwork++ (`pypatchworkpp.Parameters`)."""

    sensor_height: float = 1.723
    th_dist: float = 0.125
    min_range: float = 2.7
    max_range: float = 80.0


@dataclass(frozen=True)
class GroundResult:
    """What a ground method found.

    Attributes:
        mask: (N,) bool, True for ground.
        planes: (Z, 4) float64 plane coefficients [a, b, c, d] (a x + b y + c z + d = 0, unit
            normal with c > 0) of each ground bin (one row for ransac; empty for patchworkpp).
        sensor_height: metres above the ground, as estimated (None when the method has none).
        elapsed_s: seconds spent.
        method: the method's name.
    """

    mask: np.ndarray
    planes: np.ndarray
    sensor_height: float | None
    elapsed_s: float
    method: str


def params_class(method: str) -> type | None:
    """The parameter dataclass of a method. Raises ValueError for an unknown method."""
    classes = {"patchwork": PatchworkParams, "ransac": RansacParams, "patchworkpp": PatchworkppParams}
    if method not in classes:
        raise ValueError(f"unknown ground method {method!r}; known: {list(METHODS)}")
    return classes[method]


def _check_points(points: np.ndarray) -> np.ndarray:
    array = np.asarray(points)
    if array.ndim != 2 or array.shape[1] < 3:
        raise InputError("ground", "points", f"expected an (N, 3+) array, got shape {array.shape}")
    xyz = np.ascontiguousarray(array[:, :3], dtype=np.float64)
    if not np.isfinite(xyz).all():
        raise InputError("ground", "points", "NaN or infinite coordinates")
    return xyz


def segment(points: np.ndarray, method: str = "patchwork", params: object | None = None) -> GroundResult:
    """Label ground points.

    Args:
        points: (N, 3+) float array in the sensor frame (z up, metres); extra columns ignored.
        method: one of METHODS.
        params: the method's parameter dataclass (None = defaults).

    Returns:
        The `GroundResult`.
    """
    cls = params_class(method)
    params = params if params is not None else cls()
    xyz = _check_points(points)
    started = time.perf_counter()
    if len(xyz) == 0:
        return GroundResult(np.zeros(0, dtype=bool), np.zeros((0, 4)), None, 0.0, method)
    if method == "patchwork":
        mask, planes, height = _patchwork(xyz, params)  # type: ignore[arg-type]
    elif method == "ransac":
        mask, planes, height = _ransac(xyz, params)  # type: ignore[arg-type]
    else:
        mask, planes, height = _patchworkpp(xyz, params)  # type: ignore[arg-type]
    return GroundResult(mask, planes, height, time.perf_counter() - started, method)


def run(frame: Frame, method: str = "patchwork", params: object | None = None) -> Frame:
    """Label the frame's ground points; returns the frame with `ground` and timings["ground"]."""
    result = segment(frame.points, method, params)
    return frame.with_(ground=result.mask, timings={**frame.timings, "ground": result.elapsed_s})


# --- patchwork-style default ----------------------------------------------------------------


def _bins(xyz: np.ndarray, p: PatchworkParams) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Bin id of every point (-1 outside the zone model), and per bin: ring number, inner-bin map
    helpers (ring start ranges, sector counts per ring)."""
    radius = np.hypot(xyz[:, 0], xyz[:, 1])
    azimuth = np.arctan2(xyz[:, 1], xyz[:, 0]) % (2 * np.pi)
    ring_edges, ring_sectors = [], []
    for zone, (start, stop) in enumerate(zip(p.zone_edges[:-1], p.zone_edges[1:])):
        rings = p.rings_per_zone[zone]
        ring_edges += list(np.linspace(start, stop, rings + 1)[:-1])
        ring_sectors += [p.sectors_per_zone[zone]] * rings
    ring_edges.append(p.zone_edges[-1])
    ring_edges_arr = np.asarray(ring_edges)
    sectors = np.asarray(ring_sectors)
    ring = np.searchsorted(ring_edges_arr, radius, side="right") - 1
    inside = (ring >= 0) & (ring < len(sectors)) & (radius >= p.min_range) & (radius < p.max_range)
    ring = np.where(inside, ring, 0)
    sector = np.minimum((azimuth / (2 * np.pi) * sectors[ring]).astype(np.int64), sectors[ring] - 1)
    offsets = np.concatenate([[0], np.cumsum(sectors)])
    bin_id = np.where(inside, offsets[ring] + sector, -1)
    return bin_id, ring_edges_arr, sectors, offsets


def _lowest_point_levels(z: np.ndarray, bin_id: np.ndarray, n_bins: int, lpr_points: int
                         ) -> tuple[np.ndarray, np.ndarray]:
    """Per bin: median height of its `lpr_points` lowest points (NaN when empty), and point counts.

    Args:
        z: (n,) heights of points inside the zone model. bin_id: (n,) their bins (>= 0).
    """
    # One sort on a combined key (bin, then height): heights are within +-500 m of the sensor.
    order = np.argsort(bin_id * 1000.0 + np.clip(z, -499.0, 499.0))
    heights = z[order]
    counts = np.bincount(bin_id, minlength=n_bins)
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    take = np.minimum(counts, lpr_points)
    lpr = np.full(n_bins, np.nan)
    has = counts > 0
    lpr[has] = heights[starts[has] + take[has] // 2]  # upper median of the lowest `take`
    return lpr, counts


def _fit_planes(xyz: np.ndarray, bin_id: np.ndarray, n_bins: int
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """PCA plane per bin through the given points (raw moments, one pass of bincounts).

    Args:
        xyz: (n, 3) points. bin_id: (n,) their bins.

    Returns:
        normal (n_bins, 3) unit with z >= 0, d (n_bins,), mean (n_bins, 3), count (n_bins,).
    """
    count = np.bincount(bin_id, minlength=n_bins).astype(np.float64)
    safe = np.maximum(count, 1.0)[:, None]
    columns = [xyz[:, 0], xyz[:, 1], xyz[:, 2]]
    mean = np.stack([np.bincount(bin_id, c, n_bins) for c in columns], 1) / safe
    second = np.empty((n_bins, 3, 3))
    for i in range(3):
        for j in range(i, 3):
            second[:, i, j] = second[:, j, i] = np.bincount(bin_id, columns[i] * columns[j], n_bins)
    cov = second / safe[:, :, None] - mean[:, :, None] * mean[:, None, :]
    _, vectors = np.linalg.eigh(cov)
    normal = vectors[:, :, 0]
    normal *= np.where(normal[:, 2:3] < 0, -1.0, 1.0)
    d = -(normal * mean).sum(1)
    return normal, d, mean, count


def _plane_distance(xyz: np.ndarray, bin_id: np.ndarray, normal: np.ndarray, d: np.ndarray) -> np.ndarray:
    """|n . p + d| of every point to the plane of its bin."""
    n = normal[bin_id]
    return np.abs(xyz[:, 0] * n[:, 0] + xyz[:, 1] * n[:, 1] + xyz[:, 2] * n[:, 2] + d[bin_id])


def _patchwork(xyz: np.ndarray, p: PatchworkParams) -> tuple[np.ndarray, np.ndarray, float]:
    bin_all, ring_edges, sectors, offsets = _bins(xyz, p)
    n_bins = int(offsets[-1])
    inside = np.flatnonzero(bin_all >= 0)
    bins, pts = bin_all[inside], xyz[inside]
    lpr, counts = _lowest_point_levels(pts[:, 2], bins, n_bins, p.lpr_points)

    inner_bins = np.arange(offsets[p.rings_per_zone[0]])
    inner_levels = lpr[inner_bins][counts[inner_bins] >= p.min_points]
    height = -float(np.median(inner_levels)) if len(inner_levels) else p.sensor_height
    if not p.sensor_height_bounds[0] <= height <= p.sensor_height_bounds[1]:
        height = p.sensor_height

    # Only points not far above their bin's lowest level can be ground: drop the rest early.
    level = lpr[bins]
    near = np.flatnonzero(pts[:, 2] < level + p.candidate_band)
    inside, bins, pts, level = inside[near], bins[near], pts[near], level[near]
    selected = (pts[:, 2] < level + p.seed_margin) & (pts[:, 2] > level - p.seed_margin_below)
    for _ in range(p.iterations):
        normal, d, mean, fitted = _fit_planes(pts[selected], bins[selected], n_bins)
        selected = _plane_distance(pts, bins, normal, d) < p.distance_threshold

    accepted = _accept_bins(normal, d, mean, fitted, counts, sectors, offsets, height, p)
    # Bins too sparse for their own plane borrow the plane of the inner ground they continue.
    plane_of = _borrowed_planes(accepted, counts, sectors, offsets, p)
    owner = plane_of[bins]
    has_plane = owner >= 0
    owner = np.where(has_plane, owner, 0)
    is_ground = has_plane & (_plane_distance(pts, owner, normal, d) < p.distance_threshold)
    mask = np.zeros(len(xyz), dtype=bool)
    mask[inside[is_ground]] = True
    planes = np.c_[normal[accepted], d[accepted]]
    return mask, planes, height


def _sector_map(from_ring: int, to_ring: int, sectors: np.ndarray, offsets: np.ndarray) -> np.ndarray:
    """For each bin of ring `from_ring`, the bin of ring `to_ring` at the same azimuth."""
    n_from, n_to = sectors[from_ring], sectors[to_ring]
    centre = (np.arange(n_from) + 0.5) / n_from
    return offsets[to_ring] + np.minimum((centre * n_to).astype(np.int64), n_to - 1)


def _accept_bins(normal: np.ndarray, d: np.ndarray, mean: np.ndarray, fitted: np.ndarray,
                 counts: np.ndarray, sectors: np.ndarray, offsets: np.ndarray,
                 height: float, p: PatchworkParams) -> np.ndarray:
    """Ground likelihood per bin, ring by ring from the sensor outwards (see module docstring)."""
    n_bins = len(normal)
    accepted = np.zeros(n_bins, dtype=bool)
    # Reference plane per bin: the ground plane it must continue (starts as the sensor-height plane).
    reference = np.zeros((n_bins, 4))
    reference[:] = [0.0, 0.0, 1.0, height]
    upright = normal[:, 2] > p.uprightness
    enough = (fitted >= 3) & (counts >= p.min_points)
    for ring in range(len(sectors)):
        bins = np.arange(offsets[ring], offsets[ring + 1])
        if ring > 0:
            inner = _sector_map(ring, ring - 1, sectors, offsets)
            inner_planes = np.c_[normal[inner], d[inner]]
            reference[bins] = np.where(accepted[inner, None], inner_planes, reference[inner])
        ref = reference[bins]
        centre = mean[bins]
        expected_z = -(ref[:, 0] * centre[:, 0] + ref[:, 1] * centre[:, 1] + ref[:, 3]) / ref[:, 2]
        continuous = np.abs(centre[:, 2] - expected_z) < p.max_step
        accepted[bins] = enough[bins] & upright[bins] & continuous
    return accepted


def _borrowed_planes(accepted: np.ndarray, counts: np.ndarray, sectors: np.ndarray, offsets: np.ndarray,
                     p: PatchworkParams) -> np.ndarray:
    """Plane index used by each bin: its own if accepted; for a sparse bin, the nearest accepted
    inner bin at the same azimuth; -1 otherwise."""
    plane_of = np.where(accepted, np.arange(len(accepted)), -1)
    for ring in range(1, len(sectors)):
        bins = np.arange(offsets[ring], offsets[ring + 1])
        inner = plane_of[_sector_map(ring, ring - 1, sectors, offsets)]
        sparse = (counts[bins] < p.min_points) & (plane_of[bins] < 0)
        plane_of[bins] = np.where(sparse, inner, plane_of[bins])
    return plane_of


# --- other methods --------------------------------------------------------------------------


def _ransac(xyz: np.ndarray, p: RansacParams) -> tuple[np.ndarray, np.ndarray, float | None]:
    from cadpu.o3d import o3d

    mask = np.zeros(len(xyz), dtype=bool)
    if len(xyz) < p.ransac_n:
        return mask, np.zeros((0, 4)), None
    o3d.utility.random.seed(p.seed)
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(xyz))
    plane, inliers = cloud.segment_plane(p.distance_threshold, p.ransac_n, p.num_iterations)
    plane = np.asarray(plane, dtype=np.float64)
    plane /= np.linalg.norm(plane[:3]) * (1 if plane[2] >= 0 else -1)
    mask[np.asarray(inliers, dtype=np.int64)] = True
    return mask, plane[None], float(plane[3])


def _patchworkpp(xyz: np.ndarray, p: PatchworkppParams) -> tuple[np.ndarray, np.ndarray, float | None]:
    try:
        import pypatchworkpp
    except ImportError:
        raise InputError("ground", "patchworkpp", 'pypatchworkpp is not installed; install it with '
                                                  'pip install "kitti-pu[patchwork]"') from None
    parameters = pypatchworkpp.Parameters()
    parameters.sensor_height = p.sensor_height
    parameters.th_dist = p.th_dist
    parameters.min_range = p.min_range
    parameters.max_range = p.max_range
    parameters.verbose = False
    estimator = pypatchworkpp.patchworkpp(parameters)
    estimator.estimateGround(np.c_[xyz, np.zeros(len(xyz))].astype(np.float64))
    mask = np.zeros(len(xyz), dtype=bool)
    mask[np.asarray(estimator.getGroundIndices(), dtype=np.int64)] = True
    return mask, np.zeros((0, 4)), p.sensor_height
