"""Speed of the stages that make the output cloud (stitch, snap, fill) on real KITTI scans, their
options side by side: ms per frame.

    python bench/stitch.py [--data ../shared/data/kitti/odometry] [--repeats 5] [--frames 2]

For each scan, the frame is taken through ground, tile and upsample once with the defaults
(configs/pipeline.yaml: the scan-trained weights, every patch upsampled); then the chain's stitch,
snap and fill steps are timed `repeats` times in each configuration below, interleaved so that a noisy spell of a shared
machine hits them alike. Prints the median wall ms per configuration over all scans and repeats,
and the points each writes.

- defaults: ring snapping, range check with spreading, ground fill;
- no ground fill: `fill.enabled=false`;
- nearest ring only: snapping without range check nor spreading (`snap.range_tolerance=null`), no fill;
- plain stitch: no snapping, no fill.
"""

from __future__ import annotations

import argparse
import statistics
import time
from pathlib import Path

from pipeline.chain import Chain
from pipeline.config import PipelineConfig
from stages import load
from stages.frame import Frame

DEFAULT_DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "kitti" / "odometry"
#: The stages timed together: the output cloud from the upsampled patches.
CLOUD_STAGES = ("stitch", "snap", "fill")


def variants(config: PipelineConfig) -> dict[str, PipelineConfig]:
    """The configuration of each variant timed."""
    def changed(**sections: dict) -> PipelineConfig:
        return config.model_copy(update={name: getattr(config, name).model_copy(update=values)
                                         for name, values in sections.items()})

    return {
        "defaults": config,
        "no ground fill": changed(fill={"enabled": False}),
        "nearest ring only": changed(snap={"range_tolerance": None}, fill={"enabled": False}),
        "plain stitch": changed(snap={"enabled": False}, fill={"enabled": False}),
    }


def cloud_steps(config: PipelineConfig) -> list:
    """The chain's steps that make the output cloud (`CLOUD_STAGES`) with `config`."""
    return [step for step in Chain(config, writes=False).steps if step.name in CLOUD_STAGES]


def upsampled_frame(ref: load.FrameRef, config: PipelineConfig) -> Frame:
    """The scan of `ref` through the chain up to the upsample stage, with `config`."""
    frame: object = ref
    for step in Chain(config, writes=False).steps:
        if step.name in CLOUD_STAGES:
            break
        frame = step(frame)
    return frame  # type: ignore[return-value]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, default=DEFAULT_DATA, help="KITTI sequence, drive or .bin folder")
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--frames", type=int, default=2, help="first N scans")
    args = parser.parse_args()
    config = PipelineConfig()
    timed = {name: cloud_steps(variant) for name, variant in variants(config).items()}
    wall: dict[str, list[float]] = {name: [] for name in timed}
    points: dict[str, list[int]] = {name: [] for name in timed}
    refs = load.discover(args.data)[:args.frames]
    for ref in refs:
        frame = upsampled_frame(ref, config)
        for _ in range(args.repeats):
            for name, steps in timed.items():
                started = time.perf_counter()
                result = frame
                for step in steps:
                    result = step(result)
                wall[name].append(1000.0 * (time.perf_counter() - started))
                points[name].append(len(result.cloud))
    print(f"{len(refs)} scans from {args.data}, {args.repeats} repeats each, interleaved")
    print(f"{'configuration':<20} {'median ms':>10} {'points written':>15}")
    for name in timed:
        print(f"{name:<20} {statistics.median(wall[name]):>10.1f} {statistics.mean(points[name]):>15,.0f}")


if __name__ == "__main__":
    main()
