"""Dask's work stealing and the runner's frame placement: how many frames it splits, and the speed.

The runner pins each frame's tasks to one worker loosely (`pipeline.placement`), and loose pins let
Dask's work stealing move a task to another worker. This script runs the runner's frame loop
(`pipeline.runner._process`, nothing written) on the tool's own LocalCluster over the scans of
--data repeated --copies times, with work stealing on and off alternately, and prints for each
run the frames per minute (wall time of the loop after one warm-up frame per worker), how many
frames had tasks on more than one worker, and how many steals the scheduler logged.

    python bench/work_stealing.py --copies 5 --runs 2
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from ground import DEFAULT_DATA  # bench/ground.py, beside this script: the shared sequence 00


def measure(scans: Path, stealing: bool, workers: int) -> dict[str, object]:
    """One run of the frame loop over the scans of `scans`; its figures (see the module docstring)."""
    import dask
    from distributed import get_task_stream

    from pipeline.chain import Chain
    from pipeline.cluster import open_client, plan_cluster
    from pipeline.config import PipelineConfig
    from pipeline.preflight import discover_frames
    from pipeline.runner import _process

    with dask.config.set({"distributed.scheduler.work-stealing": stealing}):
        config = PipelineConfig.model_validate({"input": {"path": str(scans)}, "output": {"dir": str(scans / "out")},
                                                "dask": {"n_workers": workers}})
        refs = discover_frames(config)
        chain = Chain(config, {}, writes=False)
        with open_client(config, plan_cluster(config)) as client:
            list(_process(client, refs[:workers], chain, workers, False))  # models loaded, kernels compiled
            started = time.perf_counter()
            with get_task_stream(client) as stream:
                reports = [report for _, report in _process(client, refs, chain, 2 * workers, False)]
            wall = time.perf_counter() - started
            steals = client.run_on_scheduler(lambda dask_scheduler: sum(1 for _ in dask_scheduler.get_events("stealing")))
    workers_of_frame: dict[str, set[str]] = {}
    for task in stream.data:
        workers_of_frame.setdefault(task["key"].split("-", 1)[1], set()).add(task["worker"])
    return {"stealing": stealing, "frames": len(reports), "done": sum(r.status == "done" for r in reports),
            "frames_per_minute": round(60 * len(reports) / wall, 1),
            "frames_split": sum(len(w) > 1 for w in workers_of_frame.values()), "steals_logged": steals}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, default=DEFAULT_DATA, help="a folder holding velodyne/*.bin, or .bin files")
    parser.add_argument("--copies", type=int, default=5, help="times each scan is repeated")
    parser.add_argument("--runs", type=int, default=2, help="runs of each setting, alternating")
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--one", choices=["on", "off"], help=argparse.SUPPRESS)  # a run in its own process
    parser.add_argument("--scans", type=Path, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.one:
        print(json.dumps(measure(args.scans, args.one == "on", args.workers)))
        return
    sources = sorted((args.data / "velodyne").glob("*.bin")) or sorted(args.data.glob("*.bin"))
    if not sources:
        raise SystemExit(f"work_stealing: no .bin scans in {args.data} or its velodyne/")
    with tempfile.TemporaryDirectory(prefix="kitti-pu-stealing-") as folder:
        scans = Path(folder) / "scans"
        scans.mkdir()
        for number, source in enumerate(source for _ in range(args.copies) for source in sources):
            shutil.copyfile(source, scans / f"{number:06d}.bin")
        for _ in range(args.runs):
            for setting in ("on", "off"):
                done = subprocess.run([sys.executable, __file__, "--one", setting, "--scans", str(scans),
                                       "--workers", str(args.workers)], capture_output=True, text=True, check=False)
                lines = [line for line in done.stdout.splitlines() if line.startswith("{")]
                print(lines[-1] if lines else f"stealing {setting}: failed\n{done.stderr[-2000:]}", flush=True)


if __name__ == "__main__":
    main()
