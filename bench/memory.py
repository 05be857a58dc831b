"""Worker memory over a long run: the demo's simulated drive through the real pipeline.

Usage:
    python bench/memory.py [--drive /tmp/kitti-pu-memory-drive] [--frames 100] [--workers N]
                           [--interval 0.25] [--samples FILE.csv] [--set key=value ...] [--json]
    python bench/memory.py --in-process [--trim] [--frames 60]   (the first 60 frames of --drive)

Writes (or reuses, when it already holds `--frames` scans) a simulated KITTI raw drive in --drive,
the one `kitti-pu demo` writes (`pipeline.synthetic_drive`, seed 0), then runs it through
`pipeline.runner.run_pipeline` with the product's defaults (its own LocalCluster, one worker per
core, at most 4) into a temporary output folder. A thread samples the resident set size of every
worker process (the direct children of this process that multiprocessing spawned: the LocalCluster's
nannies live in this process and spawn one worker process each) every --interval seconds, with the
number of frames finished at that moment, and reads each worker's peak (VmHWM) at every sample.

Prints, per worker: the peak RSS, the RSS at the first sample after 10, 25, 50, 75 and all frames
had finished, and the slope of a least-squares line through the samples of the second half of the
run (frames finished >= half), in MiB per 10 frames: through all samples, and through the floor
(the lowest sample while each count of frames finished held, which the frames in flight move
less). --samples FILE writes every sample as CSV.

With --in-process [--trim], runs the chain over the frames in this process instead, without Dask,
and prints the RSS after 10, 25, 50, 75 and 100% of them (`in_process`).
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import psutil

sys.path.insert(0, str(Path(__file__).resolve().parent))
import revisions  # noqa: E402

MIB = 1024.0 * 1024.0
MARKS = (10, 25, 50, 75, 100)


def ensure_drive(folder: Path, frames: int, seed: int = 0, at_least: bool = False) -> Path:
    """The raw base `folder` holding the demo's simulated drive of `frames` scans (written when
    the folder does not hold exactly that many, or with `at_least`, at least that many)."""
    from pipeline.synthetic_drive import write_synthetic_drive

    scans = sorted(folder.glob("*/*_drive_*_sync/velodyne_points/data/*.bin"))
    if len(scans) < frames or (len(scans) != frames and not at_least):
        started = time.perf_counter()
        write_synthetic_drive(folder, n_frames=frames, seed=seed)
        print(f"simulated {frames} frames in {folder} ({time.perf_counter() - started:.0f} s)", file=sys.stderr)
    return folder


def worker_processes() -> list[psutil.Process]:
    """This process's children started by multiprocessing's spawn (the LocalCluster's workers)."""
    found = []
    for child in psutil.Process().children():
        try:
            if any("spawn_main" in part for part in child.cmdline()):
                found.append(child)
        except psutil.Error:
            continue
    return found


def peak_rss(pid: int) -> float | None:
    """VmHWM of `pid` in bytes (the kernel's peak resident set size), or None when unreadable."""
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmHWM:"):
                return float(line.split()[1]) * 1024.0
    except OSError:
        return None
    return None


@dataclass
class Sampler:
    """Samples worker RSS every `interval` seconds in a thread while `frames_done` advances."""

    interval: float
    frames_done: int = 0
    samples: dict[int, list[tuple[float, int, float]]] = field(default_factory=dict)  # pid -> (t, frames, rss)
    peaks: dict[int, float] = field(default_factory=dict)
    _stop: threading.Event = field(default_factory=threading.Event)

    def _loop(self) -> None:
        started = time.perf_counter()
        while not self._stop.wait(self.interval):
            for process in worker_processes():
                try:
                    rss = float(process.memory_info().rss)
                except psutil.Error:
                    continue
                self.samples.setdefault(process.pid, []).append((time.perf_counter() - started, self.frames_done, rss))
                peak = peak_rss(process.pid)
                if peak is not None:
                    self.peaks[process.pid] = max(peak, self.peaks.get(process.pid, 0.0))

    def __enter__(self) -> "Sampler":
        self._thread = threading.Thread(target=self._loop, daemon=True)
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._thread.join()


def figures(sampler: Sampler, frames: int) -> dict[str, float]:
    """Per worker (numbered by start order): peak MiB, MiB after each of MARKS, and the slope (MiB
    per 10 frames) of the second half."""
    out: dict[str, float] = {}
    for number, (pid, rows) in enumerate(sorted(sampler.samples.items()), start=1):
        array = np.array([(done, rss) for _, done, rss in rows])
        out[f"worker {number}: peak MiB"] = sampler.peaks.get(pid, array[:, 1].max()) / MIB
        for mark in MARKS:
            target = round(mark * frames / 100)
            after = array[array[:, 0] >= target]
            if len(after):
                out[f"worker {number}: MiB after {target} frames"] = after[0, 1] / MIB
            elif mark == MARKS[-1]:  # the workers may end before a sample sees the last report
                out[f"worker {number}: MiB at its last sample ({int(array[-1, 0])} frames)"] = array[-1, 1] / MIB
        half = array[array[:, 0] >= frames / 2]
        if len(half) > 2 and np.ptp(half[:, 0]) > 0:
            slope = np.polyfit(half[:, 0], half[:, 1] / MIB, 1)[0]
            out[f"worker {number}: MiB per 10 frames, 2nd half"] = 10.0 * slope
            counts = np.unique(half[:, 0])
            floors = np.array([half[half[:, 0] == count, 1].min() for count in counts])
            if len(counts) > 2:
                slope = np.polyfit(counts, floors / MIB, 1)[0]
                out[f"worker {number}: floor MiB per 10 frames, 2nd half"] = 10.0 * slope
    return out


def write_samples(sampler: Sampler, path: Path) -> None:
    """The samples as CSV: worker, seconds, frames finished, RSS MiB."""
    rows = ["worker,seconds,frames_done,rss_mib"]
    for number, (_, samples) in enumerate(sorted(sampler.samples.items()), start=1):
        rows += [f"{number},{t:.2f},{done},{rss / MIB:.1f}" for t, done, rss in samples]
    path.write_text("\n".join(rows) + "\n")


def in_process(drive: Path, frames: int, trim: bool) -> dict[str, float]:
    """Run the chain (`pipeline.chain.Chain`, outputs written to a temporary folder) over the
    drive's first `frames` frames in this process with one torch thread, no Dask; return the RSS
    (MiB) after each of MARKS' frames, and with `trim` also after glibc's `malloc_trim(0)`, which
    is called after every frame (what remains then is what the frames keep alive)."""
    import ctypes
    import gc

    import torch

    from pipeline.chain import Chain
    from pipeline.config import load_config
    from pipeline.preflight import discover_frames, resolve_paths

    torch.set_num_threads(1)
    libc = ctypes.CDLL("libc.so.6")
    process = psutil.Process()
    out: dict[str, float] = {}
    with tempfile.TemporaryDirectory(prefix="kitti-pu-memory-") as folder:
        config = resolve_paths(load_config([], {"input.path": str(drive), "input.kind": "raw", "output.dir": folder}))
        chain = Chain(config, {"ratio": "4", "model_checksum": "", "config_hash": "", "tool_version": "bench"})
        targets = {round(mark * frames / 100) for mark in MARKS}
        for done, ref in enumerate(discover_frames(config)[:frames], start=1):
            chain.run(ref)
            gc.collect()
            rss = process.memory_info().rss / MIB
            if trim:
                libc.malloc_trim(0)
            if done in targets:
                out[f"in process: MiB after {done} frames"] = rss
                if trim:
                    out[f"in process: MiB after {done} frames, trimmed"] = process.memory_info().rss / MIB
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--drive", type=Path, default=Path(tempfile.gettempdir()) / "kitti-pu-memory-drive",
                        help="raw base of the simulated drive (written when it lacks --frames scans)")
    parser.add_argument("--frames", type=int, default=100)
    parser.add_argument("--workers", type=int, default=None, help="dask.n_workers (default: the product's)")
    parser.add_argument("--interval", type=float, default=0.25, help="seconds between samples")
    parser.add_argument("--in-process", action="store_true",
                        help="run the chain in this process instead (no Dask), see `in_process`")
    parser.add_argument("--trim", action="store_true", help="with --in-process: malloc_trim(0) after every frame")
    parser.add_argument("--samples", type=Path, default=None, help="write every sample to this CSV file")
    parser.add_argument("--set", dest="sets", action="append", default=[], metavar="KEY=VALUE",
                        help="a configuration override, as kitti-pu run's --set")
    revisions.add_arguments(parser)
    args = revisions.parse_or_compare(parser, Path(__file__))
    if args is None:
        return

    from pipeline.cli_common import _parse_sets
    from pipeline.config import load_config
    from pipeline.runner import run_pipeline

    drive = ensure_drive(args.drive, args.frames, at_least=args.in_process)
    if args.in_process:
        for name, value in in_process(drive, args.frames, args.trim).items():
            print(f"{name:<44}{value:>10.1f}")
        return
    with tempfile.TemporaryDirectory(prefix="kitti-pu-memory-") as out:
        overrides = {"input.path": str(drive), "input.kind": "raw", "output.dir": out, "dask.n_workers": args.workers}
        config = load_config([], overrides, _parse_sets(args.sets))
        sampler = Sampler(args.interval)

        def count(report: object) -> None:
            sampler.frames_done += 1

        started = time.perf_counter()
        with sampler:
            summary = run_pipeline(config, progress=False, on_report=count)
        wall = time.perf_counter() - started
    failed = [frame.error for frame in summary.frames if frame.status not in ("done", "replaced")]
    if failed:
        raise SystemExit(f"frames failed: {failed[:3]}")
    result = figures(sampler, args.frames)
    if args.samples:
        write_samples(sampler, args.samples)
    if args.json:
        revisions.emit(result)
        return
    print(f"{args.frames} simulated frames, {summary.workers} workers, {wall:.0f} s, "
          f"samples every {args.interval} s")
    for name, value in result.items():
        print(f"{name:<44}{value:>10.1f}")


if __name__ == "__main__":
    main()
