"""Inference with a trained CAD-PU generator: batches of patches, or a whole object.

Ratios: the weights are trained at one ratio (4). A ratio that is a power of it (16, 64) runs the
network repeatedly (16 = 4 then 4 again): for patches, each 1,024-point result is cut into 4 equal
disjoint clusters of 256 that are upsampled again (exactly 4,096 points per patch); for whole
objects, each pass re-tiles the result into overlapping patches. Any other ratio is refused,
since the network has never been trained to produce it.

Oversampling: with `oversample` m > 1 the network makes m times the points of a pass, and farthest
point sampling keeps the pass's share of each patch's, so that the points kept are evenly spread
and reach further into the gaps the input left (the selection of PU-GAN's and Grad-PU's test
procedures; figures in the model card, "Oversampled patches").

Offset scale: with `offset_scale` s != 1 every generated point moves along the line from its
parent to s times its distance from it (its offset from the parent times s), before any
selection. The networks place their points much closer to their parents than samples of the
surface lie to the nearest input point, so the gaps between input points stay thin; larger
offsets reach further into them, at the cost of leaving the surface where it curves (figures, and
how the default was chosen: model card, "Scaled offsets").
"""

from __future__ import annotations

import math
import numbers
import warnings
from pathlib import Path

import numpy as np
import torch

from . import engines
from .checks import check_finite_points
from .geometry import farthest_point_sampling
from .kernels import farthest_point_picks
from .patches import equal_clusters, keep_owned, overlapping_patches, spare_points, to_count
from .network import Generator
from .weights import load_generator

#: Patches per forward pass on a CPU: the fastest per patch at 1 thread, as each pipeline worker
#: runs, in bench/inference.py's sweep (docs/inference.md, "Batch size").
DEFAULT_BATCH_SIZE = 4
#: Patches per forward pass on CUDA, where small batches leave the GPU waiting on kernel launches:
#: about one frame's patches a pass (docs/inference.md, "On a GPU").
DEFAULT_CUDA_BATCH_SIZE = 256
#: Points per patch the network was trained on.
PATCH_POINTS = 256
#: Engines "auto" tries, in order, on a CPU (the first installed one wins; eager always is).
#: Eager first: no fp32 engine was faster at the pipeline's 1 thread and batch 4 (docs/inference.md).
AUTO_ENGINES = ("eager",)
#: What `engine` accepts.
ENGINE_CHOICES = ("auto", *engines.ENGINES)


#: Candidates per kept point `oversample=None` gives weights whose training drew copies
#: curvature-adaptively (alpha < 1): such training gave curved points more copies than the ratio,
#: so the extra candidates' grid codes are ones the network has placed. Alpha = 1 weights only ever
#: placed `ratio` copies per point; their extra candidates leave the surface, so they get 1 (model
#: card, "Oversampled patches").
ADAPTIVE_OVERSAMPLE = 2
#: The most candidates per kept point: beyond 64 copies of a point the grid codes run out
#: (`Generator.expansion` clamps the rank) and candidates repeat.
MAX_OVERSAMPLE = 8
#: The offset scale `offset_scale=None` gives weights trained with alpha < 1 (the objects' default
#: file): the largest whose points stayed, on the held-out meshes it was chosen on, within 80% of the
#: midpoint baseline's mean distance from the surface (model card, "Scaled offsets"). Alpha = 1
#: weights get 1, as trained: the pipeline's default file is one, and the pipeline's settings were
#: chosen on the simulated streets with its points where the network puts them.
ADAPTIVE_OFFSET_SCALE = 1.4
#: The largest offset scale accepted: a bound against slips, far above any that keeps the points
#: near the surface (model card, "Scaled offsets").
MAX_OFFSET_SCALE = 4.0


#: How far outside the unit sphere a normalised patch's points may lie (float rounding).
UNIT_SPHERE_SLACK = 1.001


#: The largest seed: torch's generators take a signed 64-bit one.
MAX_SEED = 2**63 - 1


