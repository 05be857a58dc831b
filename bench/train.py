"""Training throughput: patch samples per second per core of one training step of each recipe, by phase.

    python bench/train.py [--recipes configs/train.yaml configs/train_lidar.yaml] [--steps 3]
                          [--repeats 5] [--compare REV]

Each code version runs in its own worker process (`--compare REV` adds git revision REV's cadpu,
exported with `git archive`, beside the working tree's); the parent alternates the workers, each
timing `--steps` steps per repeat, and prints medians over the repeats and the ratio. Both start
from the recipe's shipped weights (a trained state: the EMD assignment's cost depends on it) with
the discriminator active, on the same small patch set built from the recipe's data kind, with the
recipe's thread count. Phases are timed by wrapping the functions Trainer.step calls, so both
versions are measured the same way: data (Trainer.batch), forward (Generator.forward), emd
(losses.emd and the shared distances), regularizer, backward (the generator's), discriminator
(its forwards and its backward), other (optimiser steps, schedulers). The working tree's worker
also prints the auction EMD's gap to the exact assignment on the batches it trained on.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PHASES = ("data", "forward", "emd", "regularizer", "backward", "discriminator", "other")
#: Shipped weights each recipe's worker starts from, by the recipe's data kind.
START_WEIGHTS = {"meshes": "cadpu_r4", "streets": "cadpu_r4_lidar"}


def _instrument(cadpu_train, losses, network, totals: dict[str, float]) -> None:
    """Wrap the functions Trainer.step calls so their seconds add up in `totals` by phase."""
    import torch

    def timed(phase, function):
        def wrapper(*args, **kwargs):
            started = time.perf_counter()
            try:
                return function(*args, **kwargs)
            finally:
                totals[phase] += time.perf_counter() - started
        return wrapper

    cadpu_train.Trainer.batch = timed("data", cadpu_train.Trainer.batch)
    network.Generator.forward = timed("forward", network.Generator.forward)
    network.Discriminator.forward = timed("discriminator", network.Discriminator.forward)
    losses.emd = timed("emd", losses.emd)
    if hasattr(losses, "pred_target_distances"):
        losses.pred_target_distances = timed("emd", losses.pred_target_distances)
    losses.curvature_regularizer = timed("regularizer", losses.curvature_regularizer)
    original_backward = torch.Tensor.backward
    calls = {"n": 0}

    def backward(self, *args, **kwargs):
        phase = "backward" if calls["n"] % 2 == 0 else "discriminator"  # G's first, then D's
        calls["n"] += 1
        started = time.perf_counter()
        try:
            return original_backward(self, *args, **kwargs)
        finally:
            totals[phase] += time.perf_counter() - started
    torch.Tensor.backward = backward


def worker(recipe_path: Path, patches_path: Path, gap: bool) -> None:
    """Serve timing requests on stdin ("STEPS" per line) for one recipe with the importable cadpu;
    answer each with one JSON line of seconds per phase and samples."""
    import numpy as np
    import torch

    from cadpu import losses, network
    from cadpu import train as cadpu_train
    from cadpu.data import PatchSet

    recipe = cadpu_train.Recipe.from_yaml(recipe_path)
    kind = "streets" if recipe.data.streets else "meshes"
    # the trainer's output folder (it writes nothing there in these steps), removed at the end
    with tempfile.TemporaryDirectory(prefix="bench-train-") as scratch:
        recipe = dataclasses.replace(recipe, init_weights=START_WEIGHTS[kind], output=scratch, checkpoint=None)
        torch.set_num_threads(recipe.threads or 1)
        with np.load(patches_path) as saved:
            patches = PatchSet(saved["inputs"], saved["truth"], saved["truth_normals"], saved["scanline"])
        trainer = cadpu_train.Trainer(recipe, patches, torch.device("cpu"))
        trainer.step_count = recipe.adversarial_from  # the discriminator trains too
        trainer.step()  # compile and warm up
        totals = dict.fromkeys(PHASES, 0.0)
        _instrument(cadpu_train, losses, network, totals)
        for line in sys.stdin:
            steps = int(line)
            for key in totals:
                totals[key] = 0.0
            started = time.perf_counter()
            for _ in range(steps):
                trainer.step()
            wall = time.perf_counter() - started
            totals["other"] = wall - sum(v for k, v in totals.items() if k != "other")
            print(json.dumps({"wall": wall, "samples": steps * recipe.batch_size,
                              "threads": torch.get_num_threads(), "phases": totals}), flush=True)
        if gap:
            print(json.dumps({"gap": _gaps(trainer, recipe)}), flush=True)


def _gaps(trainer, recipe, batches: int = 3) -> list[list[float]]:
    """Per item of `batches` fresh training batches: [exact EMD, auction EMD] of the current generator."""
    import torch

    from cadpu import losses
    from cadpu.assignment import matched_cost

    rows = []
    for _ in range(batches):
        inputs, truth, _ = trainer.batch()
        with torch.no_grad():
            pred, _ = trainer.generator(inputs, generator=trainer.sampler)
        cost = losses.pred_target_distances(pred, truth)
        exact = matched_cost(cost, losses.assignment(pred, truth, 0.0))
        approx = matched_cost(cost, losses.assignment(pred, truth, recipe.emd_epsilon or 1e-4))
        rows += [[float(e), float(a)] for e, a in zip(exact, approx)]
    return rows


def _patches(recipe_path: Path, out: Path) -> None:
    """A small patch set of the recipe's data kind (4 meshes or 1 street), saved as npz."""
    import numpy as np

    from cadpu.data import build_patches
    from cadpu.train import Recipe

    spec = Recipe.from_yaml(recipe_path).data
    spec = dataclasses.replace(spec, meshes=min(spec.meshes, 4), streets=min(spec.streets, 1))
    np.savez(out, **dataclasses.asdict(build_patches(spec)))


