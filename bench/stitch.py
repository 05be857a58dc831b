"""Speed of the stages after the network on real KITTI scans: the output cloud (stitch, snap, fill)
with its options side by side, and the write stage: ms per frame.

    python bench/stitch.py [--data ../shared/data/kitti/odometry] [--repeats 5] [--frames 2]
                           [--inputs DIR] [--keep OUT] [--compare REF [--runs 3]]

For each scan, the frame is taken through load, ground, tile and upsample once with the defaults
(configs/pipeline.yaml: the scan-trained weights, every patch upsampled); with --inputs DIR the
upsampled frames are kept there (one .npz per scan) and reused by later runs, so the network runs
once. After one untimed pass (imports, compiled kernels), the chain's stitch, snap and fill steps
are timed `repeats` times in each configuration below, interleaved so that a noisy spell of a
shared machine hits them alike, and the write step (the default formats, Parquet and PLY, into a
temporary folder) once per repeat on the defaults' cloud. Prints the median wall ms per
configuration over all scans and repeats, the points each writes, the defaults' ms per stage, and
the same in CPU ms (`time.process_time`: this process,
all its threads; on a machine shared with other work it moves less than the wall time: stitch,
snap and fill run on one thread, write on two, Parquet beside PLY).

- defaults: ring snapping, range check with spreading, ground fill;
- no ground fill: `fill.enabled=false`;
- nearest ring only: snapping without range check nor spreading (`snap.range_tolerance=null`), no fill;
- plain stitch: no snapping, no fill.

With --compare REF, runs this script on git revision REF and on the working tree, interleaved,
and prints both with their ratio (`bench/revisions.py`; give --inputs so that both sides stitch
the same network output and the network runs once).
"""

from __future__ import annotations

import argparse
import dataclasses
import statistics
import tempfile
import time
from pathlib import Path

import numpy as np

import revisions
from cadpu.patches import PatchCover
from pipeline.chain import Chain
from pipeline.config import PipelineConfig
from stages import load
from stages.frame import Frame

DEFAULT_DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "kitti" / "odometry"
#: The stages timed together: the output cloud from the upsampled patches.
CLOUD_STAGES = ("stitch", "snap", "fill")
#: What the upsample stage's frame holds beyond the loaded scan (saved with --inputs).
UPSAMPLED_FIELDS = ("ground", "upsampled", "parent_slots", "upsampled_patches", "ratio")


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


def kept_upsampled_frame(ref: load.FrameRef, config: PipelineConfig, inputs: Path | None) -> Frame:
    """`upsampled_frame`, read from `inputs/NNNNNN.npz` when there (the scan loaded anew, the
    later stages' fields from the file), else computed and, with `inputs`, saved there."""
    path = None if inputs is None else inputs / f"{ref.index:06d}.npz"
    if path is not None and path.is_file():
        saved = np.load(path)
        tiling = PatchCover(**{f.name: saved[f"tiling.{f.name}"] for f in dataclasses.fields(PatchCover)})
        fields = {name: saved[name] for name in UPSAMPLED_FIELDS}
        fields["ratio"] = int(fields["ratio"])
        if not saved["has_upsampled_patches"]:
            fields["upsampled_patches"] = None  # all patches, in order
        return load.run(ref, config.input).with_(tiling=tiling, **fields)
    frame = upsampled_frame(ref, config)
    if path is not None:
        path.parent.mkdir(parents=True, exist_ok=True)
        arrays = {f"tiling.{f.name}": getattr(frame.tiling, f.name) for f in dataclasses.fields(PatchCover)}
        arrays.update({name: np.zeros(0, np.int64) if getattr(frame, name) is None else getattr(frame, name)
                       for name in UPSAMPLED_FIELDS})
        arrays["has_upsampled_patches"] = np.array(frame.upsampled_patches is not None)
        np.savez(path, **arrays)
    return frame


