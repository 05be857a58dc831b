"""CAD-PU on a CUDA GPU: ms per patch and peak GPU memory by batch size, deviation from the CPU,
and what the 3x3 eigen-decompositions of one batch cost (a check for a machine with CUDA).

    python bench/cuda_speed.py [--weights NAME] [--patches 512] [--repeats 5]

Prints one line per batch size: median ms per patch over `--repeats` passes over `--patches`
realistic patches (bench/inference.py's), the peak memory the CUDA allocator reserved, and the
largest distance of the first 32 patches' points from the CPU's (batch 4), with whether their
parents are identical. Then the workspace `torch.linalg.eigh` (cuSOLVER) reserves for the 16,384
matrices of 64 patches, against `cadpu.geometry.jacobi_eigh_3x3`, which the torch path uses.
"""

from __future__ import annotations

import argparse
import statistics
import time

import numpy as np
import torch

from cadpu.geometry import jacobi_eigh_3x3
from cadpu.inference import Upsampler

from inference import patches

BATCHES = (16, 64, 128, 256, 512)


def _peak_reserved_above(base: int) -> float:
    """MiB the CUDA allocator reserved at its peak above `base` bytes."""
    torch.cuda.synchronize()
    return (torch.cuda.max_memory_reserved() - base) / 2**20


def eigen_decompositions(count: int = 16_384) -> None:
    """Print the peak memory and time of both eigen-decompositions of `count` 3x3 covariances."""
    seeded = torch.Generator(device="cuda").manual_seed(0)
    a = torch.randn(count, 3, 3, dtype=torch.float64, device="cuda", generator=seeded)
    covariances = a @ a.transpose(-1, -2)
    for name, solve in (("torch.linalg.eigh (cuSOLVER)", torch.linalg.eigh), ("jacobi_eigh_3x3", jacobi_eigh_3x3)):
        solve(covariances)
        torch.cuda.empty_cache()
        torch.cuda.reset_peak_memory_stats()
        base = torch.cuda.memory_reserved()
        start = time.perf_counter()
        solve(covariances)
        peak = _peak_reserved_above(base)
        print(f"{name} of {count:,} 3x3 float64 matrices: {1e3 * (time.perf_counter() - start):.2f} ms, "
              f"peak reserved {peak:,.0f} MiB above its inputs")


def batch_sweep(weights: str, count: int, repeats: int) -> None:
    """Print ms per patch, peak memory and deviation from the CPU for each of BATCHES."""
    data = patches(count)
    reference, reference_parents = Upsampler(weights, device="cpu", batch_size=4).upsample_patches(data[:32])
    for batch in BATCHES:
        torch.cuda.empty_cache()
        torch.cuda.reset_peak_memory_stats()
        upsampler = Upsampler(weights, device="cuda", batch_size=batch)
        upsampler.upsample_patches(data[:batch])
        seconds = []
        for _ in range(repeats):
            torch.cuda.synchronize()
            start = time.perf_counter()
            upsampler.upsample_patches(data)
            torch.cuda.synchronize()
            seconds.append(time.perf_counter() - start)
        peak = _peak_reserved_above(0)
        points, parents = upsampler.upsample_patches(data[:32])
        print(f"batch {batch:3d}: {1e3 * statistics.median(seconds) / len(data):.3f} ms/patch, peak reserved "
              f"{peak:,.0f} MiB; against the CPU: largest distance {np.abs(points - reference).max():.2e}, "
              f"parents identical {np.array_equal(parents, reference_parents)}", flush=True)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--weights", default="cadpu_r4_lidar_alpha1")
    parser.add_argument("--patches", type=int, default=512)
    parser.add_argument("--repeats", type=int, default=5)
    args = parser.parse_args()
    if not torch.cuda.is_available():
        raise SystemExit("bench/cuda_speed.py: this machine has no CUDA device")
    print(f"device: {torch.cuda.get_device_name()}, torch {torch.__version__}")
    batch_sweep(args.weights, max(args.patches, max(BATCHES)), args.repeats)
    eigen_decompositions()


if __name__ == "__main__":
    main()