def _as_array(caller: str, points: object, dtype: type) -> np.ndarray:
    """`points` as a numpy array of `dtype`; ValueError naming `caller` for what is not numbers (an
    Open3D point cloud gave numpy's "float() argument must be ... not 'PointCloud'")."""
    try:
        return np.asarray(points, dtype=dtype)
    except (TypeError, ValueError):
        hint = " (an Open3D point cloud: np.asarray(cloud.points))" if hasattr(points, "points") else ""
        raise ValueError(f"{caller}: points must be an array of x, y, z numbers{hint}, got "
                         f"{type(points).__name__}") from None


def learned_from_scans(meta: dict) -> bool:
    """Whether weights with this meta learned from LiDAR scans (a recipe of simulated streets, or a
    user's scans by `kitti-pu finetune`) rather than from object meshes. The adaptive oversampling
    and offset scale were chosen on meshes for the object files; the pipeline runs the LiDAR files
    with neither, and `Upsampler(LiDAR file)` gave its alpha 0.5 one both (a researcher's trial)."""
    data = (meta.get("recipe") or {}).get("data") or {}
    return bool(data.get("streets")) or "finetuned_from" in meta


def passes_for(ratio: int, trained_ratio: int) -> int:
    """How many network passes make `ratio` from `trained_ratio` (ratio = trained ** passes).

    Raises ValueError for a ratio that is not a power of the trained one.
    """
    passes = round(math.log(ratio, trained_ratio)) if ratio > 1 else 0
    if passes < 1 or trained_ratio ** passes != ratio:
        raise ValueError(f"ratio {ratio} is not the trained ratio {trained_ratio} or a power of it "
                         f"(supported: {trained_ratio}, {trained_ratio ** 2}, {trained_ratio ** 3}, ...)")
    return passes


def _device(device: str) -> torch.device:
    """The torch device of `Upsampler`'s `device` argument: "auto" (CUDA when available), "cpu",
    "cuda" or "cuda:N". ValueError for another name, or for CUDA where torch has none."""
    if device == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    try:
        chosen = torch.device(device)
    except (RuntimeError, TypeError):
        raise ValueError(f"device {device!r} is not one of 'auto', 'cpu', 'cuda', 'cuda:N'") from None
    if chosen.type not in ("cpu", "cuda"):
        raise ValueError(f"device {device!r} is not one of 'auto', 'cpu', 'cuda', 'cuda:N'")
    if chosen.type == "cuda" and not torch.cuda.is_available():
        raise ValueError(f"device {device!r}: this torch has no CUDA device (use 'cpu' or 'auto')")
    if chosen.type == "cuda" and chosen.index is not None and chosen.index >= torch.cuda.device_count():
        raise ValueError(f"device {device!r}: this machine has {torch.cuda.device_count()} CUDA device(s), "
                         f"numbered from 0")
    return chosen


