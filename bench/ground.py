"""Ground removal side by side on real KITTI scans: quality, agreement with Patchwork++, speed.

    python bench/ground.py [--data ../shared/data/kitti/odometry/sequences/00] [--repeats 5]

For each method: precision, recall and F1 of the ground label on the frame with SemanticKITTI
labels (ground = classes 40 road, 44 parking, 48 sidewalk, 49 other-ground, 60 lane-marking,
72 terrain; vegetation, 70, left out of scoring), agreement with Patchwork++'s labels on every
frame, and the median milliseconds per frame.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from stages import ground  # noqa: E402
from stages.load import read_scan  # noqa: E402

GROUND_CLASSES = (40, 44, 48, 49, 60, 72)
IGNORED_CLASSES = (70,)
DEFAULT_DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "kitti" / "odometry" / "sequences" / "00"


def score(mask: np.ndarray, labels: np.ndarray) -> tuple[float, float, float]:
    """Precision, recall, F1 (percent) of a ground mask against SemanticKITTI labels."""
    semantic = labels & 0xFFFF
    scored = ~np.isin(semantic, IGNORED_CLASSES)
    truth = np.isin(semantic, GROUND_CLASSES)[scored]
    predicted = mask[scored]
    tp = float((truth & predicted).sum())
    precision = 100 * tp / max(predicted.sum(), 1)
    recall = 100 * tp / max(truth.sum(), 1)
    return precision, recall, 2 * precision * recall / max(precision + recall, 1e-9)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, default=DEFAULT_DATA)
    parser.add_argument("--repeats", type=int, default=5)
    args = parser.parse_args()
    scans = {path.stem: read_scan(path) for path in sorted((args.data / "velodyne").glob("*.bin"))}
    labels = {path.stem: np.fromfile(path, dtype=np.uint32) for path in sorted((args.data / "labels").glob("*.label"))}
    methods = [m for m in ground.METHODS]
    reference = {name: ground.segment(points, "patchworkpp").mask for name, points in scans.items()}
    print(f"{len(scans)} scans from {args.data}, {len(labels)} labelled; {args.repeats} timed repeats per scan")
    header = f"{'method':<12} {'precision':>9} {'recall':>7} {'F1':>6} {'agree min %':>11} {'agree mean %':>12} {'median ms':>9}"
    print(header)
    for method in methods:
        times, agreement = [], []
        for name, points in scans.items():
            for _ in range(args.repeats):
                started = time.perf_counter()
                mask = ground.segment(points, method).mask
                times.append(1000 * (time.perf_counter() - started))
            agreement.append(100 * float((mask == reference[name]).mean()))
        quality = [score(ground.segment(scans[name], method).mask, lab) for name, lab in labels.items()]
        precision, recall, f1 = np.mean(quality, axis=0)
        print(f"{method:<12} {precision:>9.2f} {recall:>7.2f} {f1:>6.2f} {min(agreement):>11.2f} "
              f"{np.mean(agreement):>12.2f} {np.median(times):>9.1f}")
    print("per-frame agreement of patchwork with Patchwork++ (%):",
          " ".join(f"{100 * float((ground.segment(p).mask == reference[n]).mean()):.2f}" for n, p in scans.items()))


if __name__ == "__main__":
    main()
