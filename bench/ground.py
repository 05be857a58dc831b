"""Ground removal side by side on real KITTI scans: quality, agreement with Patchwork++, speed.

    python bench/ground.py [--data ../shared/data/kitti/odometry/sequences/00] [--repeats 5]
                           [--methods patchwork,ransac,patchworkpp]

For each method: precision, recall and F1 (percent) of the ground label on the frames with
SemanticKITTI labels (ground = classes 40 road, 44 parking, 48 sidewalk, 49 other-ground,
60 lane-marking, 72 terrain; vegetation, class 70, left out of scoring), agreement with
Patchwork++'s labels (percent of points labelled the same) on every frame, and the median
milliseconds per frame over all frames and repeats, both wall-clock and CPU time of this process
(the CPU time is less disturbed by other jobs sharing the machine).
"""

from __future__ import annotations

import argparse
import importlib.util
import sys
import time
from pathlib import Path

import numpy as np

from stages import ground
from stages.load import read_scan

GROUND_CLASSES = (40, 44, 48, 49, 60, 72)
IGNORED_CLASSES = (70,)
DEFAULT_DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "kitti" / "odometry" / "sequences" / "00"


def score(mask: np.ndarray, labels: np.ndarray) -> tuple[float, float, float]:
    """Precision, recall and F1 (percent) of a (N,) ground mask against (N,) SemanticKITTI labels
    (uint32, class in the lower 16 bits), ignoring `IGNORED_CLASSES`."""
    semantic = labels & 0xFFFF
    scored = ~np.isin(semantic, IGNORED_CLASSES)
    truth = np.isin(semantic, GROUND_CLASSES)[scored]
    predicted = mask[scored]
    hits = float((truth & predicted).sum())
    precision = 100 * hits / max(int(predicted.sum()), 1)
    recall = 100 * hits / max(int(truth.sum()), 1)
    return precision, recall, 2 * precision * recall / max(precision + recall, 1e-9)


def timed(points: np.ndarray, method: str, repeats: int) -> tuple[np.ndarray, list[float], list[float]]:
    """The method's mask on a scan and its wall and CPU milliseconds over `repeats` runs (after one
    untimed warm-up run)."""
    mask = ground.segment(points, method).mask
    wall, cpu = [], []
    for _ in range(repeats):
        wall_start, cpu_start = time.perf_counter(), time.process_time()
        ground.segment(points, method)
        cpu.append(1000 * (time.process_time() - cpu_start))
        wall.append(1000 * (time.perf_counter() - wall_start))
    return mask, wall, cpu


def load(data: Path) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray]]:
    """Scans (N, 4) float32 and labels (N,) uint32 of a sequence folder, by frame name."""
    scans = {path.stem: read_scan(path) for path in sorted((data / "velodyne").glob("*.bin"))}
    if not scans:
        sys.exit(f"no velodyne/*.bin in {data}")
    labels = {path.stem: np.fromfile(path, dtype=np.uint32) for path in sorted((data / "labels").glob("*.label"))}
    return scans, {name: lab for name, lab in labels.items() if name in scans}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, default=DEFAULT_DATA)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--methods", default=",".join(ground.GROUND_METHODS))
    args = parser.parse_args()
    methods = args.methods.split(",")
    if importlib.util.find_spec("pypatchworkpp") is None:  # the reference of every agreement figure
        sys.exit('bench/ground.py: the agreement is measured against Patchwork++, the optional package '
                 'pypatchworkpp: pip install "kitti-pu[patchwork]"')
    scans, labels = load(args.data)
    reference = {name: ground.segment(points, "patchworkpp").mask for name, points in scans.items()}
    print(f"{len(scans)} scans from {args.data}, {len(labels)} labelled; {args.repeats} timed repeats per scan")
    print(f"{'method':<12} {'precision':>9} {'recall':>7} {'F1':>6} {'agree min %':>11} {'agree mean %':>12} "
          f"{'wall ms':>8} {'cpu ms':>7}")
    per_frame: dict[str, list[float]] = {}
    for method in methods:
        masks, wall, cpu = {}, [], []
        for name, points in scans.items():
            masks[name], frame_wall, frame_cpu = timed(points, method, args.repeats)
            wall += frame_wall
            cpu += frame_cpu
        agreement = [100 * float((masks[name] == reference[name]).mean()) for name in scans]
        per_frame[method] = agreement
        quality = np.mean([score(masks[name], lab) for name, lab in labels.items()], axis=0)
        print(f"{method:<12} {quality[0]:>9.2f} {quality[1]:>7.2f} {quality[2]:>6.2f} {min(agreement):>11.2f} "
              f"{np.mean(agreement):>12.2f} {np.median(wall):>8.1f} {np.median(cpu):>7.1f}")
    print("agreement with Patchwork++ per frame (%):")
    for method, agreement in per_frame.items():
        print(f"  {method:<12}", " ".join(f"{name}={value:.2f}" for name, value in zip(scans, agreement)))


if __name__ == "__main__":
    main()