def measure(data: Path, frames: int, repeats: int, inputs: Path | None,
            keep: Path | None = None) -> dict[str, float]:
    """Median ms per configuration, points per configuration, the defaults' ms per stage, and
    the write stage's ms (see the module docstring); the written files go to `keep` when given."""
    config = PipelineConfig()
    timed = {name: cloud_steps(variant) for name, variant in variants(config).items()}
    wall: dict[str, list[float]] = {name: [] for name in timed}
    points: dict[str, list[int]] = {name: [] for name in timed}
    stage_ms: dict[str, list[float]] = {name: [] for name in (*CLOUD_STAGES, "write")}
    cpu: dict[str, list[float]] = {name: [] for name in (*timed, *CLOUD_STAGES, "write")}
    with tempfile.TemporaryDirectory(prefix="kitti-pu-bench-") as temporary:
        out = keep or Path(temporary)
        write_step = Chain(config.model_copy(update={"output": config.output.model_copy(update={"dir": out})}),
                           {"tool_version": "bench"}).steps[-1]
        for number, ref in enumerate(load.discover(data)[:frames]):
            frame = kept_upsampled_frame(ref, config, inputs)
            if number == 0:  # warm-up, untimed: imports, compiled kernels loaded from their cache
                for steps in timed.values():
                    result = frame
                    for step in steps:
                        result = step(result)
                write_step(result)
            for _ in range(repeats):
                for name, steps in timed.items():
                    started, cpu_started = time.perf_counter(), time.process_time()
                    result = frame
                    for step in steps:
                        step_cpu = time.process_time()
                        result = step(result)
                        if name == "defaults":
                            cpu[step.name].append(1000.0 * (time.process_time() - step_cpu))
                    wall[name].append(1000.0 * (time.perf_counter() - started))
                    cpu[name].append(1000.0 * (time.process_time() - cpu_started))
                    points[name].append(len(result.cloud))
                    if name == "defaults":
                        for stage in CLOUD_STAGES:
                            stage_ms[stage].append(1000.0 * result.timings.get(stage, 0.0))
                        step_cpu = time.process_time()
                        written = write_step(result)
                        cpu["write"].append(1000.0 * (time.process_time() - step_cpu))
                        if not isinstance(written, Frame):
                            raise SystemExit(f"write failed: {written}")
                        stage_ms["write"].append(1000.0 * written.timings["write"])
    figures = {f"{name} ms": statistics.median(values) for name, values in wall.items()}
    figures.update({f"{name} points": float(statistics.mean(values)) for name, values in points.items()})
    figures.update({f"defaults: {stage} ms": statistics.median(values) for stage, values in stage_ms.items()})
    figures.update({f"{name} cpu ms": statistics.median(values) for name, values in cpu.items()})
    return figures


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, default=DEFAULT_DATA, help="KITTI sequence, drive or .bin folder")
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--frames", type=int, default=2, help="first N scans")
    parser.add_argument("--inputs", type=Path, default=None,
                        help="folder keeping the upsampled frames between runs (the network runs once)")
    parser.add_argument("--keep", type=Path, default=None,
                        help="write the defaults' files here (kept; bench/output_digest.py compares two such folders)")
    revisions.add_arguments(parser)
    args = revisions.parse_or_compare(parser, Path(__file__))
    if args is None:
        return
    figures = measure(args.data, args.frames, args.repeats, args.inputs, args.keep)
    if args.json:
        revisions.emit(figures)
        return
    print(f"{min(args.frames, len(load.discover(args.data)))} scans from {args.data}, {args.repeats} repeats each, "
          "interleaved")
    print(f"{'configuration':<20} {'median ms':>10} {'points written':>15}")
    for name in variants(PipelineConfig()):
        print(f"{name:<20} {figures[f'{name} ms']:>10.1f} {figures[f'{name} points']:>15,.0f}")
    print("defaults, per stage: " + ", ".join(f"{stage} {figures[f'defaults: {stage} ms']:.1f} ms"
                                             for stage in (*CLOUD_STAGES, "write")))
    print("CPU time (process_time, all threads): " + ", ".join(f"{name} {value:.1f} ms" for name, value in
                                                              figures.items() if name.endswith(" cpu ms")))


if __name__ == "__main__":
    main()
