"""A run: discover frames, skip finished ones, push the rest through Dask, summarise.

Each frame is a chain of tasks on a `distributed` client, one per `pipeline.chain.Step`
(load -> ground -> tile -> upsample -> stitch -> snap -> fill -> write), then its report. At most
`max_in_flight` frames are submitted at once, so memory stays flat
however long the sequence is. A failing frame fails alone: its error is recorded, the other
frames go on, and the write stage's atomic renames leave nothing half-written.
"""

from __future__ import annotations

import contextlib
import os
import time
import uuid
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from importlib.metadata import PackageNotFoundError, version
from pathlib import Path

import dask
import pyarrow.parquet as pq
from distributed import Client, LocalCluster, as_completed
from distributed.diagnostics.plugin import WorkerPlugin
from tqdm import tqdm

from stages import load, upsample, write
from stages.errors import StageError

from .chain import Chain, report
from .config import ConfigError, PipelineConfig
from .summary import FrameReport, RunSummary


def tool_version() -> str:
    """The installed kitti-pu version ("unknown" when run from a source tree)."""
    try:
        return version("kitti-pu")
    except PackageNotFoundError:
        return "unknown"


class WorkerSetup(WorkerPlugin):
    """Prepares every worker before its first frame.

    - Sets torch's intra-op thread count: Dask's nanny sets OMP_NUM_THREADS=1 in worker
      processes, so without this torch would run the network on one core however many the worker
      was meant to use.
    - Imports Open3D and pykitti, which the write and load stages otherwise import on first
      use: about 0.9 s and 0.4 s that would land in the first frame's timings on every worker.
    """

    name = "kitti-pu-worker-setup"

    def __init__(self, threads: int) -> None:
        self.threads = threads

    def setup(self, worker: object) -> None:
        import pykitti  # noqa: F401
        import torch

        from cadpu.o3d import o3d  # noqa: F401

        torch.set_num_threads(self.threads)


@dataclass(frozen=True)
class ClusterPlan:
    """How many LocalCluster workers and torch threads a run uses."""

    workers: int
    torch_threads: int


