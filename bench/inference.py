"""CAD-PU speed on this CPU: ms per 256-point patch at r = 4, share of the matmul peak, training steps/s.

    python bench/inference.py [--weights cadpu/weights/cadpu_r4.pt] [--repeats 5]
        [--sections engines,sweep,processes,training] [--threads 1] [--batch 4] [--sweep-threads 1,2]
        [--compare REF [--runs 3]]

Prints the FLOPs per patch (torch's FLOP counter) and this machine's measured float32
matrix-multiply peak; then, by section (every path one plain pass of the network, `oversample=1`,
no selection: what the pipeline runs):
- engines: every inference engine of `cadpu.engines` and both EdgeConv layouts side by side,
  repeats interleaved: median ms per patch, share of the peak, and the max and mean distance of
  their generated points from torch eager's (in the patches' unit sphere), and whether the parents
  are identical;
- sweep: eager at batch sizes from 1 to `--patches`, at each thread count of `--sweep-threads`;
- processes: 2 worker processes x 1 thread, as the pipeline runs;
- training: training steps per second of the recipe's batch size.

With --compare REF, runs this script on git revision REF and on the working tree, interleaved, and
prints the ms per patch of the engines and sweep sections side by side with their ratio
(`bench/revisions.py`).
"""

from __future__ import annotations

import argparse
import statistics
import time
from pathlib import Path

import numpy as np
import revisions
import torch
from torch.utils.flop_counter import FlopCounterMode

from cadpu import engines
from cadpu.data import DataSpec, build_patches
from cadpu.inference import Upsampler
from cadpu.train import Recipe, Trainer
from cadpu.weights import DEFAULT_WEIGHTS


def matmul_peak(threads: int, size: int = 1024, repeats: int = 5) -> float:
    """Median float32 GFLOP/s of a size x size matrix product with `threads` threads."""
    torch.set_num_threads(threads)
    a, b = torch.randn(size, size), torch.randn(size, size)
    a @ b
    rates = []
    for _ in range(repeats):
        started = time.perf_counter()
        for _ in range(4):
            a @ b
        rates.append(4 * 2 * size**3 / (time.perf_counter() - started) / 1e9)
    return statistics.median(rates)


