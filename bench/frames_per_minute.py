"""End-to-end pipeline benchmark on real KITTI scans: per-stage ms, frames per minute, peak memory.

Usage:
    python bench/frames_per_minute.py [--data ../shared/data/kitti/odometry] [--repeats 3] [--workers 1 2]
                                      [--threads-per-worker 1] [--torch-threads N] [--compare REF [--runs 3]]
    python bench/frames_per_minute.py --external [--workers 2] [--repeats 3]

For each worker count it runs the whole pipeline (a fresh LocalCluster, --overwrite) `repeats`
times on every scan under --data and prints the median per-stage milliseconds per frame (from the
run summaries), the median end-to-end frames per minute (wall time of the run, cluster start-up
excluded), and the peak resident memory of each worker process (ru_maxrss, read in the workers).
`--threads-per-worker` and `--torch-threads` choose the layout (`dask.threads_per_worker`,
`dask.torch_threads`): with 2 threads a worker holds 2 frames at once, so one frame's load, ground
and write overlap the other's network inside the worker.

With --external, for each worker count it runs the tool's own LocalCluster beside an existing
cluster of as many `dask worker` processes on 127.0.0.1 (one thread each, with their nannies, as the
README starts them), both prepared by the tool as `kitti-pu run` prepares them, their runs
alternating, and prints both with the ratio (issue 20: the tool sets what its workers need itself).

With --compare REF, runs this script on git revision REF and on the working tree, interleaved
(`--runs` times each, `bench/revisions.py`), and prints the median of each figure on both sides
with their ratio.
"""

from __future__ import annotations

import argparse
import contextlib
import resource
import socket
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path

from distributed import Client

import revisions

from pipeline.chain import Chain
from pipeline.cluster import WorkerSetup, local_cluster, open_client, plan_cluster
from pipeline.config import PipelineConfig, load_config
from pipeline.preflight import discover_frames
from pipeline.runner import _process
from pipeline.summary import STAGES
from stages import upsample


def _peak_rss_mib() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def bench(data: Path, workers: int, repeats: int, ratio: int, max_patch_radius: float | None = None,
          threads_per_worker: int | None = None, torch_threads: int | None = None) -> dict[str, float]:
    """Run the pipeline `repeats` times on `data` with `workers` workers of `threads_per_worker`
    Dask threads and `torch_threads` torch threads (None: the product's choices); return median
    figures (the frames are written into a temporary folder, removed afterwards)."""
    with tempfile.TemporaryDirectory(prefix="kitti-pu-bench-") as temporary:
        config = load_config([], {
            "input.path": str(data), "output.dir": temporary, "output.overwrite": True,
            "dask.n_workers": workers, "dask.threads_per_worker": threads_per_worker,
            "dask.torch_threads": torch_threads, "upsample.ratio": ratio,
            "upsample.max_patch_radius": max_patch_radius,
        })
        return _bench(config, repeats, ratio)


class _Timings:
    """Per-stage milliseconds and frames per minute of the runs of one cluster."""

    def __init__(self) -> None:
        self.per_stage: dict[str, list[float]] = {}
        self.frames_per_minute: list[float] = []

    def run(self, client: Client, refs: list, chain: Chain, in_flight: int) -> None:
        """One run of every frame of `refs` on `client`'s cluster, timed."""
        started = time.perf_counter()
        reports = [report for _, report in _process(client, refs, chain, in_flight, False)]
        wall = time.perf_counter() - started
        failed = [r.error for r in reports if r.status != "done"]
        if failed:
            raise SystemExit(f"frames failed: {failed}")
        self.frames_per_minute.append(60.0 * len(reports) / wall)
        for report in reports:
            for stage, seconds in report.timings.items():
                self.per_stage.setdefault(stage, []).append(1000.0 * seconds)

    def figures(self, client: Client, frames: int) -> dict[str, float]:
        """The medians, with the peak resident memory of `client`'s workers."""
        figures = {f"{stage}_ms": statistics.median(values) for stage, values in self.per_stage.items()}
        figures["non_network_ms"] = sum(v for k, v in figures.items() if k not in ("upsample_ms",))
        figures["frame_ms"] = figures["non_network_ms"] + figures.get("upsample_ms", 0.0)
        figures["frames_per_minute"] = statistics.median(self.frames_per_minute)
        figures["peak_worker_mib"] = max(client.run(_peak_rss_mib).values())
        figures["frames"] = frames
        return figures


def _chain(config: PipelineConfig, ratio: int) -> Chain:
    metadata = {"ratio": str(ratio), "model_checksum": upsample.model(config.upsample).checksum,
                "config_hash": config.output_hash(), "tool_version": "bench"}
    return Chain(config, metadata)


def _warm(client: Client, config: PipelineConfig) -> None:
    """Load the model in every worker, so that start-up is not timed."""
    client.run(lambda: upsample.model(config.upsample) and None)


def _bench(config: PipelineConfig, repeats: int, ratio: int) -> dict[str, float]:
    refs = discover_frames(config)
    plan = plan_cluster(config)
    chain = _chain(config, ratio)
    timings = _Timings()
    # Revisions before the cluster plan had threads per worker ran one thread each (--compare).
    threads_per_worker = getattr(plan, "threads_per_worker", 1)
    in_flight = 2 * plan.workers * threads_per_worker
    with local_cluster(plan.workers, threads_per_worker) as cluster, Client(cluster) as client:
        client.register_plugin(WorkerSetup(plan.torch_threads))
        _warm(client, config)
        for _ in range(repeats):
            timings.run(client, refs, chain, in_flight)
        return timings.figures(client, len(refs))


