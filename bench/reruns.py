"""What a scheduled rerun costs when every frame is already finished, by the number of frames.

    python bench/reruns.py --work DIR [--frames 1000] [--azimuths 100] [--formats parquet,ply,kitti]
                           [--repeats 3] [--compare REF --runs 3]

A job that densifies a growing dataset reruns `kitti-pu run` every hour, and almost every frame is
finished: what it then costs is the planning (every finished frame's files checked), not the
network. The first call writes `--frames` small synthetic scans (64 rings of `--azimuths` returns
each, a ground plane and a round wall, slightly different in each scan) into DIR/scans and runs
them once into DIR/out; later calls, and both sides of `--compare`, reuse them. Then, timed with
the code on PYTHONPATH (each command a fresh `python -m pipeline` process, as cron starts it):
`run` with every frame skipped, `run --dry-run`, `info` and `info --verify`, medians of
`--repeats`, in seconds (about 2 s of each is the start-up: imports). A rerun that does not skip every frame is
an error (the folder was made by a version whose records the code timed does not accept).
"""

from __future__ import annotations

import argparse
import json
import math
import statistics
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import revisions  # noqa: E402

#: Elevation of the HDL-64E's highest and lowest laser (degrees), as KITTI's scans span.
TOP_DEGREES, BOTTOM_DEGREES = 2.0, -24.8
#: The sensor's height above the ground plane and the wall's distance (metres).
SENSOR_HEIGHT, WALL_RADIUS = 1.73, 15.0


def synthetic_scan(azimuths: int, seed: int) -> np.ndarray:
    """(64 * azimuths, 4) float32 x, y, z, reflectance: 64 rings, stored ring by ring as KITTI's
    scans are, of a ground plane and a round wall, with 1 cm of range noise."""
    rng = np.random.default_rng(seed)
    elevation = np.radians(np.linspace(TOP_DEGREES, BOTTOM_DEGREES, 64))[:, None]
    azimuth = np.linspace(0.0, 2 * math.pi, azimuths, endpoint=False)[None, :]
    direction = np.stack(np.broadcast_arrays(np.cos(elevation) * np.cos(azimuth), np.cos(elevation) * np.sin(azimuth),
                                             np.sin(elevation) + 0 * azimuth), axis=-1).reshape(-1, 3)
    to_ground = np.where(direction[:, 2] < 0, -SENSOR_HEIGHT / np.minimum(direction[:, 2], -1e-9), np.inf)
    to_wall = WALL_RADIUS / np.hypot(direction[:, 0], direction[:, 1])
    distance = np.minimum(to_ground, to_wall) + rng.normal(0.0, 0.01, len(direction))
    points = direction * distance[:, None]
    return np.column_stack([points, rng.uniform(0.0, 1.0, len(points))]).astype(np.float32)


def cli(*args: str) -> subprocess.CompletedProcess:
    """`kitti-pu ARGS` in a fresh process of the Python running this script (its PYTHONPATH)."""
    return subprocess.run([sys.executable, "-m", "pipeline", *args], capture_output=True, text=True)


def prepare(work: Path, frames: int, azimuths: int, formats: str) -> tuple[Path, Path]:
    """DIR/scans with `frames` scans and DIR/out with all of them finished (made once)."""
    scans, out = work / "scans", work / "out"
    if not (out / "summary.json").is_file():
        scans.mkdir(parents=True, exist_ok=True)
        for index in range(frames):
            synthetic_scan(azimuths, index).tofile(scans / f"{index:06d}.bin")
        print(f"reruns: densifying {frames} scans once into {out} (later calls reuse them)", file=sys.stderr)
        done = cli("run", str(scans), "--out", str(out), "--workers", "1", "--format", formats, "--no-progress")
        if done.returncode:
            raise SystemExit(f"reruns: the first run failed (exit {done.returncode}): {done.stderr[-1000:]}")
    return scans, out


def timed(args: list[str], check_skipped: int | None = None) -> float:
    """Wall seconds of `kitti-pu ARGS`; with `check_skipped`, the run must have skipped that many."""
    started = time.perf_counter()
    done = cli(*args)
    seconds = time.perf_counter() - started
    if done.returncode not in (0, 3):  # verify exits 3 on damage: timed all the same
        raise SystemExit(f"reruns: kitti-pu {' '.join(args)} exited {done.returncode}: {done.stderr[-1000:]}")
    if check_skipped is not None:
        summary = json.loads(Path(args[args.index("--out") + 1], "summary.json").read_text())
        if summary["frames_skipped"] != check_skipped:
            raise SystemExit(f"reruns: the rerun skipped {summary['frames_skipped']} of {check_skipped} frames: "
                             "the folder was made by a version whose frames this code redoes")
    return seconds


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--work", type=Path, required=True, help="folder of the scans and the finished output (kept)")
    parser.add_argument("--frames", type=int, default=1000)
    parser.add_argument("--azimuths", type=int, default=100, help="returns per ring of each synthetic scan")
    parser.add_argument("--formats", default="parquet,ply,kitti")
    parser.add_argument("--repeats", type=int, default=3)
    revisions.add_arguments(parser)
    args = revisions.parse_or_compare(parser, Path(__file__))
    if args is None:
        return
    scans, out = prepare(args.work.absolute(), args.frames, args.azimuths, args.formats)
    frames = len(list(scans.glob("*.bin")))
    run = ["run", str(scans), "--out", str(out), "--workers", "1", "--format", args.formats, "--no-progress"]
    commands = {"rerun, every frame skipped": (run, frames), "run --dry-run": ([*run, "--dry-run"], None),
                "info": (["info", str(out)], None), "info --verify": (["info", str(out), "--verify"], None)}
    figures = {}
    for name, (command, skipped) in commands.items():
        seconds = statistics.median(timed(command, skipped) for _ in range(args.repeats))
        figures[f"{name} (s)"] = round(seconds, 3)
    if args.json:
        revisions.emit(figures)
        return
    print(f"{frames} finished frames ({args.formats}), medians of {args.repeats}:")
    for name, value in figures.items():
        print(f"  {name:45s} {value:8.3f}")


if __name__ == "__main__":
    main()
