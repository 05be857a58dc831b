"""The load stage's cost per frame in a long KITTI raw drive: what reading a frame's metadata costs
as a drive grows (`stages.load.run`, whose pykitti readers once listed every file of the drive for
each frame).

    python bench/load_metadata.py [--frames 2000] [--sample 200] [--compare REF [--runs 3]]

Writes a synthetic raw drive of `--frames` frames into a temporary folder (one small synthetic scan
linked under every frame's name, and its OXTS packet and timestamp repeated), then times
`stages.load.run` on `--sample` frames spread over the drive, and prints the median milliseconds a
frame (wall clock) for the drive at its full length and at a tenth of it.
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
import time
from pathlib import Path

import numpy as np
import revisions

from pipeline.synthetic_drive import write_synthetic_drive
from stages import load


def grown_drive(base: Path, frames: int) -> Path:
    """A raw drive of `frames` frames under `base`, every scan a link to frame 1's (cut to every
    16th point, in ring order), every packet and timestamp a copy of frame 1's."""
    drive = write_synthetic_drive(base, n_frames=2, seed=0)
    scans, packets = drive / "velodyne_points" / "data", drive / "oxts" / "data"
    scan = np.fromfile(scans / f"{1:010d}.bin", dtype=np.float32).reshape(-1, 4)[::16]
    scan.tofile(scans / f"{1:010d}.bin")
    packet = (packets / f"{1:010d}.txt").read_text()
    stamps = drive / "oxts" / "timestamps.txt"
    second = stamps.read_text().splitlines()[1]
    with stamps.open("a") as lines:
        lines.writelines(f"{second}\n" for _ in range(2, frames))
    for index in range(2, frames):
        (packets / f"{index:010d}.txt").write_text(packet)
        (scans / f"{index:010d}.bin").symlink_to(scans / f"{1:010d}.bin")
    return drive


def ms_per_frame(refs: list[load.FrameRef], sample: int) -> float:
    """Median wall milliseconds of `load.run` over `sample` frames spread over `refs`."""
    picked = refs[:: max(1, len(refs) // sample)][:sample]
    load.run(picked[0])  # imports and first reads outside the timing
    times = []
    for ref in picked:
        started = time.perf_counter()
        load.run(ref)
        times.append((time.perf_counter() - started) * 1000)
    return statistics.median(times)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=2000)
    parser.add_argument("--sample", type=int, default=200)
    revisions.add_arguments(parser)
    args = revisions.parse_or_compare(parser, Path(__file__))
    if args is None:
        return
    figures = {}
    for frames in (args.frames // 10, args.frames):
        with tempfile.TemporaryDirectory() as folder:
            grown_drive(Path(folder), frames)
            refs = load.discover(Path(folder))
            figures[f"load ms/frame, {frames}-frame drive"] = ms_per_frame(refs, args.sample)
    if args.json:
        revisions.emit(figures)
    for name, value in figures.items():
        print(f"{name}: {value:.2f}")


if __name__ == "__main__":
    main()