class Upsampler:
    """A loaded generator ready to upsample normalised patches or whole point sets.

    Args:
        weights: a weights file's path, or a shipped file's name ("cadpu_r4_lidar_alpha1", the
            pipeline's; the names are those in `cadpu/weights/`); None = the shipped `cadpu_r4`.
        ratio: output points per input point; None = the trained ratio.
        device: "cpu", "cuda" or "auto" (CUDA when available).
        batch_size: patches per forward pass (None = DEFAULT_BATCH_SIZE on a CPU,
            DEFAULT_CUDA_BATCH_SIZE on CUDA); the output does not depend on it, but for the int8
            engines, whose dynamic quantisation scales each batch's activations by that batch's
            range (a trial measured points moving by up to 1.2e-2 between batch sizes 1 and 4).
        num_threads: torch intra-op threads (None or 0 leaves torch's setting alone).
        oversample: candidates made per point kept, a whole number from 1 to MAX_OVERSAMPLE: each
            pass makes `oversample` times its points and keeps, by farthest point sampling within
            each patch, as many as it would make without, in the order they were made (None:
            ADAPTIVE_OVERSAMPLE for object weights with alpha < 1; 1, no selection, for alpha = 1
            weights and for weights that learned from LiDAR scans, `learned_from_scans`).
        offset_scale: > 0, at most MAX_OFFSET_SCALE: each generated point is moved to
            `offset_scale` times its distance from its parent, along the same line, before the
            oversampling's selection (None: ADAPTIVE_OFFSET_SCALE for object weights with alpha < 1;
            1, where the network puts them, for alpha = 1 weights and LiDAR ones). See the module
            docstring.
        seed: seed of the curvature-adaptive draws (weights with alpha < 1) and of
            `upsample_object`'s tiling (the first farthest point seed); equal seeds give
            identical outputs. Each call draws from one stream seeded so, patch after patch: the
            same for any batch size, but a patch's draws depend on its place in the call (the
            patches before it), so upsample a set of patches in one call to reproduce it.
        engine: what runs the learned part of the network (`cadpu.engines`; the seeded expansion
            always runs in torch): "auto" (the first of AUTO_ENGINES installed, on a CPU; eager on
            CUDA), "eager", or any name in `cadpu.engines.ENGINES`. A named engine whose package
            is missing falls back to eager with a warning.
        layout: memory layout of the EdgeConv edge tensors, one of `cadpu.engines.LAYOUTS`
            (None: the network's default in torch, `cadpu.engines.EXPORT_LAYOUT` in exported graphs).
        generator: a network in memory to use instead of loading `weights` (a training run scoring
            its current weights); its checksum is then "" and its meta empty.

    Attributes:
        ratio, trained_ratio, oversample, offset_scale, checksum (SHA-256 of the weights file), meta
        (training metadata), engine (the engine in use).

    Raises:
        cadpu.weights.WeightsError for a missing or corrupt weights file; ValueError for a ratio
        that is not a whole number or not one the weights can make, a batch size that is not a
        whole number of at least 1, an oversample that is not a whole number from 1 to
        MAX_OVERSAMPLE, an offset_scale that is not a number above 0 and at most MAX_OFFSET_SCALE, a
        thread count that is not a whole number of at least 0 (0 or None: torch's own), an engine
        that is not one of ENGINE_CHOICES (or not "auto"/"eager" on CUDA), or a device that is not
        one of "auto", "cpu", "cuda", "cuda:N" or is CUDA without CUDA.
    """

    def __init__(self, weights: str | Path | None = None, ratio: int | None = None, device: str = "auto",
                 batch_size: int | None = None, num_threads: int | None = None, seed: int = 0,
                 engine: str = "auto", layout: str | None = None, generator: Generator | None = None,
                 oversample: int | None = None, offset_scale: float | None = None) -> None:
        if engine not in ENGINE_CHOICES:
            raise ValueError(f"unknown inference engine {engine!r}; choose one of {ENGINE_CHOICES}")
        sizes = (("ratio", ratio, None, None), ("batch_size", batch_size, 1, None),
                 ("num_threads", num_threads, 0, None), ("oversample", oversample, 1, MAX_OVERSAMPLE))
        for name, value, least, most in sizes:
            if value is not None and (isinstance(value, bool) or not isinstance(value, numbers.Integral)
                                      or (least is not None and value < least) or (most is not None and value > most)):
                bounds = (f" from {least} to {most}" if most is not None else
                          "" if least is None else f" of at least {least}")
                raise ValueError(f"Upsampler: {name} must be a whole number{bounds} (or None), got {value!r}")
        if offset_scale is not None and (isinstance(offset_scale, bool) or not isinstance(offset_scale, numbers.Real)
                                         or not 0 < offset_scale <= MAX_OFFSET_SCALE):
            raise ValueError(f"Upsampler: offset_scale must be a number above 0 and at most {MAX_OFFSET_SCALE:g} "
                             f"(or None), got {offset_scale!r}")
        if isinstance(seed, bool) or not isinstance(seed, numbers.Integral) or not 0 <= seed <= MAX_SEED:
            # found here, not at the first upsampling as torch's or numpy's error
            raise ValueError(f"Upsampler: seed must be a whole number from 0 to {MAX_SEED}, got {seed!r}")
        if num_threads:
            torch.set_num_threads(num_threads)
        self.device = _device(device)
        if generator is None:
            generator, self.checksum, self.meta = load_generator(weights)
        else:
            self.checksum, self.meta = "", {}
        self.generator = generator.to(self.device).eval()
        self.trained_ratio = generator.ratio
        self.ratio = self.trained_ratio if ratio is None else ratio
        self.passes = passes_for(self.ratio, self.trained_ratio)
        # the two were chosen on object meshes for object weights; a LiDAR file keeps the pipeline's
        adaptive = generator.alpha < 1 and not learned_from_scans(self.meta)
        if oversample is None:
            oversample = ADAPTIVE_OVERSAMPLE if adaptive else 1
        self.oversample = int(oversample)
        if offset_scale is None:
            offset_scale = ADAPTIVE_OFFSET_SCALE if adaptive else 1.0
        self.offset_scale = float(offset_scale)
        default_batch = DEFAULT_CUDA_BATCH_SIZE if self.device.type == "cuda" else DEFAULT_BATCH_SIZE
        self.batch_size = batch_size or default_batch
        self.seed = int(seed)  # numpy integers too
        if layout is not None:
            engines.set_layout(self.generator, layout)
        self.engine, self._decode = self._engine(engine, layout)

    def _engine(self, engine: str, layout: str | None) -> tuple[str, engines.Decode]:
        """The engine to use for the requested name, and its decode callable."""
        if self.device.type != "cpu":
            if engine not in ("auto", "eager"):
                raise ValueError(f"inference engine {engine!r} runs on a CPU only; use 'auto' or 'eager' "
                                 f"on {self.device.type}")
            return "eager", engines.build("eager", self.generator, self.trained_ratio)
        for name in AUTO_ENGINES if engine == "auto" else (engine, "eager"):
            try:
                return name, engines.build(name, self.generator, self.trained_ratio * self.oversample,
                                           layout=layout)
            except engines.EngineUnavailable as error:
                if engine != "auto":
                    warnings.warn(f"{error}; using torch eager instead", stacklevel=3)
        raise AssertionError("eager is always available")  # pragma: no cover

    def _forward(self, patches: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """One trained-ratio pass over (B, K, 3) patches, B >= 1, in batches: (B, K * trained ratio, 3)
        points and (B, K * trained ratio) parents, the kept share of the candidates when oversampling."""
        out_points, out_parents = [], []
        sampler = torch.Generator().manual_seed(self.seed)  # on the CPU: see Generator.expansion
        made = self.trained_ratio * self.oversample
        for start in range(0, len(patches), self.batch_size):
            batch = torch.from_numpy(np.ascontiguousarray(patches[start:start + self.batch_size],
                                                          dtype=np.float32)).to(self.device)
            with torch.inference_mode():
                parents, rank, frames, radius = self.generator.expansion(batch, made, sampler)
            points = self._decode(batch, parents, rank, frames, radius)
            if self.offset_scale != 1.0:
                points = self._scale_offsets(batch, points, parents, self.offset_scale)
            if self.oversample > 1:
                points, parents = self._keep_spread(points, parents, batch.shape[1] * self.trained_ratio)
            out_points.append(points.cpu().numpy())
            out_parents.append(parents.cpu().numpy())
        return np.concatenate(out_points), np.concatenate(out_parents)

    @staticmethod
    def _scale_offsets(patches: torch.Tensor, points: torch.Tensor, parents: torch.Tensor,
                       scale: float) -> torch.Tensor:
        """(B, M, 3) `points` moved to `scale` times their distance from their parents (slots
        (B, M) into the (B, K, 3) `patches`), along the line from each parent."""
        origin = patches.gather(1, parents[..., None].expand(-1, -1, 3))
        return origin + scale * (points - origin)

    @staticmethod
    def _keep_spread(points: torch.Tensor, parents: torch.Tensor, count: int) -> tuple[torch.Tensor, torch.Tensor]:
        """`count` of each patch's (B, M, 3) candidate points, and their parents, by farthest point
        sampling: compiled on a CPU, torch's loop where the points are (on CUDA). Kept in the order
        they were made (sorted picks), so that a pick swapped by float rounding moves one point,
        not the order of all those after it, and a parent's copies stay side by side."""
        if points.device.type == "cpu":
            kept = torch.from_numpy(farthest_point_picks(points.numpy(), count))
        else:
            kept = farthest_point_sampling(points, count)
        kept = kept.sort(dim=1).values
        return points.gather(1, kept[..., None].expand(-1, -1, 3)), parents.gather(1, kept)

    def upsample_patches(self, patches: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Upsample normalised patches.

        Args:
            patches: (B, K, 3) float32 patches in the unit sphere (K = 256 as trained).

        Returns:
            points (B, K * ratio, 3) float32 in the same normalised frame, and parents
            (B, K * ratio) int64: slot 0..K-1 of the input point each output point came from.
        """
        patches = _as_array("upsample_patches", patches, np.float32)
        if patches.ndim != 3 or patches.shape[2] != 3:
            raise ValueError(f"upsample_patches: patches must be (B, K, 3), got {patches.shape}")
        self.check_patch_points(patches.shape[1])
        check_finite_points("upsample_patches", patches)
        largest = float(np.sqrt((patches ** 2).sum(-1)).max()) if patches.size else 0.0
        if largest > UNIT_SPHERE_SLACK:
            raise ValueError(f"upsample_patches: patches must be normalised to the unit sphere (centred, divided "
                             f"by their largest radius); a point lies {largest:.3g} from the origin "
                             "(`upsample_object` takes points in any frame)")
        if not len(patches):
            width = patches.shape[1] * self.ratio
            return np.zeros((0, width, 3), np.float32), np.zeros((0, width), np.int64)
        points, parents = self._forward(patches)
        for _ in range(self.passes - 1):  # higher powers: each result upsampled again
            results = [self._cluster_pass(p) for p in points]
            points = np.stack([r[0] for r in results])
            parents = np.stack([parents[i][r[1]] for i, r in enumerate(results)])
        return points, parents

    def check_patch_points(self, k: int) -> None:
        """Raise ValueError, naming what would work, when patches of `k` points cannot be upsampled
        at this ratio: fewer than the network's neighbourhoods need; for ratios of several passes,
        k * trained ratio points that do not split into a power of two of 256-point clusters; or,
        for an exported engine, another size than the graph was traced on."""
        if self.engine in engines.EXPORTED and k != engines.EXPORTED_PATCH_POINTS:
            # found here (and so by the pipeline's preflight), not as the runtime's shape error
            raise ValueError(f"upsample_patches: patches of {k} points; the {self.engine} engine runs a graph "
                             f"traced on patches of {engines.EXPORTED_PATCH_POINTS} (use engine 'eager' for "
                             "other sizes)")
        if k < self.generator.min_points:
            raise ValueError(f"upsample_patches: patches of {k} points; this network needs at least "
                             f"{self.generator.min_points} per patch (its neighbourhoods; it was trained on "
                             f"{PATCH_POINTS}); `upsample_object` cuts a whole point set into such patches")
        clusters, rest = divmod(k * self.trained_ratio, PATCH_POINTS)
        if self.passes > 1 and (rest or clusters & (clusters - 1)):
            sizes = ", ".join(str(PATCH_POINTS * 2 ** m // self.trained_ratio) for m in range(4)
                              if PATCH_POINTS * 2 ** m // self.trained_ratio >= self.generator.min_points)
            raise ValueError(f"upsample_patches: ratio {self.ratio} upsamples each patch's {k} * {self.trained_ratio} "
                             f"points again in clusters of {PATCH_POINTS}, which needs a power of two of them: "
                             f"patches of {sizes}, ... points, not {k}")

    def _cluster_pass(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """One trained-ratio pass over a set of K * r^j points, cut into equal disjoint clusters of
        K (the paper's test protocol), so the output has exactly r times as many points.

        Returns points (r * M, 3) float32 in the frame of `points`, and the index of each
        one's source point."""
        k = PATCH_POINTS
        clusters = equal_clusters(points, len(points) // k)
        members = points[clusters]
        centroid = members.mean(axis=1, keepdims=True)
        radius = np.linalg.norm(members - centroid, axis=2).max(axis=1)[:, None, None]
        generated, slots = self._forward(((members - centroid) / radius).astype(np.float32))
        source = np.take_along_axis(clusters, slots, axis=1)
        return (generated * radius + centroid).reshape(-1, 3).astype(np.float32), source.reshape(-1)

    def _object_pass(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """One trained-ratio pass over a whole point set: tile, upsample, keep owned points, and
        make their count exactly trained ratio * M (`to_count`: curvature-adaptive draws keep
        about that many).

        Returns points (trained ratio * M, 3) float64 and the index of each one's source point."""
        cover = overlapping_patches(points, patch_size=PATCH_POINTS, seed=self.seed, stray_seeds=True)
        generated, parents = self._forward(cover.normalized)
        kept, source = keep_owned(cover, generated, parents)
        count = self.trained_ratio * len(points)
        if len(kept) == count:  # uniform expansion (alpha = 1): every parent's copies kept
            return kept, source
        return to_count(kept, source, count, *spare_points(cover, generated, parents), points)

    def upsample_object(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Upsample a whole point set of any size >= 256 (tiled into overlapping patches).

        A point given several times is upsampled once, as one point: its copies add nothing to the
        surface, and filled its own neighbourhood (about 6 points out for each one in, with the
        oversampling's selection; at 12 copies or more, every output point sat on its parent).
        The distinct points are tiled in one order whatever the input's (sorted by x, then y,
        then z), so a shuffled input gives the same points: the tiling's first seed and the
        network's draws follow the order.

        Args:
            points: (M, 3) in any frame and unit, at least 256 distinct.

        Returns:
            points (ratio * D, 3) float64 in the input frame (D: the distinct input points), and
            source (same length) int64: the index of the input point each output point descends
            from (of a repeated point, its first copy).
        """
        current = _as_array("upsample_object", points, np.float64)
        if current.ndim != 2 or current.shape[1] != 3 or len(current) < PATCH_POINTS:
            raise ValueError(f"upsample_object: points must be an (M, 3) array with M >= {PATCH_POINTS}, "
                             f"got shape {current.shape}")
        check_finite_points("upsample_object", current)
        _, first = np.unique(current, axis=0, return_index=True)
        if len(first) < PATCH_POINTS:
            raise ValueError(f"upsample_object: {len(first)} distinct points among the {len(current)} given; "
                             f"needs at least {PATCH_POINTS}")
        distinct = first  # first copies, sorted by their coordinates (np.unique's order)
        current = current[distinct]
        # tiled in the unit sphere: squared distances of coordinates near 1e154 overflowed (an
        # IndexError), and those of 1e-20 underflowed into another tiling. Centred on the median:
        # one stray point 1e12 away moved the mean so far that the others, 1e-12 apart about it,
        # became one float32 value in the tiling, and came out hundreds of units off (a trial)
        centre = np.median(current, axis=0)
        scale = float(np.abs(current - centre).max()) or 1.0
        current = (current - centre) / scale
        source = distinct
        for _ in range(self.passes):
            current, parent = self._object_pass(current)
            source = source[parent]
        return current * scale + centre, source

