"""Stage 4, upsample: run a frame's normalised patches through CAD-PU (`cadpu.inference.Upsampler`).

The model named by the stage's `Options` is built once per process (`model`) and kept: a Dask
worker loads it on its first frame, never per task.
"""

from __future__ import annotations

import re
import threading
import warnings
from pathlib import Path
from typing import Protocol

import numpy as np
from pydantic import Field, field_validator

from .errors import StageError
from .frame import Frame, stage_inputs
from .options import StageOptions
from .tile import left_untiled
from .wording import counted

#: The largest `Options.seed`: torch's generators take a signed 64-bit seed (the same bound as
#: `cadpu.inference.MAX_SEED`, which this stage does not import: it would load torch).
MAX_SEED = 2**63 - 1
#: The largest `Options.oversample` (`cadpu.inference.MAX_OVERSAMPLE`, not imported for the same reason).
MAX_OVERSAMPLE = 8
#: The largest `Options.offset_scale` (`cadpu.inference.MAX_OFFSET_SCALE`, not imported for the same reason).
MAX_OFFSET_SCALE = 4.0


class PatchUpsampler(Protocol):
    """What this stage needs of a model: `cadpu.inference.Upsampler` provides it."""

    ratio: int

    def upsample_patches(self, patches: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(B, K, 3) float32 normalised patches -> (B, K*r, 3) points, (B, K*r) int64 parent slots."""
        ...


class Options(StageOptions):
    """The network and the widest patch it is given.

    ratio: output points per input point (4, or a power of 4).
    weights: a file, or the name of a shipped one (`cadpu.weights.resolve`); which file is the
        default and why: README, "The model".
    batch_size: patches per forward pass (None: the model's choice).
    device: "auto" (CUDA when present), "cpu" or "cuda[:N]".
    seed: seed of the curvature-adaptive expansion's random draw.
    max_patch_radius: patches whose radius (`tiling.scale`: metres, in the tiled coordinates,
        whose z may be scaled, see `stages.tile`) exceeds this pass through without upsampling;
        0 upsamples every patch.
    engine: what runs the network's learned part (`cadpu.engines`; "auto" is torch eager, the
        fastest measured on a CPU: docs/inference.md).
    oversample: candidates the network makes per point kept (`cadpu.inference.Upsampler`); 1, no
        selection, is what the pipeline's settings were chosen with on the simulated streets.
    offset_scale: factor on each generated point's distance from its parent
        (`cadpu.inference.Upsampler`); 1, the network's own placement, is what the pipeline's
        settings were chosen with (`tile.vertical_scale` already widens the copies across the ring
        gaps).
    """

    ratio: int = Field(4, ge=2, le=64)
    weights: Path = Path("cadpu_r4_lidar_alpha1")
    batch_size: int | None = Field(None, ge=1)
    device: str = "auto"
    seed: int = Field(0, ge=0, le=MAX_SEED)
    max_patch_radius: float = Field(0.0, ge=0)
    engine: str = "auto"
    oversample: int = Field(1, ge=1, le=MAX_OVERSAMPLE)
    offset_scale: float = Field(1.0, gt=0, le=MAX_OFFSET_SCALE)

    @field_validator("weights", mode="before")
    @classmethod
    def _check_weights(cls, value: object) -> object:
        # null read as "no file" gave Upsampler()'s object-trained default, not the pipeline's
        if value is None or value == "":
            raise ValueError(f"upsample.weights must name a weights file or a shipped name; leave the key out "
                             f"for the pipeline's default ({cls.model_fields['weights'].default})")
        return value

    @field_validator("engine")
    @classmethod
    def _check_engine(cls, value: str) -> str:
        from cadpu.inference import ENGINE_CHOICES

        if value not in ENGINE_CHOICES:
            raise ValueError(f"upsample.engine must be one of {', '.join(ENGINE_CHOICES)}, got {value!r}")
        return value

    @field_validator("device")
    @classmethod
    def _check_device(cls, value: str) -> str:
        if value not in ("auto", "cpu") and not value.startswith("cuda"):
            raise ValueError(f"upsample.device must be 'auto', 'cpu' or 'cuda[:N]', got {value!r}")
        return value

    def model_key(self) -> tuple:
        """What identifies the loaded model: its settings, and the weights file's size and
        modification time (a file replaced in place is loaded again)."""
        from cadpu.weights import resolve

        path = resolve(self.weights)
        stat = path.stat() if path.is_file() else None
        version = (stat.st_size, stat.st_mtime_ns) if stat else None
        return (str(self.weights) if self.weights else None, version, *upsampler_settings(self).values())


def upsampler_settings(options: Options = Options()) -> dict[str, object]:
    """The keyword arguments of `cadpu.inference.Upsampler` that `options` sets, all but the weights:
    every place that builds a model of the stage's settings takes them from here, and so does the
    cache key of the loaded models (`Options.model_key`): a setting one of them left out fell back
    to the file's own default there."""
    return dict(ratio=options.ratio, device=options.device, batch_size=options.batch_size, seed=options.seed,
                engine=options.engine, oversample=options.oversample, offset_scale=options.offset_scale)


_MODELS: dict[tuple, PatchUpsampler] = {}
_MODELS_LOCK = threading.Lock()


def model(options: Options = Options()) -> PatchUpsampler:
    """This process's `cadpu.inference.Upsampler` for `options`, built on first use and kept.

    An engine whose packages are missing falls back to torch eager without a warning here (every
    worker would print it): the model's `engine` names what runs, and `pipeline.preflight` says it
    once.

    Raises:
        cadpu.weights.WeightsError: the weights file is missing or corrupt (naming it).
        ValueError: a ratio the weights cannot make.
    """
    key = options.model_key()
    with _MODELS_LOCK:
        if key not in _MODELS:
            from cadpu.inference import Upsampler

            with warnings.catch_warnings():
                warnings.filterwarnings("ignore", message="inference engine .* using torch eager instead")
                _MODELS[key] = Upsampler(weights=options.weights, **upsampler_settings(options))
        return _MODELS[key]


def run(frame: Frame, options: Options = Options(), upsampler: PatchUpsampler | None = None) -> Frame:
    """The upsample stage: upsample the frame's patches no wider than `options.max_patch_radius`.

    Args:
        frame: a frame through `stages.tile`.
        options: the model and the patch limit.
        upsampler: a model to use instead of `model(options)` (e.g. a non-learned baseline).

    Reads: tiling. Adds: upsampled (S, K*r, 3) float32, parent_slots (S, K*r) int64,
    upsampled_patches (S,) int64 (which patches of the tiling those rows are), ratio, and a note
    when patches were left out; only `ratio` when the tile stage left the frame without patches.

    Raises:
        StageError("upsample", ...) when the tile stage has not run on the frame, or the weights
        cannot upsample by `options.ratio` (trained at a ratio it is not a power of).
        cadpu.weights.WeightsError: the weights file is missing or corrupt (naming it).
    """
    frame, options = stage_inputs(frame, options, Options, "upsample")
    if frame.tiling is None:
        if not left_untiled(frame):
            raise StageError("upsample", frame.source or frame.key, "the frame has no patches (run stages.tile first)")
        return frame.with_stage_result(ratio=upsampler.ratio if upsampler is not None else options.ratio)
    if upsampler is None:
        try:
            upsampler = model(options)
        except ValueError as error:  # a ratio the weights cannot make: a bare ValueError, taken for a bug
            named = re.search(rf"\bratio {options.ratio}\b", str(error))  # not "ratio 1" in "ratio 16"
            said = str(error) if named else f"ratio {options.ratio}: {error}"
            raise StageError("upsample", frame.source or frame.key, said) from None
    tiling = frame.tiling
    chosen = np.arange(len(tiling.scale))
    if options.max_patch_radius:
        chosen = np.flatnonzero(tiling.scale <= options.max_patch_radius)
        if len(chosen) < len(tiling.scale):
            total = counted(len(tiling.scale), "patch", "patches")
            frame = frame.with_note(f"upsample: {len(tiling.scale) - len(chosen)} of {total} "
                                    f"wider than {options.max_patch_radius:g} m not upsampled")
    if len(chosen):
        points, slots = upsampler.upsample_patches(tiling.normalized[chosen])
    else:
        width = tiling.normalized.shape[1] * upsampler.ratio
        points, slots = np.zeros((0, width, 3), np.float32), np.zeros((0, width), np.int64)
    return frame.with_stage_result(upsampled=points, parent_slots=slots, upsampled_patches=chosen,
                                   ratio=upsampler.ratio)
