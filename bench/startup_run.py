"""Where `kitti-pu run` spends its time before the first frame task runs, and after the last.

Usage:
    python bench/startup_run.py [--data ../shared/data/kitti/odometry/sequences/00] [--frames 4]
                                [--workers N] [--repeats 3] [--timeline] [--compare REF [--runs 3]]

(Not bench/startup.py, which measures the Open3D `.pth` hook's cost at interpreter start.)

Each repeat is a fresh Python process that imports `pipeline.cli` and calls the `run` verb on the
first --frames scans under --data (a LocalCluster with the product's defaults, a new output
folder), as `kitti-pu run DATA --first 0 --last N-1 --out TMP --no-progress` does (the program `pipeline.cli.app`), with
timers wrapped around the functions a run goes through (names that a revision lacks are left out).
Times are wall-clock seconds from the process's start (`process_start`):

- `cli imported`: `import pipeline.cli` done;
- `preflight` and its parts (paths, environment, discovery, weights: the model loaded here);
- `cluster started`, `client connected`, `workers set up` (`WorkerSetup` on every worker);
- `first task running`: the first task executing on any worker (the workers' state logs);
- `first frame done`; `model load in worker`: the first upsample task on each worker minus the
  median of its later ones (median over workers; needs --frames of at least twice the workers);
- `first frame's extra in worker`: the same for every stage, summed (lazy imports, Numba's cache
  loads, the model);
- `last task done`; `exit`: the program's exit handlers run (cluster closed, summary printed);
  `process ended` (as the parent sees it).

Prints the median over --repeats of each mark (and with --timeline, every repeat's marks).
"""

from __future__ import annotations

import argparse
import atexit
import contextlib
import functools
import json
import statistics
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
import revisions  # noqa: E402

CHILD_MARK = "STARTUP-MARKS "


def process_start(pid: int | None = None) -> float:
    """Wall-clock time a process started (this one by default), from its start in clock ticks
    since boot and the uptime (psutil's create_time rounds the boot time to the second)."""
    import os

    stat = Path(f"/proc/{pid or os.getpid()}/stat").read_text()
    ticks = int(stat.rsplit(")", 1)[1].split()[19])
    uptime = float(Path("/proc/uptime").read_text().split()[0])
    return time.time() - (uptime - ticks / os.sysconf("SC_CLK_TCK"))


def _timed(events: list[tuple[str, float, float]], name: str, function):
    @functools.wraps(function)
    def wrapper(*args, **kwargs):
        started = time.time()
        try:
            return function(*args, **kwargs)
        finally:
            events.append((name, started, time.time()))
    return wrapper


def _wrap(events, module, attribute: str, name: str) -> None:
    """Time every call of `module.attribute` as event `name` (nothing when the module lacks it)."""
    if hasattr(module, attribute):
        setattr(module, attribute, _timed(events, name, getattr(module, attribute)))


def _worker_log(dask_worker) -> dict:
    """A worker's process creation time and, per task key, when it began and ended executing."""
    began, ended = {}, {}
    for entry in dask_worker.state.log:
        if len(entry) == 7 and entry[2] == "executing":  # (key, start, finish, ..., time)
            began.setdefault(entry[0], entry[-1])
        elif len(entry) == 7 and entry[1] == "executing":
            ended[entry[0]] = entry[-1]
    return {"created": process_start(),
            "tasks": {str(key): (began[key], ended[key]) for key in began if key in ended}}


def child(data: Path, frames: int, workers: int | None) -> None:
    """One measured `kitti-pu run` in this process; prints its marks as one line."""
    t0 = process_start()
    events: list[tuple[str, float, float]] = []
    started = time.time()
    import pipeline.cli as cli
    events.append(("cli imported", started, time.time()))
    from pipeline import preflight, runner

    for attribute, name in (("resolve_paths", "preflight: paths"), ("check_environment", "preflight: environment"),
                            ("discover_frames", "preflight: discovery"), ("check_weights", "preflight: weights"),
                            ("check_output_layout", "preflight: output layout")):
        _wrap(events, preflight, attribute, name)
    _wrap(events, runner, "preflight", "preflight")
    import distributed
    _wrap(events, distributed.Client, "register_plugin", "workers set up")
    _wrap(events, distributed.Client, "__init__", "client connected")
    _wrap(events, distributed.LocalCluster, "__init__", "cluster started")
    workers: dict[str, dict] = {}
    original_open = runner.open_client

    @contextlib.contextmanager
    def open_client(*args, **kwargs):
        with original_open(*args, **kwargs) as client:
            try:
                yield client
            finally:
                workers.update(client.run(_worker_log))
    runner.open_client = open_client
    out = tempfile.mkdtemp(prefix="kitti-pu-startup-")

    def report() -> None:  # at exit, as the program ends (its own way: `pipeline.cli_common.App`)
        finished = time.time()
        shutil.rmtree(out, ignore_errors=True)
        print(CHILD_MARK + json.dumps(marks_of(events, workers, t0, finished)), flush=True)

    atexit.register(report)
    cli.app(["run", str(data), "--first", "0", "--last", str(frames - 1), "--out", out, "--no-progress",
             *(["--workers", str(workers)] if workers else [])])


