"""Runs of the snapped objective side by side on one GPU, chosen by held-out scans' snapped Chamfer.

A lent GPU machine has no Open3D, so it cannot simulate streets: `pack` writes a recipe's training
pairs (with their frames, `cadpu.scan_data.PatchFrames`) and held-out pairs of every scene type
into two compact files a call can carry (float16 points, no normals: the regularizer, 0.15 against
1,024 times the snapped Chamfer, drops out with them); `sweep` trains one process per setting on
them and scores each run's generator on the held-out pairs every few steps, per scene type
(`cadpu.validation.snapped_chamfers`), keeping every scored generator:

    python bench/snapped_sweep.py pack configs/train_lidar_alpha1_snapped.yaml .sweep --patches 3000
    python bench/snapped_sweep.py sweep configs/train_lidar_alpha1_snapped.yaml .sweep OUT \\
        --runs "lr_generator=1e-4,batch_size=32" "lr_generator=3e-5,batch_size=32" --steps 3000 --every 500

(`pack --set data.scene_types=[urban,open]` changes the recipe's data; a run's settings are the
recipe's with its `--runs` entry's overrides.)

Prints one row per run and scoring step (held-out snapped Chamfer x 1e-3 per scene type, and their
mean), the starting weights first; OUT/NAME/step-NNNNNNN.pt are the generators scored.
"""

from __future__ import annotations

import argparse
import multiprocessing
import time
from dataclasses import asdict, fields, replace
from pathlib import Path

import numpy as np

from cadpu.data import PatchSet, load_or_build
from cadpu.scan_data import PatchFrames
from cadpu.train import Recipe, parse_overrides

#: Held-out street seeds: above every training recipe's and the evaluation scans' (5,000 on).
HELDOUT_SEED = 60_000


def _pack(patches: PatchSet, path: Path, types: np.ndarray, type_names: tuple[str, ...], exact: bool) -> None:
    """Pairs, their frames, (P,) indices into `type_names` (their scene types) into an .npz; points
    float16 unless `exact`."""
    points = np.float32 if exact else np.float16
    frames = patches.frames
    np.savez_compressed(path, inputs=patches.inputs.astype(points), truth=patches.truth.astype(points), types=types,
             type_names=np.array(type_names), **{f"frames_{f.name}": getattr(frames, f.name) for f in fields(PatchFrames)})


def _unpack(path: Path) -> tuple[PatchSet, np.ndarray, list[str]]:
    """(pairs with zero normals, their scene type indices, the scene types' names) of a `_pack` file."""
    with np.load(path) as saved:
        inputs, truth = saved["inputs"].astype(np.float32), saved["truth"].astype(np.float32)
        frames = PatchFrames(*(saved[f"frames_{f.name}"] for f in fields(PatchFrames)))
        pairs = PatchSet(inputs, truth, np.zeros_like(truth), np.ones(len(inputs), bool), frames)
        return pairs, saved["types"], [str(name) for name in saved["type_names"]]


def pack(recipe: Recipe, folder: Path, count: int, heldout_streets: int) -> None:
    """Write `count` of the recipe's pairs (evenly spaced) to folder/pairs.npz and the held-out
    pairs of each of its scene types to folder/heldout.npz."""
    folder.mkdir(parents=True, exist_ok=True)
    spec = recipe.data
    patches = load_or_build(spec, Path(recipe.cache_dir), workers=2)
    per_type = [load_or_build(replace(spec, streets=heldout_streets, scans_per_street=2,
                                      first_seed=HELDOUT_SEED + 10 * i, scene_types=(scene_type,)),
                              Path(recipe.cache_dir), workers=2)
                for i, scene_type in enumerate(spec.scene_types)]
    pick = np.linspace(0, len(patches) - 1, min(count, len(patches))).round().astype(int)
    chosen = patches.subset(pick)
    _pack(chosen, folder / "pairs.npz", np.full(len(pick), -1), (), exact=False)  # (types not kept: -1)
    heldout = PatchSet.concatenate(per_type)
    types = np.concatenate([np.full(len(p), i) for i, p in enumerate(per_type)])
    _pack(heldout, folder / "heldout.npz", types, spec.scene_types, exact=True)
    print(f"{len(pick)} training pairs, {len(heldout)} held-out pairs "
          f"({', '.join(f'{t} {len(p)}' for t, p in zip(spec.scene_types, per_type))})")


