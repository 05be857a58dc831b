"""The methods the 16-to-64-beam evaluation compares, each densifying a thinned scan 4x.

- "16-ring input": the input as it is (the floor);
- "range-image linear": new rings interpolated in the range image (`stages.range_image`), the
  standard LiDAR super-resolution baseline; it densifies ground and objects alike;
- "midpoint baseline": the non-learned `cadpu.baseline` on the pipeline's patches;
- "CAD-PU" and "CAD-PU twin": the weights under test and the file they are compared with
  (`comparison_weights`); `load_models` says which files they are.

The last three run the pipeline's own chain in this process (`pipeline.chain.Chain`, without
writing), so they see the 16-ring input exactly as `kitti-pu run` would.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from cadpu.baseline import upsample_patches as midpoint_patches
from stages.frame import Frame
from stages.range_image import interpolate_rings
from stages.rings import hdl64e_rings, keep_rings
from stages.upsample import PatchUpsampler, upsampler_settings

from ..chain import Chain
from ..config import PipelineConfig

INPUT = "16-ring input"
RANGE_IMAGE = "range-image linear"
MIDPOINT = "midpoint baseline"
#: The file the weights under test are compared with (`comparison_weights`).
TWIN = "CAD-PU twin"
#: The weights under test (`--weights`; by default the pipeline's).
NETWORK = "CAD-PU"
#: The methods compared, in table order.
COMPARED_METHODS = (INPUT, RANGE_IMAGE, MIDPOINT, TWIN, NETWORK)
#: Keep one ring in this many (64 -> 16), and upsample by the same ratio.
RATIO = 4


class MidpointUpsampler:
    """The non-learned baseline (`cadpu.baseline.upsample_patches`) behind the interface
    `stages.upsample.run` expects of a model (`PatchUpsampler`).

    Its output holds each patch's input points besides the new ones, so without ring snapping its
    stitched cloud is built without re-adding the input (`keep_input=False`). With ring snapping
    those copies are generated points like a network's and move to virtual rings, so the input is
    re-added, as for the networks (`midpoint_keeps_input`).
    """

    def __init__(self, ratio: int = RATIO) -> None:
        self.ratio = ratio

    def upsample_patches(self, patches: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(B, K, 3) normalised patches -> (B, K*r, 3) float32 points and (B, K*r) int64 parent slots."""
        if len(patches) == 0:
            k = patches.shape[1] * self.ratio if patches.ndim == 3 else 0
            return np.zeros((0, k, 3), np.float32), np.zeros((0, k), np.int64)
        return midpoint_patches(np.asarray(patches, dtype=np.float64), self.ratio)


def thin_scan(points: np.ndarray, source: str = "", ratio: int = RATIO) -> tuple[np.ndarray, np.ndarray]:
    """The scan's rings 0, ratio, 2 * ratio, ... (the 16-beam input of a 64-beam scan).

    Args:
        points: (N, 4) scan in KITTI point order. source: file name for errors.

    Returns:
        (M, 4) kept points in their original order and (M,) int64 their ring ids in the full scan
        (0, ratio, 2 * ratio, ...).

    Raises:
        InputError: the point order shows other than `stages.rings.HDL64E_RINGS` rings
            (`stages.rings.hdl64e_rings`): not a full 64-ring scan in KITTI order. A 16- or 32-ring
            scan was thinned to 4 or 8 rings and scored as the 16-to-64 evaluation; a 64-ring scan
            missing a laser (63 found) was thinned to lasers 0, 4, 8, 13, ... (a trial).
    """
    rings = hdl64e_rings(points, ratio, "eval-kitti", source, "the evaluation")
    return keep_rings(points, rings, ratio=ratio), keep_rings(rings, rings, ratio=ratio)


def densify_with_pipeline(frame: Frame, upsampler: PatchUpsampler, config: PipelineConfig,
                          keep_input: bool | None = None) -> np.ndarray:
    """The pipeline's chain in this process, without writing: ground -> tile -> upsample -> stitch
    -> snap -> fill, with `config`'s settings and `upsampler` as the model.

    Args:
        frame: a frame with `points` (N, 4), sensor frame, and its `rings` (`load.frame_from_points`).
        upsampler: the model (`cadpu.inference.Upsampler`, `MidpointUpsampler`, ...).
        config: the pipeline settings.
        keep_input: override of `config.stitch.keep_input` (None keeps the configured value).

    Returns:
        (Q, 3) float32 output cloud, sensor frame, metres (ground points included as configured).
    """
    if keep_input is not None:
        config = config.model_copy(update={"stitch": config.stitch.model_copy(update={"keep_input": keep_input})})
    return Chain(config, upsampler=upsampler, writes=False).run(frame).cloud.xyz