def plan_cluster(config: PipelineConfig) -> ClusterPlan:
    """Size the LocalCluster to the machine: one worker per core (at most 4) by default."""
    cores = os.cpu_count() or 1
    workers = config.dask.n_workers or max(1, min(cores, 4))
    threads = config.dask.torch_threads or max(1, cores // workers)
    return ClusterPlan(workers=workers, torch_threads=threads)


@contextlib.contextmanager
def open_client(config: PipelineConfig, plan: ClusterPlan) -> Iterator[Client]:
    """A client on `config.dask.scheduler`, or on a new LocalCluster closed on exit."""
    if config.dask.scheduler:
        try:
            client = Client(config.dask.scheduler, timeout="20s")
        except OSError as error:
            raise ConfigError(f"dask.scheduler: cannot reach {config.dask.scheduler} ({error})") from None
        try:
            client.register_plugin(WorkerSetup(plan.torch_threads))
            yield client
        finally:
            client.close()
        return
    with local_cluster(plan.workers, config.dask.threads_per_worker, config.dask.memory_limit,
                       config.dask.dashboard) as cluster, Client(cluster) as client:
        client.register_plugin(WorkerSetup(plan.torch_threads))
        yield client


#: Dask's nanny starts every worker with MALLOC_TRIM_THRESHOLD_=65536 so that freed memory goes
#: back to the OS. Setting that variable at all switches off glibc's dynamic mmap threshold: every
#: array over 128 KiB is then mmapped and page-faulted afresh, and the numpy stages ran about 2x
#: slower than in a plain process (ground: 189 vs 83 ms per frame, side by side, one thread).
#: Worker memory here is bounded by the frames in flight, so glibc's defaults are kept.
KEEP_GLIBC_MALLOC_DEFAULTS = {"distributed.nanny.pre-spawn-environ.MALLOC_TRIM_THRESHOLD_": None}


@contextlib.contextmanager
def local_cluster(workers: int, threads_per_worker: int = 1, memory_limit: str | float = "auto",
                  dashboard: bool = False) -> Iterator[LocalCluster]:
    """A LocalCluster of `workers` processes with glibc's malloc defaults (see
    KEEP_GLIBC_MALLOC_DEFAULTS), closed on exit."""
    with dask.config.set(KEEP_GLIBC_MALLOC_DEFAULTS):
        cluster = LocalCluster(
            n_workers=workers,
            threads_per_worker=threads_per_worker,
            processes=True,
            memory_limit=memory_limit,
            dashboard_address=":0" if dashboard else None,
        )
    with cluster:
        yield cluster


def _is_finished(paths: dict[str, Path], config_hash: str) -> bool:
    """True when every output exists, is complete, and came from the same configuration."""
    if not write.is_complete(paths):
        return False
    parquet = paths.get("parquet")
    if parquet is None:
        return True
    recorded = (pq.read_metadata(parquet).metadata or {}).get(b"config_hash")
    return recorded is None or recorded.decode() == config_hash


def _failed_report(ref: load.FrameRef, error: BaseException) -> FrameReport:
    stage = error.stage if isinstance(error, StageError) else None
    return FrameReport(
        key=ref.key,
        dataset=ref.dataset,
        sequence=ref.sequence,
        index=ref.index,
        status="failed",
        source=str(ref.source),
        error=str(error) if isinstance(error, StageError) else f"{type(error).__name__}: {error}",
        failed_stage=stage,
    )


def check_weights(config: PipelineConfig) -> str:
    """Load the model once in this process to fail fast on a missing or corrupt weights file.

    Returns the weight file's sha256; raises ConfigError naming the file otherwise.
    """
    from cadpu.weights import WeightsError

    try:
        return upsample.model(config.upsample).checksum  # type: ignore[attr-defined]
    except WeightsError as error:
        raise ConfigError(f"upsample.weights: {error}") from None
    except ValueError as error:  # a ratio the weights cannot make
        raise ConfigError(f"upsample.ratio: {error}") from None


def discover_frames(config: PipelineConfig) -> list[load.FrameRef]:
    """The frames the configuration selects; ConfigError when the input is missing or empty."""
    section = config.input
    if section.path is None:
        raise ConfigError("input.path: no input given (a KITTI raw/odometry folder or a folder of .bin)")
    if not Path(section.path).exists():
        raise ConfigError(f"input.path: {section.path} does not exist")
    try:
        refs = load.discover(
            section.path, kind=section.kind, sequences=section.sequences, frames=section.frame_range()
        )
    except StageError as error:
        raise ConfigError(f"input.path: {error}") from None
    if not refs:
        raise ConfigError(f"input.path: no frames found under {section.path} (kind {section.kind})")
    return refs


def _check_writable(out_dir: Path) -> None:
    try:
        out_dir.mkdir(parents=True, exist_ok=True)
        probe = out_dir / f".write-test-{uuid.uuid4().hex}"
        probe.touch()
        probe.unlink()
    except OSError as error:
        raise ConfigError(f"output.dir: {out_dir} is not writable ({error.strerror or error})") from None


def run_pipeline(config: PipelineConfig, progress: bool = True,
                 on_report: Callable[[FrameReport], None] | None = None) -> RunSummary:
    """Process every selected frame that is not already finished and return the run's summary.

    Args:
        config: a validated configuration (see `pipeline.config.load_config`).
        progress: show a progress bar on stderr.
        on_report: called with each frame's report as the frame finishes (processed or failed;
            skipped frames are reported before any work starts).

    Returns:
        The `RunSummary`, also written to `<output.dir>/summary.json` and
        `<output.dir>/runs/<UTC time>.json`.

    Raises:
        ConfigError: bad input location, unwritable output folder, missing or corrupt weights,
            unreachable scheduler. Nothing is processed then.
    """
    started = time.perf_counter()
    out_dir = Path(config.output.dir)
    refs = discover_frames(config)
    checksum = check_weights(config)
    _check_writable(out_dir)
    config_hash = config.output_hash()
    formats = tuple(config.output.formats)
    metadata = {
        "ratio": str(config.upsample.ratio),
        "model_checksum": checksum,
        "config_hash": config_hash,
        "tool_version": tool_version(),
    }

    reports: dict[str, FrameReport] = {}
    todo: list[load.FrameRef] = []
    for ref in refs:
        paths = write.output_paths(out_dir, ref.dataset, ref.sequence, ref.index, formats, ref.source)
        if not config.output.overwrite and _is_finished(paths, config_hash):
            reports[ref.key] = FrameReport(
                key=ref.key, dataset=ref.dataset, sequence=ref.sequence, index=ref.index,
                status="skipped", source=str(ref.source),
                outputs={name: str(path) for name, path in paths.items()},
            )
            if on_report is not None:
                on_report(reports[ref.key])
        else:
            todo.append(ref)

    plan = plan_cluster(config)
    scheduler = config.dask.scheduler or f"LocalCluster({plan.workers} workers)"
    workers = plan.workers
    if todo:
        with open_client(config, plan) as client:
            workers = len(client.scheduler_info().get("workers", {})) or plan.workers
            limit = config.dask.max_in_flight or 2 * workers
            chain = Chain(config, metadata)
            for ref, frame_report in _process(client, todo, chain, limit, progress):
                reports[ref.key] = frame_report
                if on_report is not None:
                    on_report(frame_report)

    summary = RunSummary(
        frames=[reports[ref.key] for ref in refs],
        wall_seconds=time.perf_counter() - started,
        config_hash=config_hash,
        model_checksum=checksum,
        ratio=config.upsample.ratio,
        workers=workers,
        scheduler=scheduler,
        output_dir=str(out_dir),
    )
    summary.write_json(out_dir / "summary.json")
    stamp = time.strftime("%Y%m%dT%H%M%SZ", time.gmtime())
    summary.write_json(out_dir / "runs" / f"{stamp}-{uuid.uuid4().hex[:6]}.json")
    return summary


def _submit_chain(client: Client, chain: Chain, ref: load.FrameRef, token: str):
    """Submit one task per step of the chain for one frame, then its report; returns the future
    of the report (a FrameReport, or the StageError of the step that failed)."""
    name = f"{ref.dataset}-{ref.sequence}-{ref.index:06d}-{token}"
    subject = ref
    for step in chain.steps:
        subject = client.submit(step, subject, key=f"{step.name}-{name}")
    return client.submit(report, subject, key=f"report-{name}")


def _process(client: Client, refs: list[load.FrameRef], chain: Chain, limit: int,
             progress: bool) -> Iterator[tuple[load.FrameRef, FrameReport]]:
    """Keep at most `limit` frames in flight; yield each frame's report as it finishes."""
    token = uuid.uuid4().hex[:8]
    pending = iter(refs)
    by_future = {}
    finished = as_completed()
    for ref in pending:
        future = _submit_chain(client, chain, ref, token)
        by_future[future] = ref
        finished.add(future)
        if len(by_future) >= limit:
            break
    bar = tqdm(total=len(refs), unit="frame", disable=not progress, desc="kitti-pu")
    for future in finished:
        ref = by_future.pop(future)
        if future.status == "finished":  # a FrameReport, or the StageError of the stage that failed
            result = future.result()
            frame_report = result if isinstance(result, FrameReport) else _failed_report(ref, result)
        elif future.cancelled():  # e.g. the scheduler lost the task's workers
            frame_report = _failed_report(ref, RuntimeError("task cancelled by the Dask scheduler"))
        else:
            frame_report = _failed_report(ref, future.exception())
        future.release()
        bar.update(1)
        if frame_report.status == "failed":
            bar.write(f"failed: {frame_report.error}")
        yield ref, frame_report
        next_ref = next(pending, None)
        if next_ref is not None:
            next_future = _submit_chain(client, chain, next_ref, token)
            by_future[next_future] = next_ref
            finished.add(next_future)
    bar.close()
