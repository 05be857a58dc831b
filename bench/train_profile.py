"""Where a training step's time goes, operator by operator: torch's profiler over a few steps of a
recipe from its shipped weights, the discriminator on, on a small patch set of the recipe's kind,
one thread (the costs behind `bench/train.py`'s phases; cadpu/MODEL_CARD.md, "Training throughput").

    python bench/train_profile.py [--recipe configs/train.yaml] [--steps 4] [--rows 25]

Prints the operators by self CPU time, grouped by input shape (the Numba kernels, outside torch,
do not appear; `bench/train.py` times them within its phases).
"""

from __future__ import annotations

import argparse
import dataclasses
import tempfile
from pathlib import Path

import torch
from torch.profiler import ProfilerActivity, profile

from cadpu.data import load_or_build
from cadpu.train import Recipe, Trainer

#: Shipped weights each recipe starts from, by its data kind (as `bench/train.py`).
START_WEIGHTS = {"meshes": "cadpu_r4", "streets": "cadpu_r4_lidar"}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--recipe", type=Path, default=Path("configs/train.yaml"))
    parser.add_argument("--steps", type=int, default=4)
    parser.add_argument("--rows", type=int, default=25)
    args = parser.parse_args()
    torch.set_num_threads(1)
    recipe = Recipe.from_yaml(args.recipe)
    kind = "streets" if recipe.data.streets else "meshes"
    small = dataclasses.replace(recipe.data, meshes=min(recipe.data.meshes, 4), streets=min(recipe.data.streets, 2))
    with tempfile.TemporaryDirectory(prefix="bench-train-profile-") as scratch:
        recipe = dataclasses.replace(recipe, data=small, init_weights=START_WEIGHTS[kind], adversarial_from=0,
                                     output=scratch, checkpoint=None, cache_dir=scratch)
        trainer = Trainer(recipe, load_or_build(recipe.data, Path(scratch), False), torch.device("cpu"))
        for _ in range(2):  # compile the kernels, warm the allocator
            trainer.step()
        with profile(activities=[ProfilerActivity.CPU], record_shapes=True) as profiled:
            for _ in range(args.steps):
                trainer.step()
    print(f"{args.recipe}: {args.steps} steps, batch {recipe.batch_size}, one thread")
    print(profiled.key_averages(group_by_input_shape=True).table(sort_by="self_cpu_time_total", row_limit=args.rows,
                                                                   max_name_column_width=28, max_shapes_column_width=60))


if __name__ == "__main__":
    main()
