"""A frame's journey, written once: the stages in order, each with its options from the config.

    load -> ground -> tile -> upsample -> stitch -> snap -> fill -> write

`Chain(config)` holds the steps; `chain.run(ref_or_frame)` runs them in this process (the library
path, `eval-kitti`, the benches), and the Dask runner submits the same `Step` objects one task
each (`pipeline.runner`). A `Step` times its stage, and turns a failure into a `StageError` naming
the stage and the frame; `report` makes the frame's `FrameReport`. Both happen only here.
"""

from __future__ import annotations

import functools
import json
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from importlib.metadata import PackageNotFoundError, version
from typing import Any

from stages import fill, ground, load, snap, stitch, tile, upsample, write
from stages.errors import StageError
from stages.frame import Frame
from stages.upsample import PatchUpsampler

from .config import PipelineConfig
from .summary import STAGES, FrameReport


@dataclass(frozen=True)
class Step:
    """One stage bound to its options: `step(subject)` -> the next Frame, or a StageError.

    A StageError (bad input, a failure the stage foresees) is returned, not raised, and a later
    step hands it on unchanged: the Dask runner then reports it once, in its own words, with no
    worker traceback. Any other exception is a bug: it is raised as a StageError naming stage and
    frame, with the original as its cause. The seconds the stage took go into `Frame.timings`.
    """

    name: str
    function: Callable[[Any], Frame]

    def __call__(self, subject: Any) -> Frame | StageError:
        if isinstance(subject, StageError):  # an earlier stage of this frame failed
            return subject
        started = time.perf_counter()
        try:
            frame = self.function(subject)
        except StageError as error:
            if isinstance(subject, Frame):  # the points load kept: a frame failing at write read them
                error.points_in = len(subject.points)
            return error
        except Exception as error:
            source = getattr(subject, "source", "") or getattr(subject, "key", "")
            raise StageError(self.name, str(source), f"{type(error).__name__}: {error}") from error
        return frame.with_(timings={**frame.timings, self.name: time.perf_counter() - started})


def provenance(config: PipelineConfig, upsampler: PatchUpsampler | None = None,
               given: Mapping[str, str] | None = None) -> dict[str, str]:
    """What a frame's files record of how they were made, so that `kitti-pu run` can tell whether
    they match its own settings (`pipeline.resume`): `given` (the caller's metadata, e.g. the run's)
    over the output-relevant configuration's hash and its settings (`stages.write.CONFIG_KEY`: JSON of
    `PipelineConfig.output_settings`, so that a folder handed on tells how it was made, not only
    a hash), the ratio, the tool's version and, unless
    another model than `config.upsample.weights` runs (`upsampler`), the weight file's resolved
    path and sha256 (left out when the file cannot be read; the upsample stage then names it). What
    `given` holds is not computed again: the run has hashed the weights already."""
    from cadpu.weights import WeightsError, resolve, sha256_of

    given = dict(given or {})
    record = {"config_hash": config.output_hash(), write.CONFIG_KEY: json.dumps(config.output_settings(), sort_keys=True),
              "ratio": str(config.upsample.ratio), "tool_version": tool_version()}
    if upsampler is None:
        try:
            weights = resolve(config.upsample.weights)
            record["model_weights"] = str(weights.resolve())  # where `kitti-pu info` finds the model's provenance
            if "model_checksum" not in given:
                record["model_checksum"] = sha256_of(weights)
        except (WeightsError, OSError):
            pass
    return {**record, **given}


def tool_version() -> str:
    """The installed kitti-pu version ("unknown" when run from a source tree)."""
    try:
        return version("kitti-pu")
    except PackageNotFoundError:
        return "unknown"


class Chain:
    """The steps of a frame's journey with the settings of `config`.

    Args:
        config: the pipeline settings (each stage's options are its section).
        metadata: file metadata the write step stores, over the chain's own `provenance` (the
            config hash, ratio and model checksum a re-run compares before it skips a frame).
        upsampler: a model to use instead of the one `config.upsample` names (e.g. a baseline).
        writes: include the write step (False: the chain ends with the finished cloud in memory).
    """

    def __init__(self, config: PipelineConfig | None = None, metadata: Mapping[str, str] | None = None,
                 upsampler: PatchUpsampler | None = None, writes: bool = True) -> None:
        self.config = config = config or PipelineConfig()
        functions: dict[str, Callable[[Any], Frame]] = {
            "load": functools.partial(load.run, options=config.input),
            "ground": functools.partial(ground.run, options=config.ground),
            "tile": functools.partial(tile.run, options=config.tile),
            "upsample": functools.partial(upsample.run, options=config.upsample, upsampler=upsampler),
            "stitch": functools.partial(stitch.run, options=config.stitch),
            "snap": functools.partial(snap.run, options=config.snap),
            "fill": functools.partial(fill.run, options=config.fill),
        }
        if writes:
            functions["write"] = functools.partial(write.run, options=config.output,
                                                   metadata=provenance(config, upsampler, metadata))
        names = STAGES if writes else STAGES[:-1]
        self.steps: tuple[Step, ...] = tuple(Step(name, functions[name]) for name in names)

    def run(self, subject: load.FrameRef | Frame) -> Frame:
        """Run the steps in this process: from a `FrameRef` (all of them) or from a `Frame` (all
        but load; e.g. `stages.load.frame_from_points(points)`).

        Raises:
            StageError: naming the stage and the file of the first failure.
        """
        steps = self.steps if isinstance(subject, load.FrameRef) else self.steps[1:]
        result: Any = subject
        for step in steps:
            result = step(result)
        if isinstance(result, StageError):
            raise result
        return result


def report(subject: Frame | StageError) -> FrameReport | StageError:
    """The `FrameReport` of a frame that went through the chain (a StageError is handed on)."""
    if isinstance(subject, StageError):
        return subject
    frame, cloud = subject, subject.cloud
    counts: dict[str, int] = {}
    if cloud is not None:
        counts = dict(points_out=len(cloud), ground=int(cloud.ground.sum()), generated=int(cloud.generated.sum()),
                      ground_filled=int((cloud.generated & cloud.ground).sum()), dropped=cloud.dropped)
    return FrameReport(key=frame.key, dataset=frame.dataset, sequence=frame.sequence, index=frame.index,
                       status="done", source=frame.source, points_in=int(frame.points.shape[0]),
                       timings=dict(frame.timings), outputs=dict(frame.outputs), notes=list(frame.notes),
                       **counts)
