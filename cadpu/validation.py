"""Scoring a generator on held-out data while it trains, and keeping its best weights.

`cadpu.train.train` takes a `Validation`: every `every` steps (and at step 0, the starting weights)
it scores the generator with the validation's `scorer` (lower is better), appends the score to
`<output>/validation.csv`, and, with `keep_best`, remembers the weights of the best score so far;
those are the weights the run writes. That is early stopping on data the optimiser never saw:
what a fine-tuning run on a handful of real scans needs, since it can overfit them. A scorer must
be deterministic (fixed random sources), so that two scores differ only through the weights:
`PatchChamfer` scores held-out training pairs; `pipeline.finetune` scores whole held-out scans.
"""

from __future__ import annotations

import copy
import csv
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from .data import PatchSet
from .metrics import chamfer_distance
from .network import Generator

VALIDATION_COLUMNS = ("step", "score", "best_step")


def pair_chamfers(outputs: np.ndarray, truth: np.ndarray) -> list[float]:
    """`cadpu.metrics.chamfer_distance` of each output patch (B, M, 3) to its truth (B, M*, 3)."""
    return [chamfer_distance(o, t) for o, t in zip(outputs, truth)]


@torch.no_grad()
def generated(generator: Generator, inputs: np.ndarray, batch_size: int = 16, seed: int = 0) -> np.ndarray:
    """The generator's (eval mode, left so) outputs (P, r * 256, 3) for input patches (P, 256, 3),
    the expansion draws from a source seeded with `seed`: deterministic for fixed weights."""
    device = next(generator.parameters()).device
    sampler = torch.Generator(device=device).manual_seed(seed)
    generator.eval()
    outputs = [generator(torch.from_numpy(inputs[start:start + batch_size]).to(device), generator=sampler)[0].cpu().numpy()
               for start in range(0, len(inputs), batch_size)]
    return np.concatenate(outputs)


def heldout_chamfer(generator: Generator, patches: PatchSet, batch_size: int = 16, seed: int = 0) -> float:
    """Mean Chamfer distance (`cadpu.metrics.chamfer_distance`) between generated and true points.

    Chamfer, not the training EMD: it is what the scan evaluation scores, and a k-d tree query
    costs milliseconds per patch where an assignment of 1,024 points costs a quarter of a second.

    Args:
        generator: the network, scored in eval mode (left in eval mode; training steps switch back).
        patches: held-out pairs. batch_size: patches per forward pass. seed: the expansion draws'
            random source.

    Returns:
        The mean over patches, in the patches' normalised units (unit sphere of the input).
    """
    if len(patches) == 0:
        raise ValueError("heldout_chamfer: the held-out set is empty")
    return float(np.mean(pair_chamfers(generated(generator, patches.inputs, batch_size, seed), patches.truth)))


def snapped_chamfers(outputs: np.ndarray, patches: PatchSet, batch_size: int = 64) -> float:
    """Mean `cadpu.losses.snapped_chamfer` of output patches (P, M, 3) against scan pairs with
    their frames, unaugmented: what `objective: snapped_chamfer` trains, in metres over the patch
    radius, over the patches with rings between the input's.

    Raises:
        ValueError: the set is empty or has no frames (pairs of meshes).
    """
    from .losses import snapped_chamfers_per_patch

    frames = patches.frames
    if len(patches) == 0 or frames is None:
        raise ValueError("snapped_chamfers: the held-out set is empty or has no frames")
    values = []
    for start in range(0, len(patches), batch_size):
        part = slice(start, start + batch_size)
        count = len(outputs[part])
        arrays = (outputs[part], patches.truth[part], np.tile(np.eye(3, dtype=np.float32), (count, 1, 1)),
                  np.ones(count, np.float32), *(array[part] for array in frames.arrays()))
        with torch.no_grad():
            values.append(snapped_chamfers_per_patch(*(torch.from_numpy(np.ascontiguousarray(a)) for a in arrays)))
    return float(torch.cat(values).mean()) if sum(len(v) for v in values) else 0.0


def heldout_snapped_chamfer(generator: Generator, patches: PatchSet, batch_size: int = 16, seed: int = 0) -> float:
    """`snapped_chamfers` of the generator's outputs (eval mode, expansion draws seeded by `seed`)."""
    return snapped_chamfers(generated(generator, patches.inputs, batch_size, seed), patches)


@dataclass(frozen=True)
class PatchChamfer:
    """A scorer: `heldout_chamfer` of the generator on fixed held-out pairs."""

    patches: PatchSet

    def __call__(self, generator: Generator) -> float:
        return heldout_chamfer(generator, self.patches)


@dataclass
class Validation:
    """A held-out score followed during training (see the module docstring).

    Attributes:
        scorer: generator -> score, lower is better (e.g. `PatchChamfer`). every: score every
            this many steps (and at the last step). keep_best: the run writes the weights of the
            best score instead of the last step's.
    """

    scorer: Callable[[Generator], float]
    every: int = 100
    keep_best: bool = True
    best_score: float = field(default=float("inf"), init=False)
    best_step: int = field(default=-1, init=False)
    best_weights: dict[str, torch.Tensor] | None = field(default=None, init=False)

    def __post_init__(self) -> None:
        if self.every < 1:
            raise ValueError(f"validation: every must be >= 1, got {self.every}")

    def due(self, step: int, last_step: int) -> bool:
        return step % self.every == 0 or step == last_step

    def score(self, generator: Generator, step: int, log_path: Path) -> float:
        """Score `generator` at `step`, remember it if best, and append a row to `log_path`."""
        value = float(self.scorer(generator))
        if value < self.best_score:
            self.best_score, self.best_step = value, step
            self.best_weights = copy.deepcopy({k: v.detach().cpu() for k, v in generator.state_dict().items()})
        new = not log_path.is_file()
        with log_path.open("a", newline="") as handle:
            writer = csv.DictWriter(handle, VALIDATION_COLUMNS)
            if new:
                writer.writeheader()
            writer.writerow({"step": step, "score": f"{value:.6g}", "best_step": self.best_step})
        return value

    def state(self) -> dict:
        """What a checkpoint keeps so that a resumed run keeps the same best."""
        return {"best_score": self.best_score, "best_step": self.best_step, "best_weights": self.best_weights}

    def restore(self, state: dict | None) -> None:
        if state:
            self.best_score = float(state["best_score"])
            self.best_step = int(state["best_step"])
            self.best_weights = state["best_weights"]

    def weights_to_write(self, generator: Generator) -> Generator:
        """The generator to save: a copy holding the best weights when `keep_best` and a score exists."""
        if not self.keep_best or self.best_weights is None:
            return generator
        best = copy.deepcopy(generator).cpu()
        best.load_state_dict(self.best_weights)
        return best


def read_validation_log(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """Steps and held-out scores of a `validation.csv`, as two arrays (empty if the file is missing)."""
    if not Path(path).is_file():
        return np.zeros(0, dtype=np.int64), np.zeros(0)
    rows = list(csv.DictReader(Path(path).open()))
    return (np.array([int(r["step"]) for r in rows], dtype=np.int64),
            np.array([float(r["score"]) for r in rows]))