def bench_external(data: Path, workers: int, repeats: int, ratio: int) -> dict[str, dict[str, float]]:
    """The tool's own LocalCluster of `workers` workers beside an existing cluster of as many
    `dask worker` processes (one thread each, with their nannies, started as the README starts
    them, on 127.0.0.1), both prepared as `kitti-pu run` prepares them (`open_client`), their runs
    alternating; returns {"local": figures, "external": figures}."""
    with tempfile.TemporaryDirectory(prefix="kitti-pu-bench-") as temporary, \
            _dask_processes(Path(temporary), workers) as address:
        settings = {"input.path": str(data), "output.dir": temporary, "output.overwrite": True,
                    "upsample.ratio": ratio}
        configs = {"local": load_config([], {**settings, "dask.n_workers": workers}),
                   "external": load_config([], {**settings, "dask.scheduler": address})}
        refs = discover_frames(configs["local"])
        chain = _chain(configs["local"], ratio)
        timings = {name: _Timings() for name in configs}
        with open_client(configs["local"], plan_cluster(configs["local"])) as local, \
                open_client(configs["external"], plan_cluster(configs["external"])) as external:
            clients = {"local": local, "external": external}
            for name, client in clients.items():
                _warm(client, configs[name])
            for _ in range(repeats):
                for name, client in clients.items():
                    timings[name].run(client, refs, chain, 2 * workers)
            return {name: timings[name].figures(client, len(refs)) for name, client in clients.items()}


@contextlib.contextmanager
def _dask_processes(folder: Path, workers: int) -> Iterator[str]:
    """`dask scheduler` and `workers` `dask worker --nthreads 1` processes on 127.0.0.1 (their logs
    in `folder`); yields the scheduler's address once every worker has joined."""
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]
    address = f"tcp://127.0.0.1:{port}"
    dask = [sys.executable, "-m", "dask"]
    commands = [[*dask, "scheduler", "--host", "127.0.0.1", "--port", str(port), "--no-dashboard"],
                *[[*dask, "worker", address, "--nthreads", "1", "--no-dashboard", "--host", "127.0.0.1"]
                  for _ in range(workers)]]
    processes = [subprocess.Popen(command, stdout=(folder / f"dask-{index}.log").open("w"), stderr=subprocess.STDOUT,
                                  cwd=folder) for index, command in enumerate(commands)]
    try:
        with Client(address, timeout="60s") as client:
            client.wait_for_workers(workers, timeout=120)
        yield address
    finally:
        for process in reversed(processes):
            process.terminate()
            try:
                process.wait(timeout=20)
            except subprocess.TimeoutExpired:
                process.kill()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path,
                        default=Path(__file__).resolve().parents[2] / "shared/data/kitti/odometry")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--workers", type=int, nargs="+", default=[1, 2])
    parser.add_argument("--ratio", type=int, default=4)
    parser.add_argument("--max-patch-radius", type=float, default=None,
                        help="upsample.max_patch_radius (default: the configured value, 0 = every patch)")
    parser.add_argument("--threads-per-worker", type=int, default=None,
                        help="dask.threads_per_worker (default: the product's)")
    parser.add_argument("--torch-threads", type=int, default=None, help="dask.torch_threads (default: the product's)")
    parser.add_argument("--external", action="store_true",
                        help="the tool's own LocalCluster beside an existing cluster of as many `dask worker` "
                             "processes (loopback, one thread each), runs alternating, for each --workers count")
    revisions.add_arguments(parser)
    args = revisions.parse_or_compare(parser, Path(__file__))
    if args is None:
        return
    if args.external:
        _print_external(args)
        return
    rows = {workers: bench(args.data, workers, args.repeats, args.ratio, args.max_patch_radius,
                           args.threads_per_worker, args.torch_threads)
            for workers in args.workers}
    keys = [f"{stage}_ms" for stage in STAGES] + ["non_network_ms", "frame_ms", "frames_per_minute", "peak_worker_mib"]
    if args.json:
        revisions.emit({f"{workers} worker(s): {key}": figures[key] for workers, figures in rows.items()
                        for key in keys if key in figures})
        return
    print(f"data: {args.data} ({next(iter(rows.values()))['frames']} frames), ratio {args.ratio}, "
          f"threads per worker {args.threads_per_worker or 'default'}, torch threads {args.torch_threads or 'default'}, "
          f"medians of {args.repeats} runs")
    print(f"{'figure':<20}" + "".join(f"{str(w) + ' worker(s)':>16}" for w in rows))
    for key in keys:
        print(f"{key:<20}" + "".join(f"{rows[w].get(key, float('nan')):>16.1f}" for w in rows))


def _print_external(args: argparse.Namespace) -> None:
    keys = [f"{stage}_ms" for stage in STAGES] + ["non_network_ms", "frame_ms", "frames_per_minute", "peak_worker_mib"]
    for workers in args.workers:
        rows = bench_external(args.data, workers, args.repeats, args.ratio)
        if args.json:
            revisions.emit({f"{workers} worker(s), {name}: {key}": figures[key] for name, figures in rows.items()
                            for key in keys if key in figures})
            continue
        print(f"data: {args.data} ({rows['local']['frames']} frames), ratio {args.ratio}, {workers} worker(s) of one "
              f"thread, medians of {args.repeats} runs each, alternating")
        print(f"{'figure':<20}{'local':>16}{'external':>16}{'external/local':>16}")
        for key in keys:
            local, external = rows["local"].get(key, float("nan")), rows["external"].get(key, float("nan"))
            print(f"{key:<20}{local:>16.1f}{external:>16.1f}{external / local if local else float('nan'):>16.2f}")


if __name__ == "__main__":
    main()