def _run(recipe: Recipe, folder: Path, out: Path, steps: int, every: int, seconds: float) -> None:
    import torch

    from cadpu.train import Trainer
    from cadpu.validation import generated, snapped_chamfers
    from cadpu.weights import save

    torch.set_num_threads(2)
    pairs, _, _ = _unpack(folder / "pairs.npz")
    heldout, types, type_names = _unpack(folder / "heldout.npz")
    device = torch.device("cuda" if torch.cuda.is_available() else "cpu")
    recipe = replace(recipe, beta=0.0)  # the packed pairs carry no normals for the regularizer
    trainer = Trainer(recipe, pairs, device)
    out.mkdir(parents=True, exist_ok=True)
    rows = out / "scores.csv"
    rows.write_text("step,samples_seen,seconds," + ",".join(type_names) + ",mean\n")
    started = time.perf_counter()

    def score() -> None:
        outputs = generated(trainer.generator, heldout.inputs, batch_size=64)
        values = [snapped_chamfers(outputs[types == i], heldout.subset(np.flatnonzero(types == i)))
                  for i in range(len(type_names))]
        with rows.open("a") as handle:
            handle.write(f"{trainer.step_count},{trainer.samples_at(trainer.step_count)},"
                         f"{time.perf_counter() - started:.0f}," + ",".join(f"{v:.6g}" for v in values)
                         + f",{np.mean(values):.6g}\n")
        save(trainer.generator, out / f"step-{trainer.step_count:07d}.pt",
             {"recipe": asdict(recipe), "steps": trainer.step_count,
              "samples_seen": trainer.samples_at(trainer.step_count), "init_weights": recipe.init_weights,
              "hardware": str(device)})
        trainer.generator.train()

    score()
    while trainer.step_count < steps and time.perf_counter() - started < seconds:
        trainer.step()
        if trainer.step_count % every == 0:
            score()
    if trainer.step_count % every:
        score()


def sweep(recipe_path: Path, folder: Path, out: Path, runs: list[str], steps: int, every: int, seconds: float) -> None:
    """Train one process per entry of `runs` (comma-separated KEY=VALUE recipe overrides of the
    recipe at `recipe_path`, so no value may hold a comma) on the packed pairs, side by side, and
    print every run's held-out scores."""
    context = multiprocessing.get_context("spawn")
    processes = []
    for setting in runs:
        changed = Recipe.from_yaml(recipe_path, parse_overrides(setting.split(",")) if setting else None)
        name = setting.replace(",", "_").replace("=", "") or "recipe"
        process = context.Process(target=_run, args=(changed, folder, out / name, steps, every, seconds))
        process.start()
        processes.append((name, process))
    for _, process in processes:
        process.join()
    for name, _ in processes:
        print(f"## {name}")
        print((out / name / "scores.csv").read_text())


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    commands = parser.add_subparsers(dest="command", required=True)
    packing = commands.add_parser("pack")
    packing.add_argument("recipe", type=Path)
    packing.add_argument("folder", type=Path)
    packing.add_argument("--patches", type=int, default=3000)
    packing.add_argument("--heldout-streets", type=int, default=1)
    packing.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="recipe override")
    sweeping = commands.add_parser("sweep")
    sweeping.add_argument("recipe", type=Path)
    sweeping.add_argument("folder", type=Path)
    sweeping.add_argument("out", type=Path)
    sweeping.add_argument("--runs", nargs="+", default=[""])
    sweeping.add_argument("--steps", type=int, default=3000)
    sweeping.add_argument("--every", type=int, default=500)
    sweeping.add_argument("--seconds", type=float, default=420.0)
    args = parser.parse_args()
    if args.command == "pack":
        pack(Recipe.from_yaml(args.recipe, parse_overrides(args.set)), args.folder, args.patches, args.heldout_streets)
    else:
        sweep(args.recipe, args.folder, args.out, args.runs, args.steps, args.every, args.seconds)


if __name__ == "__main__":
    main()
