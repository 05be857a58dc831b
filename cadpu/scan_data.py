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

`PatchFrames` keeps where each patch sits in its scan (centroid, radius, vertical scale) and which
truth points lie on the rings the input lacks, with those rings' elevations: what a loss scored
after ring snapping needs (`cadpu.losses.snapped_chamfer`), since the pipeline puts every
generated point on such a ring.
"""

from __future__ import annotations

from dataclasses import dataclass, fields

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
#: Rings between the input's that one patch's truth can span, at most (a patch spans a few input
#: scan lines; more distinct rings are dropped from its elevation list, farthest from the median first).
MAX_VIRTUAL_RINGS = 48


@dataclass(frozen=True)
class PatchFrames:
    """Where P patches of scan pairs sit in their scans.

    Attributes:
        centroid: (P, 3) float32, the input's centroid in the tiling's frame (sensor frame, metres,
            z multiplied by the vertical scale): a normalised point q is q * scale + centroid there.
        scale: (P,) float32, the input's radius in the same frame.
        vertical_scale: (P,) float32, the z factor of that frame (1: unscaled).
        truth_ring: (P, 1024) int16, for a truth point on a ring the input does not keep (where the
            pipeline puts generated points) that ring's place in `ring_elevations`; -1 for the
            points of the input's rings.
        ring_elevations: (P, MAX_VIRTUAL_RINGS) float32, the elevations (radians, seen from the
            sensor origin) of the patch's rings between the input's, each the median over its truth
            points, ascending; NaN pads the rest.
    """

    centroid: np.ndarray
    scale: np.ndarray
    vertical_scale: np.ndarray
    truth_ring: np.ndarray
    ring_elevations: np.ndarray

    def __len__(self) -> int:
        return int(self.scale.shape[0])

    def arrays(self) -> tuple[np.ndarray, ...]:
        """The fields in order: the frame arguments of `cadpu.losses.snapped_chamfer`."""
        return tuple(getattr(self, f.name) for f in fields(self))

    def subset(self, index: np.ndarray) -> "PatchFrames":
        """The frames of the patches at `index`."""
        return PatchFrames(*(array[index] for array in self.arrays()))

    @staticmethod
    def concatenate(parts: "list[PatchFrames]") -> "PatchFrames":
        return PatchFrames(*(np.concatenate([getattr(p, f.name) for p in parts]) for f in fields(PatchFrames)))

    @staticmethod
    def empty() -> "PatchFrames":
        return PatchFrames(np.zeros((0, 3), np.float32), np.zeros(0, np.float32), np.zeros(0, np.float32),
                           np.zeros((0, TRUTH_POINTS), np.int16), np.zeros((0, MAX_VIRTUAL_RINGS), np.float32))


def ring_elevations(elevation: np.ndarray, ring: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The median elevation of each distinct ring id of Q points.

    Returns:
        (MAX_VIRTUAL_RINGS,) float32 medians, ascending, NaN padded (the rings nearest the overall
        median kept when there are more), and (Q,) int16 each point's ring's place among them
        (-1 for a ring not kept).
    """
    ids, row = np.unique(ring, return_inverse=True)
    medians = np.array([np.median(elevation[row == i]) for i in range(len(ids))])
    kept = np.argsort(np.abs(medians - np.median(medians)))[:MAX_VIRTUAL_RINGS]
    order = kept[np.argsort(medians[kept])]
    place = np.full(len(ids), -1, np.int16)
    place[order] = np.arange(len(order))
    padded = np.full(MAX_VIRTUAL_RINGS, np.nan, np.float32)
    padded[:len(order)] = medians[order]
    return padded, place[row]