def patches(count: int, seed: int = 0) -> np.ndarray:
    """Realistic normalised test patches (uniform and scan-line inputs from synthetic meshes)."""
    data = build_patches(DataSpec(meshes=max(1, count // 8), patches_per_mesh=8, first_seed=2_000_000 + seed))
    return data.inputs[:count]


def _worker_throughput(args: tuple[str, np.ndarray, int, int]) -> float:
    """In a separate process: seconds to upsample `data` `repeats` times with 1 thread."""
    weights, data, batch, repeats = args
    torch.set_num_threads(1)
    upsampler = Upsampler(weights, device="cpu", batch_size=batch, oversample=1)
    upsampler.upsample_patches(data[:batch])
    started = time.perf_counter()
    for _ in range(repeats):
        upsampler.upsample_patches(data)
    return time.perf_counter() - started


def two_process_ms_per_patch(weights: Path, data: np.ndarray, batch: int, repeats: int) -> float:
    """Machine throughput as the pipeline uses it (2 worker processes x 1 thread): ms per patch."""
    import multiprocessing

    with multiprocessing.get_context("spawn").Pool(2) as pool:
        seconds = pool.map(_worker_throughput, [(str(weights), data, batch, repeats)] * 2)
    # both loops run side by side (model loading is outside the timed part): the slower bounds it
    return max(seconds) / (2 * repeats * len(data)) * 1000


#: (label, engine, EdgeConv layout) of every path the engines section compares; eager first.
#: Layout None: the engine's own default (neighbour-major in torch, point-major when exported).
PATHS = [("eager", "eager", "neighbour-major"), ("eager point-major", "eager", "point-major"),
         *[(name, name, None) for name in engines.ENGINES if name != "eager"],
         ("onnxruntime neighbour-major", "onnxruntime", "neighbour-major")]


def compare_engines(weights: Path, data: np.ndarray, threads: int, batch: int, repeats: int, flops: float,
                    only: set[str] | None = None) -> dict[str, float]:
    """Print every path of PATHS (or those labelled in `only`, and eager) side by side, `repeats`
    interleaved runs over `data` each; the matmul peak is measured once per round, between them.
    Returns the median ms per patch by path label."""
    torch.set_num_threads(threads)
    runs: dict[str, tuple[Upsampler, float]] = {}
    for label, engine, layout in PATHS:
        if only and label not in only and label != "eager":
            continue
        if not engines.available(engine):
            print(f"{label}: not installed, skipped")
            continue
        started = time.perf_counter()
        upsampler = Upsampler(weights, device="cpu", batch_size=batch, engine=engine, layout=layout, oversample=1)
        upsampler.upsample_patches(data[:batch])  # compiles, where the engine compiles
        runs[label] = upsampler, time.perf_counter() - started
    times: dict[str, list[float]] = {label: [] for label in runs}
    outputs, peaks = {}, []
    for repeat in range(repeats):
        peaks.append(matmul_peak(threads, repeats=1))
        labels = list(runs)
        for label in labels[repeat % len(labels):] + labels[:repeat % len(labels)]:  # rotate the order
            started = time.perf_counter()
            outputs[label] = runs[label][0].upsample_patches(data)
            times[label].append((time.perf_counter() - started) / len(data) * 1000)
    reference_points, reference_parents = outputs["eager"]
    peak = statistics.median(peaks)
    print(f"{threads} thread(s), batch {batch}, {len(data)} patches, medians of {repeats} interleaved runs; "
          f"matmul peak {peak:.1f} GFLOP/s (median of one per round, range {min(peaks):.1f}-{max(peaks):.1f})")
    print(f"{'path':<24} {'setup s':>7} {'ms/patch':>8} {'% peak':>6} {'max dev':>9} {'mean dev':>9} parents")
    figures = {}
    for label, (upsampler, setup) in runs.items():
        ms = figures[f"{label} ms/patch"] = statistics.median(times[label])
        points, parents = outputs[label]
        deviation = np.linalg.norm(points - reference_points, axis=-1)
        rate = flops / (ms / 1000) / 1e9
        print(f"{label:<24} {setup:>7.1f} {ms:>8.2f} {100 * rate / peak:>5.1f}% {deviation.max():>9.2e} "
              f"{deviation.mean():>9.2e} {'same' if np.array_equal(parents, reference_parents) else 'DIFFERENT'}")
    return figures


def flops_per_patch(upsampler: Upsampler, sample: np.ndarray) -> float:
    counter = FlopCounterMode(display=False)
    with counter, torch.inference_mode():
        upsampler.generator(torch.from_numpy(sample))
    return counter.get_total_flops() / len(sample)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--weights", type=Path, default=DEFAULT_WEIGHTS)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--train-steps", type=int, default=5, help="steps of the training section")
    parser.add_argument("--sections", default="engines,sweep,processes,training",
                        help="comma-separated: engines, sweep, processes, training")
    parser.add_argument("--threads", type=int, default=1, help="threads of the engines section")
    parser.add_argument("--batch", type=int, default=4, help="patches per forward pass, engines section")
    parser.add_argument("--patches", type=int, default=64)
    parser.add_argument("--sweep-threads", default="1,2", help="comma-separated thread counts of the sweep section")
    parser.add_argument("--paths", help="comma-separated labels of the engines section (default: all)")
    revisions.add_arguments(parser)
    args = revisions.parse_or_compare(parser, Path(__file__))
    if args is None:
        return
    sections = set(args.sections.split(","))
    if args.repeats < 1 or args.train_steps < 1 or not sections <= {"engines", "sweep", "processes", "training"}:
        parser.error("--repeats and --train-steps must be at least 1, --sections from engines, sweep, "
                     "processes, training")
    data = patches(args.patches)
    print(f"matmul peak (float32, 1024^2): 1 thread {matmul_peak(1):.1f} GFLOP/s, "
          f"2 threads {matmul_peak(2):.1f} GFLOP/s")
    upsampler = Upsampler(args.weights, device="cpu", engine="eager", oversample=1)
    flops = flops_per_patch(upsampler, data[:8])
    print(f"FLOPs per patch (counted matmuls/convs): {flops / 1e6:.1f} MFLOP")
    figures: dict[str, float] = {}
    if "engines" in sections:
        figures |= compare_engines(args.weights, data, args.threads, args.batch, args.repeats, flops,
                                   set(args.paths.split(",")) if args.paths else None)
    if "sweep" in sections:
        figures |= print_sweep(upsampler, data, flops, args.repeats,
                               tuple(int(t) for t in args.sweep_threads.split(",")))
    if "processes" in sections:
        peak = matmul_peak(2)
        for batch in (4, 8, 16):
            ms = statistics.median(two_process_ms_per_patch(args.weights, data, batch, 2) for _ in range(3))
            rate = flops / (ms / 1000) / 1e9
            print(f"2 processes x 1 thread, batch {batch}: {ms:.2f} ms/patch (whole machine), "
                  f"{rate:.1f} GFLOP/s, {100 * rate / peak:.1f}% of the 2-thread peak")
    if "training" in sections:
        print_training_speed(args.train_steps)
    if args.json:
        revisions.emit(figures)


def print_sweep(upsampler: Upsampler, data: np.ndarray, flops: float, repeats: int,
                threads_list: tuple[int, ...] = (1, 2)) -> dict[str, float]:
    """Eager at 1 and 2 threads and batches of 1 to a whole frame's patches (up to `--patches`):
    median ms per patch and share of the peak. Batching the patches of several frames together
    pays only if batches beyond one frame's (about 200 patches) are faster per patch. Returns the
    median ms per patch by "T thread(s), batch B"."""
    print(f"{'threads':>7} {'batch':>5} {'ms/patch':>9} {'GFLOP/s':>8} {'% of peak':>9}")
    figures = {}
    for threads in threads_list:
        peak = matmul_peak(threads)
        torch.set_num_threads(threads)
        for batch in [b for b in (1, 4, 8, 16, 32, 64, 128, 256) if b <= len(data)]:
            upsampler.batch_size = batch
            upsampler.upsample_patches(data[:batch])
            times = []
            for _ in range(repeats):
                started = time.perf_counter()
                upsampler.upsample_patches(data)
                times.append((time.perf_counter() - started) / len(data) * 1000)
            ms = figures[f"{threads} thread(s), batch {batch} ms/patch"] = statistics.median(times)
            rate = flops / (ms / 1000) / 1e9
            print(f"{threads:>7} {batch:>5} {ms:>9.2f} {rate:>8.1f} {100 * rate / peak:>8.1f}%")
    return figures


def print_training_speed(steps: int) -> None:
    """Training steps per second of configs/train.yaml's batch size, 2 threads, GAN terms on."""
    torch.set_num_threads(2)
    recipe = Recipe.from_yaml(Path(__file__).resolve().parents[1] / "configs" / "train.yaml",
                              {"data": {"meshes": 2, "patches_per_mesh": 8}, "adversarial_from": 0})
    trainer = Trainer(recipe, build_patches(recipe.data), torch.device("cpu"))
    trainer.step()
    started = time.perf_counter()
    for _ in range(steps):
        trainer.step()
    elapsed = (time.perf_counter() - started) / steps
    print(f"training (recipe batch {recipe.batch_size}, 2 threads, with GAN terms): {1 / elapsed:.2f} steps/s "
          f"({elapsed:.2f} s/step)")


if __name__ == "__main__":
    main()
