"""Synthetic training patches (paper, section 5.1), generated from `cadpu.synthetic.shapes`, cached on disk.

A patch is a surface region of a mesh covering about 1/8 of it (what the test protocol's
8 clusters of 256 points cover). From the region's 10,000 uniform samples:
- input: 256 points, either uniform or scan-line structured (rows along a few parallel lines,
  as a rotating LiDAR samples a surface);
- ground truth: 1,024 points drawn without replacement with the probabilities of equation (3),
  from the region's curvature, with their exact face normals.
Both are normalised by the input's centroid and radius (what inference sees).
"""

from __future__ import annotations

import contextlib
import hashlib
import json
from dataclasses import asdict, dataclass, fields
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from .geometry import curvature_np
from .network import SAMPLING_EPS
from .scan_data import PatchFrames, street_scan_pairs
from .synthetic.lidar import HDL64E, LidarModel
from .synthetic.scenes import SCENE_TYPES
from .synthetic.shapes import Mesh, random_mesh, sample_surface

INPUT_POINTS = 256
TRUTH_POINTS = 1024
REGION_POINTS = 10_000
#: Changes the cache name of sets with scan patches when the way their truth is drawn changes.
SCAN_TRUTH_VERSION = 2
#: Changes the cache name of sets with scan patches simulated by the measured sensor
#: (`cadpu.synthetic.lidar.HDL64E`) whenever its output changes; `sensor: clean` sets keep their names.
SIMULATOR_VERSION = 2
SENSORS = ("measured", "clean")


@dataclass(frozen=True)
class DataSpec:
    """What a training set is made of; its hash names the cache file.

    Attributes:
        meshes: number of procedural meshes (seeds first_seed ...).
        patches_per_mesh: surface regions taken from each mesh.
        scanline_share: share of patches whose input is scan-line structured.
        first_seed: seed of the first mesh (held-out test meshes use seeds above 1,000,000) and
            of the first street.
        streets: procedural streets whose simulated scans give LiDAR patches (`cadpu.scan_data`);
            0 for none.
        scans_per_street: simulated scans per street. patches_per_scan: patches kept per scan.
        scan_vertical_scale: z factor the scan patches are cut and normalised with (the pipeline's
            `tile.vertical_scale`); 1 cuts them unscaled.
        sensor: the simulated LiDAR of the street scans: "measured" (`HDL64E`, the sensor measured
            on real KITTI scans) or "clean" (`LidarModel.clean()`, the sensor of the caches and
            weights made before it).
        scene_types: the scene types of `cadpu.synthetic.scenes` the streets cycle through: street i
            is of type scene_types[i % len(scene_types)] ("urban" alone: every set made before
            the types existed).
    """

    meshes: int = 200
    patches_per_mesh: int = 24
    scanline_share: float = 0.5
    first_seed: int = 0
    streets: int = 0
    scans_per_street: int = 4
    patches_per_scan: int = 40
    scan_vertical_scale: float = 1.0
    sensor: str = "measured"
    scene_types: tuple[str, ...] = ("urban",)

    def __post_init__(self) -> None:
        counts = {name: getattr(self, name) for name in ("meshes", "patches_per_mesh", "streets", "scans_per_street",
                                                         "patches_per_scan")}
        if all(isinstance(value, int) and not isinstance(value, bool) for value in counts.values()):
            # (values of another kind are named by the recipe's type checks)
            negative = [name for name, value in counts.items() if value < 0]
            if negative:
                raise ValueError(f"DataSpec: {', '.join(negative)} must be 0 or more")
            if self.meshes + self.streets == 0:
                raise ValueError("DataSpec: meshes and streets are both 0: no training data")
            empty = ([name for name in ("patches_per_mesh",) if self.meshes and not counts[name]]
                     + [name for name in ("scans_per_street", "patches_per_scan") if self.streets and not counts[name]])
            if empty:
                raise ValueError(f"DataSpec: {', '.join(empty)} must be at least 1 (0 makes no patches)")
        # (values of another kind are named by the recipe's type checks)
        if isinstance(self.scanline_share, (int, float)) and not 0 <= self.scanline_share <= 1:  # NaN too
            raise ValueError(f"DataSpec: scanline_share must be in [0, 1], got {self.scanline_share}")
        if isinstance(self.first_seed, int) and self.first_seed < 0:
            raise ValueError(f"DataSpec: first_seed must be 0 or more, got {self.first_seed}")
        if self.sensor not in SENSORS:
            raise ValueError(f"DataSpec: sensor must be one of {SENSORS}, got {self.sensor!r}")
        object.__setattr__(self, "scene_types", tuple(self.scene_types))  # YAML gives a list
        unknown = sorted(set(self.scene_types) - set(SCENE_TYPES))
        if not self.scene_types or unknown:
            raise ValueError(f"DataSpec: scene_types must be a non-empty list of {SCENE_TYPES}, got "
                             f"{list(self.scene_types)}")

    def key(self) -> str:
        """12 hex digits naming the cache of this set: a hash of the fields that change its content."""
        fields = asdict(self)
        if fields["scan_vertical_scale"] == 1.0:  # the default keeps the names of caches made before it
            del fields["scan_vertical_scale"]
        del fields["sensor"]  # mesh-only sets and clean-sensor sets keep the names made before it
        if self.scene_types == ("urban",):  # urban-only sets keep the names made before the types
            del fields["scene_types"]
        if self.streets:  # scan truths are drawn by covering_sample since version 2
            fields["scan_truth_version"] = SCAN_TRUTH_VERSION
            if self.sensor == "measured":
                fields["simulator_version"] = SIMULATOR_VERSION
        return hashlib.sha256(json.dumps(fields, sort_keys=True).encode()).hexdigest()[:12]


