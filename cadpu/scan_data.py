"""LiDAR training patches: simulated 64-beam scans of procedural streets, thinned to 16 beams.

What a KITTI frame looks like to the network in the pipeline: the non-ground points of a scan,
cut by `cadpu.patches.partitioned_patches` (the pipeline's tiling) into 256-point patches whose
points lie on a few scan lines. To teach the network to fill the space between scan lines with
what a denser sensor would see (issue 5's 16-to-64-beam evaluation), a training pair is made
the same way from a simulated scan (`cadpu.synthetic.lidar`):

- input: a patch of the scan's non-ground points on rings offset, offset + 4, ... (16 of 64);
- ground truth: the full scan's non-ground points (all 64 rings) whose nearest input point is in
  the patch: about 4 per input point, brought to exactly 4 * 256 = 1,024 by `covering_sample`
  (every point kept when there are fewer); with the exact normals of the triangles they lie on;
- both normalised by the patch's centroid and radius, as inference normalises; with a vertical
  scale, z is multiplied by it first, as the pipeline's `tile.vertical_scale` does (the normals
  are transformed to stay normal to the scaled surface).

Ground is left out by its semantic labels, as the pipeline's ground stage leaves it out of tiling.
Deterministic given the street seed.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from .synthetic.lidar import HDL64E, LidarModel, SceneCaster, mount_pose, simulate_scan
from .patches import partitioned_patches
from .synthetic.scenes import make_scene
from .synthetic.street import LANE_HALF_WIDTH, is_ground

INPUT_POINTS = 256
TRUTH_POINTS = 1024
RATIO = 4
STREET_LENGTH = 120.0
#: Sensor positions along the street (metres), where the street has buildings on both sides.
SENSOR_X_RANGE = (0.0, 90.0)


def street_scan_patches(seed: int, scans: int, patches_per_scan: int, vertical_scale: float = 1.0,
                        model: LidarModel = HDL64E, scene_type: str = "urban",
                        ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Training pairs from `scans` simulated scans of street `seed` (see the module docstring).

    The street is `cadpu.synthetic.scenes.make_scene(scene_type, seed)` ("urban": the street of
    `make_street`, the only type before scene types were added; its pairs are unchanged). Each
    scan is taken at a random position and heading on the street's driving lanes, keeps a random
    ring offset in 0..3, and gives up to `patches_per_scan` random patches of its tiling
    (cut with z multiplied by `vertical_scale`), simulated with the sensor `model`.

    Returns:
        inputs (P, 256, 3), truth (P, 1024, 3), truth normals (P, 1024, 3), float32, each patch
        in its own unit sphere.
    """
    rng = np.random.default_rng([seed, 2])
    scene = make_scene(scene_type, seed, length_m=STREET_LENGTH, slope=float(rng.uniform(-0.03, 0.03)))
    caster = SceneCaster(scene)
    parts = []
    for i in range(scans):
        heading = float(rng.choice([0.0, np.pi]) + rng.normal(scale=0.05))
        lateral = float(rng.uniform(-0.8, 0.8) * LANE_HALF_WIDTH)
        pose = mount_pose(scene, float(rng.uniform(*SENSOR_X_RANGE)), lateral, heading)
        scan = simulate_scan(caster, pose, seed=int(rng.integers(2**31)), model=model)
        objects = ~is_ground(scan.labels)
        parts.append(thinned_scan_patches(scan.points[objects, :3], scan.ring[objects], scan.normals[objects],
                                          int(rng.integers(RATIO)), patches_per_scan, rng, vertical_scale))
    return tuple(np.concatenate(column) for column in zip(*parts))  # type: ignore[return-value]


def covering_sample(indices: np.ndarray, count: int, rng: np.random.Generator) -> np.ndarray:
    """`count` of `indices`, as evenly as possible: a random subset when there are enough, else every
    one the same number of times plus a random subset of them once more.

    A draw with replacement from about 1,000 points would leave a third of them out at random, so
    two draws of the same region would differ by most of the EMD a network can win (the EMDs
    measured on simulated scan patches: docs/results.md, "Training data").

    Returns:
        (count,) int64 entries of `indices`.
    """
    if len(indices) == 0:
        raise ValueError("covering_sample: no indices to draw from")
    repeats, remainder = divmod(count, len(indices))
    return np.concatenate([np.tile(indices, repeats), rng.choice(indices, remainder, replace=False)])


def thinned_scan_patches(points: np.ndarray, rings: np.ndarray, normals: np.ndarray, offset: int,
                         count: int, rng: np.random.Generator, vertical_scale: float = 1.0,
                         ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Training pairs from the non-ground points of one full scan.

    Args:
        points: (N, 3) non-ground points of the full scan, sensor frame, metres.
        rings: (N,) their ring ids. normals: (N, 3) their surface normals.
        offset: first ring kept in the input (rings offset, offset + 4, ...).
        count: at most this many patches, drawn at random from the tiling of the input.
        vertical_scale: z is multiplied by this before tiling and normalising (1: unscaled).

    Returns:
        inputs (P, 256, 3), truth (P, 1024, 3), normals (P, 1024, 3) float32, P <= count
        (0 when the thinned scan has fewer than 256 points).
    """
    axis_scale = np.array([1.0, 1.0, vertical_scale])
    points = np.asarray(points, dtype=np.float64) * axis_scale
    normals = np.asarray(normals, dtype=np.float64) / axis_scale  # inverse transpose of the scaling
    normals /= np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-12)
    kept = (np.asarray(rings) - offset) % RATIO == 0
    thinned = points[kept]
    if len(thinned) < INPUT_POINTS:
        empty = np.zeros((0, INPUT_POINTS, 3), np.float32)
        return empty, np.zeros((0, TRUTH_POINTS, 3), np.float32), np.zeros((0, TRUTH_POINTS, 3), np.float32)
    cover = partitioned_patches(thinned, INPUT_POINTS)
    _, nearest_input = cKDTree(thinned).query(points, workers=-1)
    chosen = rng.permutation(len(cover.point_index))[:count]
    inputs, truth, truth_normals = [], [], []
    for p in chosen:
        in_patch = np.zeros(len(thinned), dtype=bool)
        in_patch[cover.point_index[p]] = True
        region = np.flatnonzero(in_patch[nearest_input])
        picked = covering_sample(region, TRUTH_POINTS, rng)
        inputs.append(cover.normalized[p])
        truth.append((points[picked] - cover.centroid[p]) / cover.scale[p])
        truth_normals.append(normals[picked])
    return (np.stack(inputs).astype(np.float32), np.stack(truth).astype(np.float32),
            np.stack(truth_normals).astype(np.float32))
