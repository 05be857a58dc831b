"""Whether `Upsampler` output depends on the batch size or the device (a check for a machine with
CUDA; prints the largest difference from batch 4 on the CPU, per device and batch size).

    python bench/cuda_batches.py [--weights NAME] [--patches 12]
"""

from __future__ import annotations

import argparse

import numpy as np
import torch

from cadpu.inference import Upsampler
from cadpu.patches import partitioned_patches


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--weights", default="cadpu_r4")
    parser.add_argument("--patches", type=int, default=12, help="at least 6: the batch sizes compared split them")
    args = parser.parse_args()
    if args.patches < 6:
        parser.error("--patches must be at least 6 (batches of 1, 3 and 5 must each split them)")
    points = np.random.default_rng(0).normal(size=(256 * args.patches, 3)) * [4.0, 4.0, 1.0]
    patches = partitioned_patches(points, 256, 1.0).normalized[:args.patches]
    reference, parents = Upsampler(args.weights, device="cpu", batch_size=4).upsample_patches(patches)
    devices = ["cpu"] + (["cuda"] if torch.cuda.is_available() else [])
    if len(devices) == 1:
        print("no CUDA device: the CPU rows only (the check this script is for needs a GPU)")
    for device in devices:
        for batch in (1, 3, 4, 5):  # all below the patch count: each splits the patches its own way
            out, out_parents = Upsampler(args.weights, device=device, batch_size=batch).upsample_patches(patches)
            print(f"{device:5s} batch {batch:3d}: max |difference| {np.abs(out - reference).max():.2e}, "
                  f"parents equal {np.array_equal(out_parents, parents)}")


if __name__ == "__main__":
    main()