def midpoint_keeps_input(config: PipelineConfig) -> bool:
    """Whether the midpoint baseline's stitched cloud re-adds the input points: only when its own
    copies of them are moved away by ring snapping (see `MidpointUpsampler`)."""
    return config.snap.enabled and config.stitch.keep_input


def method_outputs(frame: Frame, rings: np.ndarray, models: dict[str, PatchUpsampler], config: PipelineConfig,
                   ratio: int = RATIO) -> dict[str, tuple[np.ndarray, float]]:
    """Every method's densification of one 16-ring frame.

    Args:
        frame: the thinned scan (`thin_scan`) as a frame. rings: (M,) ring id of each of its points.
        models: the learned methods by name (e.g. {TWIN: ..., NETWORK: ...}).
        config: pipeline settings. ratio: the input keeps one ring in `ratio`, and is densified by it.

    Returns:
        {method: ((Q, 3) float32 cloud in the sensor frame, seconds taken)} in `COMPARED_METHODS` order
        (methods missing from `models` are left out).
    """
    results: dict[str, tuple[np.ndarray, float]] = {INPUT: (frame.points[:, :3], 0.0)}
    started = time.perf_counter()
    dense = interpolate_rings(frame.points, rings, ratio=ratio)
    results[RANGE_IMAGE] = (dense[:, :3], time.perf_counter() - started)
    started = time.perf_counter()
    results[MIDPOINT] = (densify_with_pipeline(frame, MidpointUpsampler(ratio), config,
                                               keep_input=midpoint_keeps_input(config)),
                         time.perf_counter() - started)
    for name in COMPARED_METHODS:
        if name in models:
            started = time.perf_counter()
            results[name] = (densify_with_pipeline(frame, models[name], config), time.perf_counter() - started)
    return results


def comparison_weights(weights: Path, twin_weights: str | Path | None, meta: dict | None = None
                       ) -> tuple[Path, str]:
    """The file the weights under test are compared with, and why that one.

    Args:
        weights: the weights under test (resolved). twin_weights: the file asked for, if any.
        meta: the meta of `weights` when already loaded (else read from the file when needed).

    Returns:
        (path, reason): `twin_weights` when given; for a shipped file, its twin trained on the same
        data with the other alpha (`cadpu.weights.twin`); for a file of one's own, the file it was
        trained or fine-tuned from (its meta's `init_weights`), else the pipeline's default weights.
    """
    from cadpu.weights import load_generator, resolve, sha256_of, twin

    if twin_weights is not None:
        return resolve(twin_weights), "--twin-weights"
    shipped_twin = twin(weights)
    if shipped_twin is not None:
        return shipped_twin, "the shipped file of the same data with the other alpha"
    meta = meta if meta is not None else load_generator(weights)[2]
    start, recorded = meta.get("init_weights"), meta.get("init_sha256")
    default = resolve(PipelineConfig().upsample.weights)
    if start and resolve(start).is_file():
        if recorded and sha256_of(resolve(start)) != recorded:  # another file at that path now
            return default, f"the pipeline's default: {start}, the file it was trained from, has changed since"
        return resolve(start), "the file it was trained from"
    return default, "the pipeline's default"


def load_models(weights: str | Path | None, twin_weights: str | Path | None,
                config: PipelineConfig) -> tuple[dict[str, PatchUpsampler], dict[str, str]]:
    """The two CAD-PU models: `weights` (None = `config.upsample.weights`, the pipeline's default)
    and the file it is compared with (`comparison_weights`).

    Returns:
        ({NETWORK: model, TWIN: model}, {NETWORK: description, TWIN: description}), each
        description the file and its checksum's first digits (and, for the twin, why that file).

    Raises:
        cadpu.weights.WeightsError naming a missing or corrupt file, or one that cannot upsample by
        `config.upsample.ratio` (trained at another ratio).
    """
    from cadpu.inference import Upsampler
    from cadpu.weights import WeightsError, resolve

    section = config.upsample
    common = upsampler_settings(section)  # as the pipeline's upsample stage builds its model

    def model(path: Path) -> Upsampler:
        try:
            return Upsampler(path, **common)
        except ValueError as error:  # a ratio the file cannot make (a traceback, exit 1, before)
            raise WeightsError(f"{path}: {error}") from None

    tested = resolve(weights or section.weights)
    network = model(tested)
    other, reason = comparison_weights(tested, twin_weights, network.meta)
    models = {TWIN: model(other), NETWORK: network}
    same = ("; the same weights as CAD-PU, so their rows are the same"
            if models[TWIN].checksum == models[NETWORK].checksum else "")
    # absolute: eval_kitti.json records them, and a relative path names nothing from elsewhere (a trial)
    described = {NETWORK: f"{Path(tested).absolute()} (sha256 {models[NETWORK].checksum[:12]})",
                 TWIN: f"{Path(other).absolute()} (sha256 {models[TWIN].checksum[:12]}; {reason}{same})"}
    return models, described