@dataclass(frozen=True)
class PatchSet:
    """Training pairs: inputs (P, 256, 3), truth (P, 1024, 3), truth_normals (P, 1024, 3), float32,
    normalised to the input's unit sphere; scanline (P,) bool, True where the input lies on scan lines
    (scan-line inputs of meshes and patches of simulated street scans); frames: where each patch
    sits in its scan (`cadpu.scan_data.PatchFrames`), for sets of scan patches only (None otherwise)."""

    inputs: np.ndarray
    truth: np.ndarray
    truth_normals: np.ndarray
    scanline: np.ndarray
    frames: PatchFrames | None = None

    def __len__(self) -> int:
        return int(self.inputs.shape[0])

    def subset(self, index: np.ndarray) -> "PatchSet":
        """The pairs at `index`, with their frames."""
        return PatchSet(*(getattr(self, name)[index] for name in PAIR_ARRAYS),
                        None if self.frames is None else self.frames.subset(index))

    @staticmethod
    def concatenate(sets: "list[PatchSet]") -> "PatchSet":
        """One set of all `sets`' pairs, in order; with frames only when every set has them."""
        arrays = [np.concatenate([getattr(s, name) for s in sets]) for name in PAIR_ARRAYS]
        frames = [s.frames for s in sets]
        return PatchSet(*arrays, PatchFrames.concatenate(frames) if all(f is not None for f in frames) else None)


#: The arrays every `PatchSet` has (its frames aside).
PAIR_ARRAYS = ("inputs", "truth", "truth_normals", "scanline")


def curvature_adaptive_subset(kappa: np.ndarray, count: int, rng: np.random.Generator) -> np.ndarray:
    """Indices of `count` points drawn without replacement with the probabilities of equation (3)."""
    weights = np.log(kappa + 1.0 + SAMPLING_EPS)
    return rng.choice(len(kappa), size=count, replace=False, p=weights / weights.sum())


def scanline_input(region: np.ndarray, count: int, rng: np.random.Generator) -> np.ndarray:
    """`count` points of `region` lying on a few parallel lines, as a spinning LiDAR samples them.

    The lines are the region cut by 4-8 parallel planes whose normal is close to vertical (a
    rotating sensor sweeps nearly horizontal cones); along each line the points are thinned evenly.

    Args:
        region: (M, 3) dense uniform samples of one surface region.

    Returns:
        (count, 3) float64 indices-free point set (may repeat a point when a line is short).
    """
    tilt = rng.normal(scale=0.15, size=2)
    normal = np.array([tilt[0], tilt[1], 1.0])
    normal /= np.linalg.norm(normal)
    height = region @ normal
    lines = int(rng.integers(4, 9))
    spacing = (height.max() - height.min()) / lines
    offset = height.min() + spacing * (rng.random() + np.arange(lines))
    nearest_line = np.abs(height[:, None] - offset[None, :])
    tolerance = 0.04 * spacing
    on_line = nearest_line.min(1) < tolerance
    if on_line.sum() < count:  # degenerate region (e.g. a flat cap facing the lines): uniform
        return region[rng.choice(len(region), count, replace=False)]
    candidates = np.flatnonzero(on_line)
    return region[rng.choice(candidates, count, replace=False)]


