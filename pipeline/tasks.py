"""The functions Dask runs: one per stage, each wrapping the stage and naming it in any error.

They live at module level so workers import them instead of receiving pickled closures, and the
CAD-PU model is built once per worker process (`get_upsampler`) rather than shipped with tasks.
"""

from __future__ import annotations

import functools
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any, TypeVar

from stages import ground, load, stitch, tile, upsample, write
from stages.errors import StageError
from stages.frame import Frame

from .summary import FrameReport

T = TypeVar("T")


@dataclass(frozen=True)
class ModelSpec:
    """What identifies a loaded model in a worker: weights file (None = shipped), ratio, device."""

    weights: str | None
    ratio: int
    device: str
    batch_size: int | None
    seed: int


_MODELS: dict[ModelSpec, Any] = {}
_MODELS_LOCK = threading.Lock()


def get_upsampler(spec: ModelSpec) -> Any:
    """The worker's `cadpu.inference.Upsampler` for `spec`, built on first use and kept."""
    with _MODELS_LOCK:
        if spec not in _MODELS:
            from cadpu.inference import Upsampler

            _MODELS[spec] = Upsampler(
                weights=spec.weights,
                ratio=spec.ratio,
                device=spec.device,
                batch_size=spec.batch_size,
                seed=spec.seed,
            )
        return _MODELS[spec]


def _named(stage: str) -> Callable[[Callable[..., T]], Callable[..., T | StageError]]:
    """Wrap a stage task so that every failure names the stage and the frame.

    A StageError (bad input, the failures a stage foresees) is returned as the task's value and
    handed on unchanged by the frame's later tasks, so the runner reports it once, in its own words:
    raised, Dask's worker would also log it with a traceback, in every scheduled run's log. Any
    other exception is a bug: it is raised as a StageError naming stage and frame, and the worker
    logs its traceback.
    """

    def decorate(function: Callable[..., T]) -> Callable[..., T | StageError]:
        @functools.wraps(function)
        def wrapper(subject: Any, *args: Any, **kwargs: Any) -> T | StageError:
            if isinstance(subject, StageError):  # an earlier stage of this frame failed
                return subject
            try:
                return function(subject, *args, **kwargs)
            except StageError as error:
                return error
            except Exception as error:
                source = getattr(subject, "source", "") or getattr(subject, "key", "")
                raise StageError(stage, str(source), f"{type(error).__name__}: {error}") from error

        return wrapper

    return decorate


@_named("load")
def load_task(ref: load.FrameRef, max_points: int) -> Frame:
    """Read one scan (see `stages.load.load_frame`)."""
    started = time.perf_counter()
    frame = load.load_frame(ref, max_points=max_points)
    return frame.with_(timings={**frame.timings, "load": time.perf_counter() - started})


@_named("ground")
def ground_task(frame: Frame, method: str, params: Any) -> Frame:
    """Label ground points (see `stages.ground.run`)."""
    return ground.run(frame, method=method, params=params)


@_named("tile")
def tile_task(frame: Frame, patch_size: int, overlap: float, seed: int, method: str,
              vertical_scale: float) -> Frame:
    """Cut the non-ground points into normalised patches (see `stages.tile.run`)."""
    return tile.run(frame, patch_size=patch_size, overlap=overlap, seed=seed, method=method,
                    vertical_scale=vertical_scale)


@_named("upsample")
def upsample_task(frame: Frame, spec: ModelSpec, max_patch_radius: float | None) -> Frame:
    """Run the frame's patches through the worker's model (see `stages.upsample.run`)."""
    return upsample.run(frame, get_upsampler(spec), max_patch_radius)


@_named("stitch")
def stitch_task(frame: Frame, options: dict[str, Any]) -> tuple[Frame, stitch.StitchedCloud]:
    """Map patches back to the sensor frame and assemble the output cloud: `stages.stitch.run`
    with `options` (`pipeline.config.stitch_options`)."""
    started = time.perf_counter()
    frame, cloud = stitch.run(frame, **options)
    return frame.with_(timings={**frame.timings, "stitch": time.perf_counter() - started}), cloud


@_named("write")
def write_task(
    stitched: tuple[Frame, stitch.StitchedCloud],
    out_dir: str,
    formats: tuple[str, ...],
    metadata: dict[str, str],
) -> FrameReport:
    """Write the frame's files (atomically) and return its report."""
    frame, cloud = stitched
    started = time.perf_counter()
    paths = write.write_frame(cloud, frame, Path(out_dir), metadata=metadata, formats=formats)
    timings = {**frame.timings, "write": time.perf_counter() - started}
    return FrameReport(
        key=frame.key,
        dataset=frame.dataset,
        sequence=frame.sequence,
        index=frame.index,
        status="done",
        source=frame.source,
        points_in=int(frame.points.shape[0]),
        points_out=int(cloud.xyz.shape[0]),
        ground=int(cloud.ground.sum()),
        generated=int(cloud.generated.sum()),
        ground_filled=int((cloud.generated & cloud.ground).sum()),
        dropped=cloud.dropped,
        timings=timings,
        outputs={name: str(path) for name, path in paths.items()},
        notes=list(frame.notes),
    )
