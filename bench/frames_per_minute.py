"""End-to-end pipeline benchmark on real KITTI scans: per-stage ms, frames per minute, peak memory.

Usage:
    python bench/frames_per_minute.py [--data ../shared/data/kitti/odometry] [--repeats 3] [--workers 1 2]
                                      [--threads-per-worker 1] [--torch-threads N] [--compare REF [--runs 3]]

For each worker count it runs the whole pipeline (a fresh LocalCluster, --overwrite) `repeats`
times on every scan under --data and prints the median per-stage milliseconds per frame (from the
run summaries), the median end-to-end frames per minute (wall time of the run, cluster start-up
excluded), and the peak resident memory of each worker process (ru_maxrss, read in the workers).
`--threads-per-worker` and `--torch-threads` choose the layout (`dask.threads_per_worker`,
`dask.torch_threads`): with 2 threads a worker holds 2 frames at once, so one frame's load, ground
and write overlap the other's network inside the worker.

With --compare REF, runs this script on git revision REF and on the working tree, interleaved
(`--runs` times each, `bench/revisions.py`), and prints the median of each figure on both sides
with their ratio.
"""

from __future__ import annotations

import argparse
import resource
import statistics
import tempfile
import time
from pathlib import Path

from distributed import Client

import revisions

from pipeline.chain import Chain
from pipeline.cluster import WorkerSetup, local_cluster, plan_cluster
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


def _bench(config: PipelineConfig, repeats: int, ratio: int) -> dict[str, float]:
    refs = discover_frames(config)
    plan = plan_cluster(config)
    metadata = {"ratio": str(ratio), "model_checksum": upsample.model(config.upsample).checksum,
                "config_hash": config.output_hash(), "tool_version": "bench"}
    chain = Chain(config, metadata)
    per_stage: dict[str, list[float]] = {}
    frames_per_minute = []
    # Revisions before the cluster plan had threads per worker ran one thread each (--compare).
    threads_per_worker = getattr(plan, "threads_per_worker", 1)
    in_flight = 2 * plan.workers * threads_per_worker
    with local_cluster(plan.workers, threads_per_worker) as cluster, Client(cluster) as client:
        client.register_plugin(WorkerSetup(plan.torch_threads))
        # warm-up: load the model in every worker so start-up is not timed
        client.run(lambda: upsample.model(config.upsample) and None)
        for _ in range(repeats):
            started = time.perf_counter()
            reports = [report for _, report in _process(client, refs, chain, in_flight, False)]
            wall = time.perf_counter() - started
            failed = [r.error for r in reports if r.status != "done"]
            if failed:
                raise SystemExit(f"frames failed: {failed}")
            frames_per_minute.append(60.0 * len(reports) / wall)
            for report in reports:
                for stage, seconds in report.timings.items():
                    per_stage.setdefault(stage, []).append(1000.0 * seconds)
        peak = client.run(_peak_rss_mib)
    figures = {f"{stage}_ms": statistics.median(values) for stage, values in per_stage.items()}
    figures["non_network_ms"] = sum(v for k, v in figures.items() if k not in ("upsample_ms",))
    figures["frame_ms"] = figures["non_network_ms"] + figures.get("upsample_ms", 0.0)
    figures["frames_per_minute"] = statistics.median(frames_per_minute)
    figures["peak_worker_mib"] = max(peak.values())
    figures["frames"] = len(refs)
    return figures


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
    revisions.add_arguments(parser)
    args = revisions.parse_or_compare(parser, Path(__file__))
    if args is None:
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


if __name__ == "__main__":
    main()