def _spawn(code_root: Path, recipe: Path, patches: Path, gap: bool) -> subprocess.Popen:
    command = [sys.executable, str(Path(__file__).resolve()), "--worker", str(recipe), "--patches", str(patches)]
    if gap:
        command.append("--gap")
    env = {"PYTHONPATH": str(code_root), "PATH": "/usr/bin:/bin", "HOME": str(Path.home())}
    return subprocess.Popen(command, cwd=code_root, env=env, stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                            text=True)


def bench(recipe: Path, versions: dict[str, Path], steps: int, repeats: int, scratch: Path) -> None:
    """Time `recipe` with every version's cadpu, interleaved; print medians, ratios and the gap."""
    patches = scratch / f"{recipe.stem}.npz"
    _patches(recipe, patches)
    workers = {name: _spawn(root, recipe.resolve(), patches, name == "tree") for name, root in versions.items()}
    results: dict[str, list[dict]] = {name: [] for name in versions}
    for _ in range(repeats):
        for name, process in workers.items():
            process.stdin.write(f"{steps}\n")
            process.stdin.flush()
            results[name].append(json.loads(process.stdout.readline()))
    gaps = None
    for name, process in workers.items():
        process.stdin.close()
        tail = process.stdout.read().strip()
        process.wait()
        if name == "tree" and tail:
            gaps = json.loads(tail.splitlines()[-1])["gap"]
    print(f"\n{recipe}: {steps} steps x {repeats} repeats per version, medians (ms per step)")
    print(f"{'version':>10} " + " ".join(f"{p:>13}" for p in PHASES) + f" {'step':>8} {'samples/s/core':>15}")
    rates = {}
    for name, runs in results.items():
        per_step = {p: statistics.median(r["phases"][p] for r in runs) / steps * 1e3 for p in PHASES}
        rate = statistics.median(r["samples"] / r["wall"] / r["threads"] for r in runs)
        rates[name] = rate
        wall = statistics.median(r["wall"] for r in runs) / steps * 1e3
        print(f"{name:>10} " + " ".join(f"{per_step[p]:13.1f}" for p in PHASES) + f" {wall:8.0f} {rate:15.2f}")
    for name in versions:
        if name != "tree":
            print(f"throughput ratio tree / {name}: {rates['tree'] / rates[name]:.2f}x")
    if gaps:
        relative = [(a - e) / e for e, a in gaps]
        print(f"auction EMD gap to exact on {len(gaps)} training patches: mean {statistics.mean(relative):.5%}, "
              f"max {max(relative):.5%} (exact EMD mean {statistics.mean(e for e, _ in gaps):.5f})")


def main() -> None:
    """CLI; see the module docstring."""
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--recipes", nargs="+", type=Path,
                        default=[ROOT / "configs/train.yaml", ROOT / "configs/train_lidar.yaml"])
    parser.add_argument("--steps", type=int, default=3)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--compare", metavar="REV", default=None, help="git revision to time beside the tree")
    parser.add_argument("--worker", type=Path, help=argparse.SUPPRESS)
    parser.add_argument("--patches", type=Path, help=argparse.SUPPRESS)
    parser.add_argument("--gap", action="store_true", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.worker:
        worker(args.worker, args.patches, args.gap)
        return
    with tempfile.TemporaryDirectory(prefix="bench-train-") as folder:
        scratch = Path(folder)
        versions = {"tree": ROOT}
        if args.compare:
            export = scratch / "compare"
            export.mkdir()
            archive = subprocess.run(["git", "archive", args.compare, "cadpu"], cwd=ROOT, check=True,
                                     capture_output=True).stdout
            subprocess.run(["tar", "-x", "-C", str(export)], input=archive, check=True)
            versions[args.compare] = export
        for recipe in args.recipes:
            bench(recipe, versions, args.steps, args.repeats, scratch)


if __name__ == "__main__":
    main()
