"""A non-learned upsampler to compare CAD-PU against: tangent-plane midpoint insertion.

For every input point p, r - 1 new points are placed at the midpoints between p and its
nearest neighbours (the 1st, 2nd, ... nearest, skipping duplicates of earlier picks), then projected
onto the tangent plane of p (plane fitted to its k = 12 nearest distinct points). The inputs are kept, so the
output has exactly r * N points.
"""

from __future__ import annotations

import numbers

import numpy as np
from scipy.spatial import cKDTree

from .checks import check_finite_points
from .geometry import CURVATURE_K, curvature_and_normals_np


def midpoint_upsample(points: np.ndarray, ratio: int = 4) -> tuple[np.ndarray, np.ndarray]:
    """Upsample a point set by tangent-plane midpoint insertion.

    Args:
        points: (N, 3), N > ratio. ratio: r >= 2.

    Returns:
        points (r * N, 3) float64: the inputs followed by the inserted points; parents (r * N,)
        int64 index of the input point each output point belongs to.
    """
    points = np.asarray(points, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 3:
        raise ValueError(f"midpoint_upsample: points must be an (N, 3) array, got shape {points.shape}")
    check_finite_points("midpoint_upsample", points)
    n = len(points)
    _check_ratio("midpoint_upsample", ratio)
    if n <= ratio:
        raise ValueError(f"midpoint_upsample: need more than ratio = {ratio} points, got {n}")
    distinct, first, inverse = np.unique(points, axis=0, return_index=True, return_inverse=True)
    inverse = inverse.reshape(-1)
    # without duplicates, fitted in the points' own order (the same sums, bit for bit, as before)
    normals = _normals_of_distinct(points) if len(distinct) == n else _normals_of_distinct(distinct)[inverse]
    partners = points[_distinct_neighbours(points, ratio - 1, distinct, first, inverse)]  # (N, r-1, 3)
    midpoints = 0.5 * (points[:, None, :] + partners)
    offset = midpoints - points[:, None, :]
    along_normal = (offset * normals[:, None, :]).sum(-1, keepdims=True)
    projected = midpoints - along_normal * normals[:, None, :]
    out = np.concatenate([points, projected.reshape(-1, 3)])
    parents = np.concatenate([np.arange(n), np.repeat(np.arange(n), ratio - 1)])
    return out, parents


def _check_ratio(caller: str, ratio: object) -> None:
    """Raise ValueError naming `caller` unless `ratio` is a whole number >= 2 (a fractional one gave
    points and parents of different lengths)."""
    if isinstance(ratio, bool) or not isinstance(ratio, numbers.Integral) or ratio < 2:
        raise ValueError(f"{caller}: ratio must be a whole number >= 2, got {ratio!r}")


def _normals_of_distinct(distinct: np.ndarray) -> np.ndarray:
    """(D, 3) unit normals of distinct points, each of the plane fitted to its `CURVATURE_K` nearest
    (fitted with duplicates, a point repeated a few times filled its own neighbourhood and tilted
    its plane: the inserted points moved 7 times further off a sphere at 6 copies a point, a
    trial); zeros, so nothing is projected, for fewer than 3 distinct points."""
    if len(distinct) < 3:
        return np.zeros_like(distinct)
    return curvature_and_normals_np(distinct, min(CURVATURE_K, len(distinct)))[1]


def _distinct_neighbours(points: np.ndarray, count: int, distinct: np.ndarray, first: np.ndarray,
                         inverse: np.ndarray) -> np.ndarray:
    """(N, count) indices of each point's nearest neighbours at a distance above 0, nearest first:
    the point itself and its duplicates skipped, whose midpoints would be the point again. Found
    among the distinct points (`np.unique(points, axis=0, return_index=True, return_inverse=True)`:
    one index per distinct point); where a point has fewer than `count` distinct neighbours, the
    last (farthest) of them repeats."""
    if len(distinct) == len(points):  # no duplicates: the plain search (column 0 is the point itself)
        return cKDTree(points).query(points, k=count + 1)[1][:, 1:]
    k = min(count + 1, len(distinct))
    _, index = cKDTree(distinct).query(distinct, k=k)
    index = np.asarray(index).reshape(len(distinct), k)[:, 1:]  # column 0: the distinct point itself
    if index.shape[1] == 0:  # every point is the same point: nothing else to pair with
        return np.repeat(np.arange(len(points))[:, None], count, axis=1)
    index = index[:, np.minimum(np.arange(count), index.shape[1] - 1)]
    return first[index][inverse]


def upsample_patches(patches: np.ndarray, ratio: int = 4) -> tuple[np.ndarray, np.ndarray]:
    """`midpoint_upsample` on each of (B, K, 3) patches -> (B, K*r, 3) float32, (B, K*r) int64
    parents (slots in the patch), as `cadpu.inference.Upsampler.upsample_patches`; B may be 0."""
    patches = np.asarray(patches)
    if patches.ndim != 3 or patches.shape[2] != 3:
        raise ValueError(f"upsample_patches: patches must be (B, K, 3), got {patches.shape}")
    _check_ratio("upsample_patches", ratio)  # before the empty case, which took 2.5, 0 and -1 (a trial)
    if not len(patches):
        width = patches.shape[1] * ratio
        return np.zeros((0, width, 3), np.float32), np.zeros((0, width), np.int64)
    results = [midpoint_upsample(p, ratio) for p in patches]
    return (np.stack([r[0] for r in results]).astype(np.float32), np.stack([r[1] for r in results]))