def street_scan_patches(seed: int, scans: int, patches_per_scan: int, vertical_scale: float = 1.0,
                        model: LidarModel = HDL64E, scene_type: str = "urban",
                        ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """`street_scan_pairs` without the patches' frames: inputs (P, 256, 3), truth (P, 1024, 3),
    truth normals (P, 1024, 3)."""
    return street_scan_pairs(seed, scans, patches_per_scan, vertical_scale, model, scene_type)[:3]


def street_scan_pairs(seed: int, scans: int, patches_per_scan: int, vertical_scale: float = 1.0,
                      model: LidarModel = HDL64E, scene_type: str = "urban",
                      ) -> tuple[np.ndarray, np.ndarray, np.ndarray, PatchFrames]:
    """Training pairs from `scans` simulated scans of street `seed` (see the module docstring).

    The street is `cadpu.synthetic.scenes.make_scene(scene_type, seed)` ("urban": the street of
    `make_street`, the only type before scene types were added; its pairs are unchanged). Each
    scan is taken at a random position and heading on the street's driving lanes, keeps a random
    ring offset in 0..3, and gives up to `patches_per_scan` random patches of its tiling
    (cut with z multiplied by `vertical_scale`), simulated with the sensor `model`.

    Returns:
        inputs (P, 256, 3), truth (P, 1024, 3), truth normals (P, 1024, 3), float32, each patch
        in its own unit sphere; and the patches' `PatchFrames`.
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
        parts.append(thinned_scan_pairs(scan.points[objects, :3], scan.ring[objects], scan.normals[objects],
                                        int(rng.integers(RATIO)), patches_per_scan, rng, vertical_scale))
    inputs, truth, normals = (np.concatenate([part[i] for part in parts]) for i in range(3))
    return inputs, truth, normals, PatchFrames.concatenate([part[3] for part in parts])


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
    """`thinned_scan_pairs` without the patches' frames: inputs (P, 256, 3), truth (P, 1024, 3),
    normals (P, 1024, 3)."""
    return thinned_scan_pairs(points, rings, normals, offset, count, rng, vertical_scale)[:3]


def thinned_scan_pairs(points: np.ndarray, rings: np.ndarray, normals: np.ndarray, offset: int,
                       count: int, rng: np.random.Generator, vertical_scale: float = 1.0,
                       ) -> tuple[np.ndarray, np.ndarray, np.ndarray, PatchFrames]:
    """Training pairs from the non-ground points of one full scan.

    Args:
        points: (N, 3) non-ground points of the full scan, sensor frame, metres.
        rings: (N,) their ring ids. normals: (N, 3) their surface normals.
        offset: first ring kept in the input (rings offset, offset + 4, ...).
        count: at most this many patches, drawn at random from the tiling of the input.
        vertical_scale: z is multiplied by this before tiling and normalising (1: unscaled).

    Returns:
        inputs (P, 256, 3), truth (P, 1024, 3), normals (P, 1024, 3) float32, P <= count
        (0 when the thinned scan has fewer than 256 points), and their `PatchFrames`.
    """
    axis_scale = np.array([1.0, 1.0, vertical_scale])
    metres = np.asarray(points, dtype=np.float64)
    elevation = np.arcsin(np.clip(metres[:, 2] / np.maximum(np.linalg.norm(metres, axis=1), 1e-9), -1.0, 1.0))
    rings = np.asarray(rings)
    between = (rings - offset) % RATIO != 0
    points = metres * axis_scale
    normals = np.asarray(normals, dtype=np.float64) / axis_scale  # inverse transpose of the scaling
    normals /= np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-12)
    kept = ~between
    thinned = points[kept]
    if len(thinned) < INPUT_POINTS:
        empty = np.zeros((0, INPUT_POINTS, 3), np.float32)
        return (empty, np.zeros((0, TRUTH_POINTS, 3), np.float32), np.zeros((0, TRUTH_POINTS, 3), np.float32),
                PatchFrames.empty())
    cover = partitioned_patches(thinned, INPUT_POINTS)
    _, nearest_input = cKDTree(thinned).query(points, workers=-1)
    chosen = rng.permutation(len(cover.point_index))[:count]
    inputs, truth, truth_normals, truth_ring, elevations = [], [], [], [], []
    for p in chosen:
        in_patch = np.zeros(len(thinned), dtype=bool)
        in_patch[cover.point_index[p]] = True
        region = np.flatnonzero(in_patch[nearest_input])
        picked = covering_sample(region, TRUTH_POINTS, rng)
        inputs.append(cover.normalized[p])
        truth.append((points[picked] - cover.centroid[p]) / cover.scale[p])
        truth_normals.append(normals[picked])
        place = np.full(len(picked), -1, np.int16)
        virtual = between[picked]
        medians = np.full(MAX_VIRTUAL_RINGS, np.nan, np.float32)
        if virtual.any():
            medians, place[virtual] = ring_elevations(elevation[picked[virtual]], rings[picked[virtual]])
        truth_ring.append(place)
        elevations.append(medians)
    frames = PatchFrames(np.asarray(cover.centroid, np.float32)[chosen], np.asarray(cover.scale, np.float32)[chosen],
                         np.full(len(chosen), vertical_scale, np.float32), np.stack(truth_ring),
                         np.stack(elevations))
    return (np.stack(inputs).astype(np.float32), np.stack(truth).astype(np.float32),
            np.stack(truth_normals).astype(np.float32), frames)