def marks_of(events: list[tuple[str, float, float]], workers: dict[str, dict], t0: float,
             finished: float) -> dict[str, float]:
    """The marks (seconds from t0) of a run's timed calls and of its workers' task logs."""
    marks: dict[str, float] = {}
    for name, begin, end in events:
        marks.setdefault(name, end - t0)
    tasks = [span for info in workers.values() for span in info["tasks"].values()]
    if tasks:
        marks["first task running"] = min(begin for begin, _ in tasks) - t0
        marks["first frame done"] = min(end for key, (_, end) in
                                        ((k, s) for info in workers.values() for k, s in info["tasks"].items())
                                        if key.startswith("report-")) - t0
        marks["last task done"] = max(end for _, end in tasks) - t0
        marks["workers created"] = max(info["created"] for info in workers.values()) - t0
        loads, extras = [], []
        for info in workers.values():
            by_stage: dict[str, list[tuple[float, float]]] = {}
            for key, (begin, end) in info["tasks"].items():
                by_stage.setdefault(key.split("-", 1)[0], []).append((begin, end - begin))
            extra = 0.0
            for stage, spans in by_stage.items():
                if stage == "report" or len(spans) < 2:
                    continue
                spans.sort()
                first = spans[0][1] - statistics.median(d for _, d in spans[1:])
                extra += first
                if stage == "upsample":
                    loads.append(first)
            extras.append(extra)
        if loads:
            marks["model load in worker"] = statistics.median(loads)
            marks["first frame's extra in worker"] = statistics.median(extras)
    marks["exit"] = finished - t0
    marks["t0"] = t0
    return marks


def run_child(data: Path, frames: int, workers: int | None) -> dict[str, float]:
    """Run `child` in a fresh process; its marks."""
    done = subprocess.run([sys.executable, __file__, "--child", "--data", str(data), "--frames", str(frames),
                           *(["--workers", str(workers)] if workers else [])], capture_output=True, text=True)
    ended = time.time()
    lines = [line for line in done.stdout.splitlines() if line.startswith(CHILD_MARK)]
    if done.returncode or not lines:
        raise SystemExit(f"startup child failed (exit {done.returncode}):\n{done.stdout[-2000:]}\n{done.stderr[-3000:]}")
    marks = json.loads(lines[-1][len(CHILD_MARK):])
    marks["process ended"] = ended - marks.pop("t0")
    return marks


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path,
                        default=Path(__file__).resolve().parents[2] / "shared/data/kitti/odometry/sequences/00")
    parser.add_argument("--frames", type=int, default=4)
    parser.add_argument("--workers", type=int, default=None, help="kitti-pu run --workers (default: the product's)")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--timeline", action="store_true", help="print every repeat's marks")
    parser.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    revisions.add_arguments(parser)
    args = revisions.parse_or_compare(parser, Path(__file__))
    if args is None:
        return
    if args.child:
        child(args.data, args.frames, args.workers)
        return
    runs = [run_child(args.data, args.frames, args.workers) for _ in range(args.repeats)]
    names = sorted({name for marks in runs for name in marks}, key=lambda n: statistics.median(
        marks[n] for marks in runs if n in marks) if not n.endswith("in worker") else 1e9)
    medians = {name: statistics.median(marks[name] for marks in runs if name in marks) for name in names}
    if args.json:
        revisions.emit(medians)
        return
    print(f"kitti-pu run on {args.frames} scans of {args.data}: seconds from process start, "
          f"medians of {args.repeats} runs")
    for name in names:
        row = f"{name:<28}{medians[name]:>8.2f}"
        if args.timeline:
            row += "   " + " ".join(f"{marks.get(name, float('nan')):6.2f}" for marks in runs)
        print(row)


if __name__ == "__main__":
    main()
