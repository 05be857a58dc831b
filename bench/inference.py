"""CAD-PU speed on this CPU: ms per 256-point patch at r = 4, share of the matmul peak, training steps/s.

    python bench/inference.py [--weights cadpu/weights/cadpu_r4.pt] [--repeats 5]

Prints, for several batch sizes and thread counts, the median wall time per patch of batched
inference (no gradients), the FLOPs per patch (torch's FLOP counter) and the share of this
machine's measured float32 matrix-multiply peak that represents; then the training steps per
second of the recipe's batch size.
"""

from __future__ import annotations

import argparse
import statistics
import time
from pathlib import Path

import numpy as np
import torch
from torch.utils.flop_counter import FlopCounterMode

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
    upsampler = Upsampler(weights, device="cpu", batch_size=batch)
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


def flops_per_patch(upsampler: Upsampler, sample: np.ndarray) -> float:
    counter = FlopCounterMode(display=False)
    with counter, torch.inference_mode():
        upsampler.generator(torch.from_numpy(sample))
    return counter.get_total_flops() / len(sample)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--weights", type=Path, default=DEFAULT_WEIGHTS)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--train-steps", type=int, default=5, help="0 skips the training figure")
    args = parser.parse_args()
    if args.repeats < 1 or args.train_steps < 0:
        parser.error("--repeats must be at least 1 and --train-steps at least 0")
    data = patches(64)
    print(f"matmul peak (float32, 1024^2): 1 thread {matmul_peak(1):.1f} GFLOP/s, "
          f"2 threads {matmul_peak(2):.1f} GFLOP/s")
    upsampler = Upsampler(args.weights, device="cpu")
    flops = flops_per_patch(upsampler, data[:8])
    print(f"FLOPs per patch (counted matmuls/convs): {flops / 1e6:.1f} MFLOP")
    print(f"{'threads':>7} {'batch':>5} {'ms/patch':>9} {'GFLOP/s':>8} {'% of peak':>9}")
    for threads in (1, 2):
        peak = matmul_peak(threads)
        torch.set_num_threads(threads)
        for batch in (4, 8, 16, 32):
            upsampler.batch_size = batch
            upsampler.upsample_patches(data[:batch])
            times = []
            for _ in range(args.repeats):
                started = time.perf_counter()
                upsampler.upsample_patches(data)
                times.append((time.perf_counter() - started) / len(data) * 1000)
            ms = statistics.median(times)
            rate = flops / (ms / 1000) / 1e9
            print(f"{threads:>7} {batch:>5} {ms:>9.2f} {rate:>8.1f} {100 * rate / peak:>8.1f}%")
    peak = matmul_peak(2)
    for batch in (4, 8, 16):
        ms = statistics.median(two_process_ms_per_patch(args.weights, data, batch, 2) for _ in range(3))
        rate = flops / (ms / 1000) / 1e9
        print(f"2 processes x 1 thread, batch {batch}: {ms:.2f} ms/patch (whole machine), "
              f"{rate:.1f} GFLOP/s, {100 * rate / peak:.1f}% of the 2-thread peak")
    if args.train_steps:
        print_training_speed(args.train_steps)


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
