"""Point-set quality metrics (numpy, any size, k-d trees): Chamfer, Hausdorff, point-to-surface,
occupied-voxel precision/recall/F1. Distances are in the inputs' units.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree


def directed_distances(source: np.ndarray, target: np.ndarray) -> np.ndarray:
    """(len(source),) distance from every source point to its nearest target point."""
    distances, _ = cKDTree(np.asarray(target, dtype=np.float64)).query(
        np.asarray(source, dtype=np.float64), k=1, workers=-1)
    return distances


def chamfer_distance(a: np.ndarray, b: np.ndarray) -> float:
    """Mean of the two directed mean nearest-neighbour distances between (N, 3) and (M, 3)."""
    return chamfer_from_distances(directed_distances(a, b), directed_distances(b, a))


def hausdorff_distance(a: np.ndarray, b: np.ndarray, percentile: float = 100.0) -> float:
    """Symmetric Hausdorff distance: the larger of the two directed maxima; with percentile < 100,
    that percentile of each directed distance set instead of its maximum (robust variant)."""
    return hausdorff_from_distances(directed_distances(a, b), directed_distances(b, a), percentile)


def chamfer_from_distances(a_to_b: np.ndarray, b_to_a: np.ndarray) -> float:
    """`chamfer_distance` from the two directed distance sets, (N,) and (M,), already computed
    (e.g. by `directed_distances`, or by a k-d tree query made for another purpose as well)."""
    return float(0.5 * (np.mean(a_to_b) + np.mean(b_to_a)))


def hausdorff_from_distances(a_to_b: np.ndarray, b_to_a: np.ndarray, percentile: float = 100.0) -> float:
    """`hausdorff_distance` (with its `percentile`) from the two directed distance sets, (N,) and
    (M,), already computed."""
    return float(max(np.percentile(a_to_b, percentile), np.percentile(b_to_a, percentile)))


def point_to_surface(points: np.ndarray, vertices: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """(N,) unsigned distance of every point to a triangle mesh (Open3D ray-casting scene; an
    ImportError naming the `open3d` extra without it)."""
    from .o3d import o3d

    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(np.asarray(vertices, np.float32)),
                        o3d.core.Tensor(np.asarray(triangles, np.uint32)))
    query = o3d.core.Tensor(np.asarray(points, np.float32))
    return scene.compute_distance(query).numpy().astype(np.float64)


@dataclass(frozen=True)
class VoxelScore:
    """Occupied-voxel agreement of a prediction with a reference (fractions in [0, 1])."""

    precision: float
    recall: float
    f1: float


def occupied_voxels(points: np.ndarray, size: float) -> np.ndarray:
    """Unique integer voxel coordinates (V, 3) occupied by points, for cubes of edge `size`."""
    return np.unique(np.floor(np.asarray(points, dtype=np.float64) / size).astype(np.int64), axis=0)


def voxel_f1(predicted: np.ndarray, reference: np.ndarray, size: float = 0.1) -> VoxelScore:
    """Precision (occupied predicted voxels that the reference occupies), recall (occupied
    reference voxels the prediction occupies) and their F1, on a grid of `size` cubes."""
    pred, ref = occupied_voxels(predicted, size), occupied_voxels(reference, size)
    if len(pred) == 0 or len(ref) == 0:
        return VoxelScore(0.0, 0.0, 0.0)
    both = len(np.intersect1d(*_voxel_keys(pred, ref)))
    precision, recall = both / len(pred), both / len(ref)
    f1 = 2 * precision * recall / (precision + recall) if both else 0.0
    return VoxelScore(precision, recall, f1)


#: Bits per axis of a packed voxel key (three axes in one int64).
KEY_BITS = 21


def _voxel_keys(*voxel_sets: np.ndarray) -> tuple[np.ndarray, ...]:
    """One int64 per voxel of each (V, 3) set, equal exactly where the voxels are, for set
    operations between the sets: coordinates taken from the sets' common lowest corner, so clouds
    anywhere (UTM coordinates included) pack alike, and refused when they span more than 2^21
    voxels on an axis (210 km at 0.1 m), where keys would collide."""
    low = np.min([v.min(axis=0) for v in voxel_sets], axis=0)
    high = np.max([v.max(axis=0) for v in voxel_sets], axis=0)
    if np.any(high - low >= 1 << KEY_BITS):
        raise ValueError(f"voxel_f1: the clouds span {int((high - low).max()):,} voxels on an axis; at most "
                         f"{(1 << KEY_BITS) - 1:,} are supported (use larger voxels, or score nearer clouds)")
    keys = []
    for voxels in voxel_sets:
        shifted = voxels - low
        keys.append((shifted[:, 0] << (2 * KEY_BITS)) | (shifted[:, 1] << KEY_BITS) | shifted[:, 2])
    return tuple(keys)
