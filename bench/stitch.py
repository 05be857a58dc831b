"""Stitch-stage speed on real KITTI scans, its options side by side: ms per frame of `stages.stitch.run`.

    python bench/stitch.py [--data ../shared/data/kitti/odometry] [--repeats 5] [--frames 2]

For each scan, the frame is taken through ground, tile and upsample once with the defaults
(configs/pipeline.yaml: the scan-trained weights, every patch upsampled); then `stitch.run` is
timed `repeats` times in each configuration below, interleaved so that a noisy spell of a shared
machine hits them alike. Prints the median wall ms per configuration over all scans and repeats,
and the points each writes.

- defaults: ring snapping, range check with spreading, ground fill;
- no ground fill: `fill_ground=False`;
- nearest ring only: snapping without range check nor spreading (`range_tolerance=None`), no fill;
- plain stitch: no snapping, no fill.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

# bench/pipeline.py would shadow the `pipeline` package: put the repository root first instead.
sys.path[0] = str(Path(__file__).resolve().parents[1])

from cadpu.inference import Upsampler  # noqa: E402
from pipeline.config import PipelineConfig, stitch_options  # noqa: E402
from pipeline.eval_kitti import ground_and_tile  # noqa: E402
from stages import load, stitch, upsample  # noqa: E402
from stages.frame import Frame  # noqa: E402

DEFAULT_DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "kitti" / "odometry"


def variants(config: PipelineConfig) -> dict[str, dict]:
    """Keyword arguments of `stitch.run` for each configuration timed."""
    defaults = stitch_options(config)
    return {
        "defaults": defaults,
        "no ground fill": {**defaults, "fill_ground": False},
        "nearest ring only": {**defaults, "range_tolerance": None, "fill_ground": False},
        "plain stitch": {**defaults, "snap_to_rings": False, "fill_ground": False},
    }


def upsampled_frame(ref: load.FrameRef, config: PipelineConfig, model: Upsampler) -> Frame:
    """The scan of `ref` through ground, tile and upsample with `config`."""
    frame = ground_and_tile(load.load_frame(ref, config.input.max_points), config)
    return upsample.run(frame, model, config.upsample.patch_radius_limit)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, default=DEFAULT_DATA, help="KITTI sequence, drive or .bin folder")
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--frames", type=int, default=2, help="first N scans")
    args = parser.parse_args()
    config = PipelineConfig()
    model = Upsampler(config.upsample.weights, batch_size=config.upsample.batch_size, seed=config.upsample.seed)
    timed = variants(config)
    wall: dict[str, list[float]] = {name: [] for name in timed}
    points: dict[str, list[int]] = {name: [] for name in timed}
    refs = load.discover(args.data)[:args.frames]
    for ref in refs:
        frame = upsampled_frame(ref, config, model)
        for _ in range(args.repeats):
            for name, kwargs in timed.items():
                started = time.perf_counter()
                _, cloud = stitch.run(frame, **kwargs)
                wall[name].append(1000.0 * (time.perf_counter() - started))
                points[name].append(len(cloud))
    print(f"{len(refs)} scans from {args.data}, {args.repeats} repeats each, interleaved")
    print(f"{'configuration':<20} {'median ms':>10} {'points written':>15}")
    for name in timed:
        print(f"{name:<20} {statistics.median(wall[name]):>10.1f} {statistics.mean(points[name]):>15,.0f}")


if __name__ == "__main__":
    main()