def mesh_patches(mesh: Mesh, patches: int, scanline_share: float, rng: np.random.Generator
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Training pairs from one mesh; see the module docstring.

    Returns:
        inputs (patches, 256, 3), truth (patches, 1024, 3), normals (patches, 1024, 3),
        scanline (patches,) bool.
    """
    dense, normals = sample_surface(mesh, REGION_POINTS * 8, rng)
    tree = cKDTree(dense)
    seeds = dense[rng.choice(len(dense), patches, replace=False)]
    inputs, truth, truth_normals, scanline = [], [], [], []
    for seed in seeds:
        _, index = tree.query(seed, k=REGION_POINTS)
        region, region_normals = dense[index], normals[index]
        kappa = curvature_np(region)
        picked = curvature_adaptive_subset(kappa, TRUTH_POINTS, rng)
        is_scan = rng.random() < scanline_share
        if is_scan:
            source = scanline_input(region, INPUT_POINTS, rng)
        else:
            source = region[rng.choice(REGION_POINTS, INPUT_POINTS, replace=False)]
        centroid = source.mean(0)
        scale = np.linalg.norm(source - centroid, axis=1).max()
        inputs.append((source - centroid) / scale)
        truth.append((region[picked] - centroid) / scale)
        truth_normals.append(region_normals[picked])
        scanline.append(is_scan)
    return (np.stack(inputs).astype(np.float32), np.stack(truth).astype(np.float32),
            np.stack(truth_normals).astype(np.float32), np.array(scanline))


def _mesh_part(spec: DataSpec, index: int) -> tuple[np.ndarray, ...]:
    """The patches of mesh `index` of `spec` (seed first_seed + index)."""
    seed = spec.first_seed + index
    rng = np.random.default_rng([seed, 1])
    return mesh_patches(random_mesh(seed), spec.patches_per_mesh, spec.scanline_share, rng)


def _mesh_set(spec: DataSpec, index: int) -> PatchSet:
    return PatchSet(*_mesh_part(spec, index))


def _street_part(spec: DataSpec, index: int) -> PatchSet:
    """The patches of street `index` of `spec` (seed first_seed + index, of type
    scene_types[index % len(scene_types)]), all scan-line inputs, with their frames."""
    inputs, truth, normals, frames = street_scan_pairs(spec.first_seed + index, spec.scans_per_street,
                                                       spec.patches_per_scan, spec.scan_vertical_scale,
                                                       sensor_model(spec.sensor),
                                                       spec.scene_types[index % len(spec.scene_types)])
    return PatchSet(inputs, truth, normals, np.ones(len(inputs), dtype=bool), frames)


def build_patches(spec: DataSpec, progress: bool = False, workers: int = 1) -> PatchSet:
    """Generate the patch set of `spec` (deterministic: mesh i uses seed first_seed + i, street i
    likewise, so the set is the same for any number of `workers` processes)."""
    from concurrent.futures import ProcessPoolExecutor
    from functools import partial

    from tqdm import tqdm

    jobs = [(_mesh_set, spec.meshes, "mesh"), (_street_part, spec.streets, "street")]
    parts = []
    with ProcessPoolExecutor(workers) if workers > 1 else contextlib.nullcontext() as pool:
        for part, count, unit in jobs:
            made = map(partial(part, spec), range(count)) if pool is None else \
                pool.map(partial(part, spec), range(count), chunksize=4)
            parts.extend(tqdm(made, total=count, disable=not progress or not count, desc="patches", unit=unit))
    return PatchSet.concatenate(parts)


def sensor_model(sensor: str) -> LidarModel:
    """The simulated LiDAR a `DataSpec.sensor` names: "measured" -> `HDL64E`, "clean" -> `LidarModel.clean()`."""
    return HDL64E if sensor == "measured" else LidarModel.clean()


def load_or_build(spec: DataSpec, cache_dir: Path, progress: bool = True, workers: int = 1) -> PatchSet:
    """The patch set of `spec` from `cache_dir/patches-<hash>.npz`, generated (by `workers`
    processes) and saved if absent."""
    path = Path(cache_dir) / f"patches-{spec.key()}.npz"
    if path.is_file():
        with np.load(path) as saved:
            frame_names = [f"frames_{f.name}" for f in fields(PatchFrames)]
            frames = PatchFrames(*(saved[n] for n in frame_names)) if set(frame_names) <= set(saved.files) else None
            if frames is not None or not spec.streets or spec.meshes:
                return PatchSet(*(saved[name] for name in PAIR_ARRAYS), frames)
            # a street set cached before the frames were kept: made again, with them (same pairs)
    patches = build_patches(spec, progress, workers)
    path.parent.mkdir(parents=True, exist_ok=True)
    temporary = path.with_suffix(".tmp.npz")
    arrays = {name: getattr(patches, name) for name in PAIR_ARRAYS}
    if patches.frames is not None:
        arrays.update({f"frames_{f.name}": getattr(patches.frames, f.name) for f in fields(PatchFrames)})
    np.savez(temporary, **arrays)
    temporary.replace(path)
    return patches


def augment(inputs: np.ndarray, truth: np.ndarray, normals: np.ndarray, rng: np.random.Generator,
            jitter: float = 0.005) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Random rotation about z plus a small tilt, scale in [0.8, 1.0], Gaussian jitter on the input.

    Rotation is mostly about the vertical so scan-line inputs keep near-horizontal lines.

    Args:
        inputs (B, 256, 3), truth (B, 1024, 3), normals (B, 1024, 3).

    Returns:
        The augmented arrays, float32.
    """
    return augment_with_transform(inputs, truth, normals, rng, jitter)[:3]


#: Training augmentations (`Recipe.augmentation`): "full" (`augment`), or "azimuth": a rotation
#: about the vertical alone, the one change of a scan patch that a scan can show (the sensor turned
#: about its axis), so that the network never trains on tilted, shrunk or jittered rings.
AUGMENTATIONS = ("full", "azimuth")


def augment_with_transform(inputs: np.ndarray, truth: np.ndarray, normals: np.ndarray, rng: np.random.Generator,
                           jitter: float = 0.005, kind: str = "full") -> tuple[np.ndarray, ...]:
    """`augment` (or with `kind` "azimuth", a rotation about z alone), also returning its transform:
    the (B, 3, 3) rotations R and (B,) scales s, float32, a point q of a patch going to s * R q
    (before the input's jitter)."""
    batch = inputs.shape[0]
    if kind == "azimuth":
        rotations = np.stack([_rotation(a, np.zeros(2)) for a in rng.uniform(0, 2 * np.pi, batch)])
        turned = [np.einsum("bij,bnj->bni", rotations, a).astype(np.float32) for a in (inputs, truth, normals)]
        return (*turned, rotations.astype(np.float32), np.ones(batch, np.float32))
    angle = rng.uniform(0, 2 * np.pi, batch)
    tilt = rng.normal(scale=0.1, size=(batch, 2))
    rotations = np.stack([_rotation(a, t) for a, t in zip(angle, tilt)])
    scale = rng.uniform(0.8, 1.0, (batch, 1, 1))
    inputs = np.einsum("bij,bnj->bni", rotations, inputs) * scale
    truth = np.einsum("bij,bnj->bni", rotations, truth) * scale
    normals = np.einsum("bij,bnj->bni", rotations, normals)
    inputs = inputs + rng.normal(scale=jitter, size=inputs.shape)
    return (inputs.astype(np.float32), truth.astype(np.float32), normals.astype(np.float32),
            rotations.astype(np.float32), scale[:, 0, 0].astype(np.float32))


def _rotation(angle: float, tilt: np.ndarray) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    about_z = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    cx, sx, cy, sy = np.cos(tilt[0]), np.sin(tilt[0]), np.cos(tilt[1]), np.sin(tilt[1])
    about_x = np.array([[1.0, 0.0, 0.0], [0.0, cx, -sx], [0.0, sx, cx]])
    about_y = np.array([[cy, 0.0, sy], [0.0, 1.0, 0.0], [-sy, 0.0, cy]])
    return about_z @ about_x @ about_y
