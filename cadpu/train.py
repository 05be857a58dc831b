"""Training CAD-PU on synthetic patches from a YAML recipe (`python -m cadpu.train configs/train.yaml`).

Adam with the two time-scale update rule (generator 1e-3, discriminator 1e-4), both decayed by 0.7
every `decay_every` steps (or on a cosine to a share of their start: `Recipe.lr_schedule`);
generator loss = EMD (summed over points as equation (4), or per point: `Recipe.emd_reduction`)
+ beta * curvature regularizer + gamma / 2 * LSGAN (paper 4.2, `cadpu.losses.generator_objective`).
Writes to the run folder `log.csv` with every loss term per step, `losses.png`, and the final
generator weights with their checksum. The run's one checkpoint (the latest only) lives at
`Recipe.checkpoint` (default `<output>/checkpoint.pt`); long recipes keep it in the repository
(`cadpu/checkpoints/`) so that `python -m cadpu.train RECIPE --resume` continues a run across
sessions and machines.
"""

from __future__ import annotations

import argparse
import contextlib
import csv
import dataclasses
import functools
import math
import os
import pickle
import signal
import platform
import subprocess
import sys
import time
import types
import typing
import warnings
import zipfile
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
import yaml

from . import losses, yaml_text
from .assignment import largest_cost
from .curves import HeldoutCurves
from .data import (AUGMENTATIONS, INPUT_POINTS, TRUTH_POINTS, DataSpec, PatchSet, augment_with_transform,
                   load_or_build)
from .network import CODE_SPREAD, Discriminator, Generator
from .plots import plot_log
from .stopping import STOP_SIGNALS, StopRequest, TrainingStopped
from .validation import Validation
from .weights import WeightsError, check_weights_target, load_generator, save

EMD_REDUCTIONS = ("sum", "mean")
LR_SCHEDULES = ("step", "cosine")
#: The reconstruction term of the generator's objective: the paper's EMD (equation (4)), or the
#: Chamfer distance after ring snapping that the pipeline's output is scored by
#: (`cadpu.losses.snapped_chamfer`; scan patches only).
OBJECTIVES = ("emd", "snapped_chamfer")
LOG_COLUMNS = ("step", "seconds", "lr_g", "emd", "snapped_chamfer", "regularizer", "adversarial", "generator",
               "discriminator")


#: Recipe keys that define the network itself: a resumed run must keep them (`train`).
NETWORK_KEYS = ("ratio", "alpha", "frame_k", "offset_frame", "code_spread")


def read_yaml(text: str) -> object:
    """A recipe file's or a `--set` value's YAML (`cadpu.yaml_text`: exponent numbers are numbers,
    a key given twice is an error)."""
    return yaml_text.read_yaml(text)


#: The value kinds `_check_field_types` checks, and how its messages name them.
_FIELD_KINDS = {int: "an integer", float: "a number", str: "a string"}


def _check_field_types(instance: object, where: str) -> None:
    """ValueError naming the key when a field of a recipe dataclass holds a value of the wrong
    kind (`--set steps=abc`, a quoted number in YAML): ints must be ints, floats numbers, strings
    strings; None only where the field allows it."""
    hints = typing.get_type_hints(type(instance))
    for item in dataclasses.fields(instance):  # type: ignore[arg-type]
        value, hint = getattr(instance, item.name), hints[item.name]
        allowed = typing.get_args(hint) if typing.get_origin(hint) in (typing.Union, types.UnionType) else (hint,)
        if value is None and type(None) in allowed:
            continue
        for kind, name in _FIELD_KINDS.items():
            if kind in allowed:
                ok = isinstance(value, kind) if kind is not float else isinstance(value, (int, float))
                if not ok or isinstance(value, bool):
                    hint_text = ""
                    if kind is float and isinstance(value, str) and _parses_as_float(value):
                        # YAML reads nan and inf as text; a number in quotes is text too
                        hint_text = (" (YAML writes it .nan, .inf)" if not math.isfinite(float(value)) else
                                     " (a number in quotes is text: write it without them)")
                    raise ValueError(f"{where}: {item.name} must be {name}, got {value!r}{hint_text}")
                break


def _parses_as_float(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


@dataclass(frozen=True)
class Recipe:
    """A training recipe (YAML keys are the field names; `data` is a `DataSpec`).

    `emd_reduction` weighs the EMD against beta * R and the adversarial term: "sum" over the r * N
    points as equation (4) writes it, or "mean" per point (the regularizer ~1,000 times stronger);
    the shipped recipes use "mean", for the measured reason in cadpu/MODEL_CARD.md.
    """

    ratio: int = 4
    alpha: float = 0.5
    frame_k: int = 12
    offset_frame: str = "local"
    code_spread: float = CODE_SPREAD
    steps: int = 4000
    batch_size: int = 12
    lr_generator: float = 1e-3
    lr_discriminator: float = 1e-4
    #: Learning-rate schedule of both networks: "step" multiplies by `decay` every `decay_every`
    #: steps; "cosine" falls from the recipe's rate at step 0 to `lr_final_share` of it at `steps`,
    #: or, with `lr_cycle`, at every multiple of `lr_cycle` steps, rising back to the full rate after
    #: each (warm restarts: a run longer than a session then has an annealed generator to score and
    #: ship every `lr_cycle` steps, not only at its end).
    lr_schedule: str = "step"
    decay: float = 0.7
    decay_every: int = 1500
    lr_final_share: float = 0.01
    lr_cycle: int = 0
    beta: float = losses.BETA
    gamma: float = losses.GAMMA
    emd_reduction: str = "sum"
    #: The reconstruction term (`OBJECTIVES`); `emd_reduction` weighs it either way. With
    #: "snapped_chamfer" no assignment is solved and the log's emd column is empty (NaN).
    objective: str = "emd"
    #: The batches' augmentation (`cadpu.data.AUGMENTATIONS`): "full" (rotation, tilt, scale, input
    #: jitter) or "azimuth" (a rotation about the vertical alone).
    augmentation: str = "full"
    #: EMD assignment: 0 exact (scipy); > 0 the auction, at most this far above it (cadpu.assignment).
    emd_epsilon: float = 1e-4
    adversarial_from: int = 500
    checkpoint_every: int = 250
    seed: int = 0
    threads: int = 0
    data: DataSpec = field(default_factory=DataSpec)
    cache_dir: str = ".cache/cadpu"
    output: str = "runs/train/cadpu_r4"
    #: Weights (a shipped name or a path) the generator starts from instead of a random draw; their
    #: meta's samples_seen is carried into the new file's count.
    init_weights: str | None = None
    #: Where the run's single checkpoint lives; None is <output>/checkpoint.pt.
    checkpoint: str | None = None
    #: Held-out learning curves (`cadpu.curves`) every this many steps (0: none), on this many
    #: held-out meshes and streets, appended to curves_csv (None: <output>/curves.csv).
    curves_every: int = 0
    curves_meshes: int = 20
    curves_streets: int = 2
    curves_csv: str | None = None
    #: Write the generator every this many steps (0: never) to <output>/snapshots/step-NNNNNNN.pt,
    #: so that a run's weights can be chosen afterwards by held-out scores.
    snapshot_every: int = 0

    @property
    def checkpoint_path(self) -> Path:
        return Path(self.checkpoint) if self.checkpoint else Path(self.output) / "checkpoint.pt"

    @staticmethod
    def from_yaml(path: Path, overrides: dict | None = None) -> "Recipe":
        """Read a recipe, with `overrides` (recipe keys, or "data.KEY" for one key of its data);
        unknown keys raise ValueError naming them."""
        overrides = dict(overrides or {})
        data_overrides = {key.split(".", 1)[1]: overrides.pop(key) for key in list(overrides) if key.startswith("data.")}
        try:
            raw = read_yaml(Path(path).read_text()) or {}
        except yaml.YAMLError as error:
            raise ValueError(f"{path}: not valid YAML {yaml_text.describe_error(error)}") from None
        if not isinstance(raw, dict):
            raise ValueError(f"{path}: a recipe is a mapping of keys to values, got {type(raw).__name__}")
        known = {f.name for f in dataclasses.fields(Recipe)}
        for where, keys in ((str(path), raw), ("--set", overrides or {})):
            unknown = sorted(set(keys) - known)
            if unknown:
                raise ValueError(f"{where}: unknown recipe key(s) {unknown}; known: {sorted(known)}")
        data_known = {f.name for f in dataclasses.fields(DataSpec)}
        given = overrides.get("data")
        given_data = {**(given if isinstance(given, dict) else {}), **data_overrides}
        for where, keys in ((str(path), raw), ("--set", {**overrides, "data": given_data})):
            data = keys.get("data") or {}
            if isinstance(data, dict) and set(data) - data_known:  # (another kind is named by the type checks)
                raise ValueError(f"{where}: unknown data key(s) {sorted(set(data) - data_known)}")
        raw.update(overrides)
        data = raw.pop("data", {}) or {}
        if data_overrides and isinstance(data, dict):
            data = {**data, **data_overrides}
        return Recipe(**raw, data=DataSpec(**data))

    def __post_init__(self) -> None:
        _check_field_types(self, "recipe")
        _check_field_types(self.data, "recipe data")
        for name in ("steps", "batch_size", "checkpoint_every"):
            if getattr(self, name) < 1:
                raise ValueError(f"recipe: {name} must be at least 1, got {getattr(self, name)}")
        for name in ("adversarial_from", "threads", "curves_every", "snapshot_every"):
            if getattr(self, name) < 0:
                raise ValueError(f"recipe: {name} must be 0 or more, got {getattr(self, name)}")
        if self.emd_reduction not in EMD_REDUCTIONS:
            raise ValueError(f"recipe: emd_reduction must be one of {EMD_REDUCTIONS}, got {self.emd_reduction!r}")
        if self.augmentation not in AUGMENTATIONS:
            raise ValueError(f"recipe: augmentation must be one of {AUGMENTATIONS}, got {self.augmentation!r}")
        if self.objective not in OBJECTIVES:
            raise ValueError(f"recipe: objective must be one of {OBJECTIVES}, got {self.objective!r}")
        if not self.emd_epsilon >= 0:  # NaN too
            raise ValueError(f"recipe: emd_epsilon must be >= 0, got {self.emd_epsilon}")
        for name in ("lr_generator", "lr_discriminator"):  # torch's "Invalid learning rate" named neither
            if not getattr(self, name) > 0 or not math.isfinite(getattr(self, name)):
                raise ValueError(f"recipe: {name} must be a number above 0, got {getattr(self, name)}")
        if self.lr_schedule not in LR_SCHEDULES:
            raise ValueError(f"recipe: lr_schedule must be one of {LR_SCHEDULES}, got {self.lr_schedule!r}")
        if not 0 < self.lr_final_share <= 1:
            raise ValueError(f"recipe: lr_final_share must be in (0, 1], got {self.lr_final_share}")
        if self.decay_every < 1:  # a ZeroDivisionError in the schedule
            raise ValueError(f"recipe: decay_every must be at least 1 step, got {self.decay_every}")
        if not 0 < self.decay <= 1:  # a negative one trained with a negative rate: gradient ascent
            raise ValueError(f"recipe: decay must be in (0, 1], got {self.decay}")
        for name in ("beta", "gamma"):
            if not 0 <= getattr(self, name) < math.inf:  # NaN too: the loss NaN, the run diverged at step 1
                raise ValueError(f"recipe: {name} must be a finite number of 0 or more, got {getattr(self, name)}")
        if self.seed < 0:  # numpy's "expected non-negative integer" named no key
            raise ValueError(f"recipe: seed must be 0 or more, got {self.seed}")
        if self.lr_cycle < 0:
            raise ValueError(f"recipe: lr_cycle must be >= 0 steps (0: one cosine over the run), got {self.lr_cycle}")
        if self.ratio * INPUT_POINTS != TRUTH_POINTS:
            raise ValueError(f"recipe: ratio must be {TRUTH_POINTS // INPUT_POINTS}: the training pairs are "
                             f"{INPUT_POINTS} -> {TRUTH_POINTS} points (higher ratios run the network again, "
                             f"cadpu.inference), got {self.ratio}")
        if self.lr_cycle and self.lr_schedule != "cosine":
            raise ValueError(f"recipe: lr_cycle restarts the cosine schedule; with lr_schedule "
                             f"{self.lr_schedule!r} it would be ignored (set lr_schedule: cosine, or lr_cycle: 0)")

    def lr_factor(self, step: int) -> float:
        """The share of the initial learning rates that the step after `step` steps uses."""
        if self.lr_schedule == "cosine":
            if self.lr_cycle:  # the generator after each multiple of lr_cycle steps is annealed
                progress = (step % self.lr_cycle) / self.lr_cycle
            else:
                progress = min(step / max(self.steps, 1), 1.0)
            return self.lr_final_share + (1 - self.lr_final_share) * 0.5 * (1 + math.cos(math.pi * progress))
        return self.decay ** (step // self.decay_every)


#: Distances between generated and true points (in the patches' unit sphere, where they are at
#: most 2) beyond which a run has diverged; lower where the EMD's auction takes less
#: (`cadpu.assignment.largest_cost` of the recipe's epsilon).
DIVERGED_DISTANCE = 100.0
#: What `kitti-pu finetune` keeps beside its checkpoint, the run's scans and settings
#: (`pipeline.finetune`): how a checkpoint written before they recorded their command is told.
FINETUNE_RUN_RECORD = "data.json"


def read_checkpoint(checkpoint: Path, device: torch.device) -> object:
    """What a checkpoint file holds (torch.load; the file is the run's own, written by it).

    Raises:
        ValueError naming the file when it does not read (cut short, empty, not torch's format:
        torch's own errors were a traceback, and a text file's "invalid literal for int()" named
        no file), with what to do.
    """
    try:
        return torch.load(checkpoint, map_location=device, weights_only=False)
    except RuntimeError as error:
        if "PytorchStreamReader" not in str(error):  # out of memory, another torch's format: not damage
            raise
        damage: Exception = error
    except (EOFError, ValueError, pickle.UnpicklingError, zipfile.BadZipFile) as error:
        damage = error
    raise ValueError(f"{checkpoint}: not a readable checkpoint ({type(damage).__name__}: "
                     f"{str(damage).splitlines()[0] if str(damage) else 'no details'}); it was cut short or "
                     "damaged: delete it to start again (or restore it from a copy)") from None


class TrainingDiverged(ValueError):
    """A step's output, loss or updated weights are not finite: the run cannot go on (nothing of
    the step is kept)."""


class Trainer:
    """Holds the networks, optimisers and data of one run; `step()` does one update of both."""

    def __init__(self, recipe: Recipe, patches: PatchSet, device: torch.device) -> None:
        if len(patches) < recipe.batch_size:  # a batch draws distinct patches
            raise ValueError(f"recipe: batch_size {recipe.batch_size} is more than the {len(patches)} training patches")
        if recipe.objective == "snapped_chamfer" and patches.frames is None:
            raise ValueError("recipe: objective snapped_chamfer needs scan patches with their frames (data with "
                             "streets and no meshes)")
        self.recipe = recipe
        self.patches = patches
        self.device = device
        torch.manual_seed(recipe.seed)
        self.generator = Generator(ratio=recipe.ratio, alpha=recipe.alpha, frame_k=recipe.frame_k,
                                   offset_frame=recipe.offset_frame, code_spread=recipe.code_spread).to(device)
        #: Patch samples the starting weights had seen before this run (0 from a random start).
        self.samples_before = 0
        #: SHA-256 of the starting weights file ("" from a random start): recorded beside its name,
        #: which another file may take later.
        self.init_checksum = ""
        if recipe.init_weights:
            start, self.init_checksum, meta = load_generator(recipe.init_weights)
            if start.config != self.generator.config:
                raise ValueError(f"recipe: init_weights {recipe.init_weights} is a {start.config} network, "
                                 f"the recipe asks for {self.generator.config}")
            self.generator.load_state_dict(start.state_dict())
            self.samples_before = samples_seen(meta)
        self.discriminator = Discriminator().to(device)
        self.opt_g = torch.optim.Adam(self.generator.parameters(), lr=recipe.lr_generator, betas=(0.9, 0.999))
        self.opt_d = torch.optim.Adam(self.discriminator.parameters(), lr=recipe.lr_discriminator,
                                      betas=(0.5, 0.999))
        # The rate is a function of the step alone, so a run resumed under another schedule (or from
        # a checkpoint written by StepLR) continues on the recipe's curve.
        self.sched_g = torch.optim.lr_scheduler.LambdaLR(self.opt_g, recipe.lr_factor)
        self.sched_d = torch.optim.lr_scheduler.LambdaLR(self.opt_d, recipe.lr_factor)
        self.rng = np.random.default_rng(recipe.seed)
        self.sampler = torch.Generator(device=device).manual_seed(recipe.seed)
        self.step_count = 0

    def samples_at(self, step: int) -> int:
        """Patch samples the generator has seen after `step` steps of this run, those of the
        starting weights included."""
        return self.samples_before + step * self.recipe.batch_size

    def batch(self) -> tuple[torch.Tensor, ...]:
        """An augmented batch: (inputs, truth, truth normals), and with the snapped objective the
        tensors `losses.snapped_chamfer` takes after them (the augmentation, the patches' frames)."""
        index = self.rng.choice(len(self.patches), self.recipe.batch_size, replace=False)
        inputs, truth, normals, rotations, scales = augment_with_transform(
            self.patches.inputs[index], self.patches.truth[index], self.patches.truth_normals[index], self.rng,
            kind=self.recipe.augmentation)
        arrays = [inputs, truth, normals]
        if self.recipe.objective == "snapped_chamfer":
            arrays += [rotations, scales, *self.patches.frames.subset(index).arrays()]
        return tuple(torch.from_numpy(a).to(self.device) for a in arrays)

    def step(self, batch: tuple[torch.Tensor, ...] | None = None) -> dict[str, float]:
        """One generator and one discriminator update; returns every loss term.

        Args:
            batch: what `batch()` returns, to train on; None draws an augmented batch.
        """
        recipe = self.recipe
        inputs, truth, normals, *frames = batch if batch is not None else self.batch()
        self.generator.train()
        pred, _ = self.generator(inputs, generator=self.sampler)
        # an output of NaN, or so large that its distances overflow, which the assignment cannot take;
        # or far outside the patches' unit sphere, where the auction's prices stop rising. The
        # distances are checked by their largest alone: one pass (a check of each for NaN and inf
        # took five), and NaN or inf there is NaN or inf somewhere
        if not bool(torch.isfinite(truth).all()):  # the data's fault, not a divergence (a reviewer's find)
            raise ValueError(f"training step {self.step_count + 1}: the batch's truth points hold NaN or infinite "
                             "values; the patch data are damaged (delete the recipe's cache to build them again)")
        self._check_finite("the generator's output", pred)
        distances = losses.pred_target_distances(pred, truth)
        if not math.isfinite(farthest := float(distances.max())):  # finite points whose distances overflow
            raise TrainingDiverged(f"training diverged at step {self.step_count + 1}: the generator's points lie so "
                                   f"far from the truth that their distances overflow (a learning rate or loss weight "
                                   f"too large?); {self._what_stands()}")
        limit = min(DIVERGED_DISTANCE, largest_cost(recipe.emd_epsilon)) if recipe.emd_epsilon > 0 else DIVERGED_DISTANCE
        if farthest > limit:
            raise TrainingDiverged(f"training diverged at step {self.step_count + 1}: the generator's points lie up to "
                                   f"{farthest:.3g} from the truth, whose patches fit in the unit sphere (a learning "
                                   f"rate or loss weight too large?); {self._what_stands()}")
        if recipe.objective == "snapped_chamfer":
            if len(frames) != 7:
                raise ValueError("Trainer.step: the snapped objective needs the batch's augmentation and frames "
                                 "(what batch() returns)")
            emd = pred.new_full((), float("nan"))
            reconstruction = snapped = losses.snapped_chamfer(pred, truth, *frames)
        else:
            reconstruction = emd = losses.emd(pred, truth, recipe.emd_epsilon, distances)
            snapped = pred.new_full((), float("nan"))
        regularizer = losses.curvature_regularizer(pred, truth, normals, distances=distances)
        use_gan = self.step_count >= recipe.adversarial_from
        adversarial = losses.generator_adversarial(self._scores_for_generator(pred)) if use_gan else pred.new_zeros(())
        points = pred.shape[1] if recipe.emd_reduction == "sum" else 1
        total = losses.generator_objective(reconstruction, regularizer, adversarial, points, recipe.beta, recipe.gamma)
        self._check_finite("the generator's loss", total)
        self.opt_g.zero_grad(set_to_none=True)
        total.backward()
        self.opt_g.step()
        self._check_finite("a generator weight", *self.generator.parameters())
        self.sched_g.step()

        d_loss = pred.new_zeros(())
        if use_gan:
            d_loss = losses.discriminator_loss(self.discriminator(truth), self.discriminator(pred.detach()))
            self.opt_d.zero_grad(set_to_none=True)
            d_loss.backward()
            self.opt_d.step()
            self._check_finite("a discriminator weight", *self.discriminator.parameters())
        with warnings.catch_warnings():  # before the discriminator starts, its decay still follows the step
            warnings.filterwarnings("ignore", message="Detected call of `lr_scheduler.step")
            self.sched_d.step()
        self.step_count += 1
        return {"emd": emd.item(), "snapped_chamfer": snapped.item(), "regularizer": regularizer.item(),
                "adversarial": adversarial.item(),
                "generator": total.item(), "discriminator": d_loss.item(),
                "lr_g": self.opt_g.param_groups[0]["lr"]}  # the rate of the next step (a test holds it)

    def _check_finite(self, what: str, *tensors: torch.Tensor) -> None:
        """TrainingDiverged naming `what` and the step when a value of `tensors` is NaN or infinite:
        raised before anything of the step is logged or saved."""
        if not all(bool(torch.isfinite(t).all()) for t in tensors):
            raise TrainingDiverged(f"training diverged at step {self.step_count + 1}: {what} is NaN or infinite "
                                   f"(a learning rate or loss weight too large?); {self._what_stands()}")

    def _what_stands(self) -> str:
        """What a divergence leaves, for its message: the run's checkpoint when it has written one
        (it said so also where none existed: a researcher's trial)."""
        checkpoint = self.recipe.checkpoint_path
        if checkpoint.is_file():
            return f"nothing of this step is saved, the last checkpoint ({checkpoint}) stands"
        return "nothing of this step is saved, and no checkpoint was written before it"

    def _scores_for_generator(self, pred: torch.Tensor) -> torch.Tensor:
        """The discriminator's (B,) scores of `pred` for the generator's adversarial term, with
        gradients for `pred` only: the discriminator's own would be discarded before its update."""
        self.discriminator.requires_grad_(False)
        try:
            return self.discriminator(pred)
        finally:
            self.discriminator.requires_grad_(True)

    def state(self) -> dict:
        return {
            "step": self.step_count, "generator": self.generator.state_dict(),
            "discriminator": self.discriminator.state_dict(), "opt_g": self.opt_g.state_dict(),
            "opt_d": self.opt_d.state_dict(), "rng": self.rng.bit_generator.state,
            "sampler": self.sampler.get_state(),
        }

    def restore(self, state: dict) -> None:
        self.step_count = state["step"]
        for key in ("generator", "discriminator", "opt_g", "opt_d"):
            getattr(self, key).load_state_dict(state[key])
        for scheduler, optimizer in ((self.sched_g, self.opt_g), (self.sched_d, self.opt_d)):
            scheduler.last_epoch = self.step_count
            for group, initial in zip(optimizer.param_groups, scheduler.base_lrs):
                group["lr"] = initial * self.recipe.lr_factor(self.step_count)
        self.rng.bit_generator.state = state["rng"]
        try:
            self.sampler.set_state(state["sampler"])
        except RuntimeError:  # saved on another kind of device: its generator state has another form
            self.sampler.manual_seed(self.recipe.seed + self.step_count)


def recipe_changes(stored: dict | None, recipe: Recipe, checkpoint: Path) -> dict[str, list]:
    """What a resumed run changes in the recipe its checkpoint was saved with.

    A resumed run may change its schedule, loss weights, data or length (each such change is kept
    in the run's segments, so the weights file says what it was trained under), but not the
    network itself (`NETWORK_KEYS`): the weights would go on training as another network than
    the one the recipe names.

    Args:
        stored: the checkpoint's recipe (`dataclasses.asdict`; None in checkpoints from before it
            was saved). recipe: the recipe of this call. checkpoint: its path, for the error.

    Returns:
        {key: [checkpoint's value, this recipe's value]} for every top-level key that differs
        (`data` as a whole).

    Raises:
        ValueError naming the checkpoint and the key when a network key differs.
    """
    if stored is None:
        return {}
    current = dataclasses.asdict(recipe)
    # a data key added since the checkpoint was saved (e.g. scene_types) reads as its default there,
    # which is what the earlier version did: not a change
    if isinstance(stored.get("data"), dict):
        stored = {**stored, "data": {**dataclasses.asdict(DataSpec()), **stored["data"]}}
    changes = {key: [stored[key], value] for key, value in current.items()
               if key in stored and _plain(stored[key]) != _plain(value)}
    network = [key for key in NETWORK_KEYS if key in changes]
    if network:
        listed = ", ".join(f"{key} {changes[key][0]!r} (the recipe says {changes[key][1]!r})" for key in network)
        raise ValueError(f"{checkpoint}: the checkpoint's network has {listed}; a resumed run cannot change "
                         "the network: restore the value, or start a new run with another `checkpoint`")
    return changes


def _plain(value: object) -> object:
    """Lists for tuples, throughout, so a recipe compares equal to its own saved copy."""
    if isinstance(value, dict):
        return {key: _plain(item) for key, item in value.items()}
    if isinstance(value, (list, tuple)):
        return [_plain(item) for item in value]
    return value


def samples_seen(meta: dict) -> int:
    """Patch samples a weights file's generator was trained on, from its meta (written by `train`;
    files from before the count existed: steps x batch size of their recipe)."""
    if "samples_seen" in meta:
        return int(meta["samples_seen"])
    return int(meta.get("steps", 0)) * int(meta.get("recipe", {}).get("batch_size", 0))


def hardware() -> str:
    """A short description of where this process trains: the GPU when one is used, then the
    processor (its model where the system names it) and torch's threads."""
    cpu = f"cpu:{processor_name()} x{torch.get_num_threads()} threads"
    return f"cuda:{torch.cuda.get_device_name(0)}, {cpu}" if torch.cuda.is_available() else cpu


@functools.lru_cache(maxsize=1)
def processor_name() -> str:
    """The CPU's model name ("AMD EPYC 9R14 ..."): /proc/cpuinfo's on Linux, sysctl's on macOS,
    else what `platform` says (on Linux that was only "x86_64": a trial)."""
    try:
        with open("/proc/cpuinfo", encoding="utf-8", errors="replace") as info:
            for line in info:
                key, _, value = line.partition(":")
                if key.strip() in ("model name", "Model") and value.strip():
                    return value.strip()
    except OSError:
        pass
    if sys.platform == "darwin":
        with contextlib.suppress(OSError, subprocess.SubprocessError):
            named = subprocess.run(["sysctl", "-n", "machdep.cpu.brand_string"], capture_output=True, text=True,
                                   timeout=5).stdout.strip()
            if named:
                return named
    return platform.processor() or platform.machine()


def checkpoint_caller(state: dict, checkpoint: Path) -> str:
    """The command whose run wrote a checkpoint (`_save_checkpoint`'s `caller`). Checkpoints from
    before it was kept: "kitti-pu finetune" in a fine-tuning run's folder (its `data.json` beside
    the checkpoint), else "cadpu.train"."""
    if "caller" in state:
        return str(state["caller"])
    return "kitti-pu finetune" if (Path(checkpoint).parent / FINETUNE_RUN_RECORD).is_file() else "cadpu.train"


def resume_command(caller: str) -> str:
    """The command a user types to resume a run of `caller` ("python -m cadpu.train", "kitti-pu finetune")."""
    return caller if caller.startswith("kitti-pu") else f"python -m {caller}"


def _save_checkpoint(trainer: Trainer, path: Path, elapsed: float, segments: list[dict],
                     validation: Validation | None = None, caller: str = "cadpu.train") -> None:
    """Write the run's one checkpoint atomically, replacing the previous one: the networks, both
    optimisers' states, the random states, elapsed seconds, the list of training segments, the
    held-out best so far and the command whose run it is (`caller`, which alone may resume it)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    temporary = path.with_name(f".{path.name}.tmp")
    torch.save({**trainer.state(), "elapsed": elapsed, "samples_before": trainer.samples_before,
                "segments": segments, "recipe": dataclasses.asdict(trainer.recipe),
                "validation": validation.state() if validation is not None else None, "caller": caller}, temporary)
    os.replace(temporary, path)


def weights_path(recipe: Recipe, weights_out: Path | str | None = None) -> Path:
    """Where `train` writes the generator: `weights_out`, else <output>/generator.pt."""
    return Path(weights_out) if weights_out else Path(recipe.output) / "generator.pt"


def _file_state(path: Path) -> tuple[int, int] | None:
    """(size, modification time in ns) of a file, None when there is none."""
    try:
        stat = path.stat()
    except OSError:
        return None
    return stat.st_size, stat.st_mtime_ns


def train(recipe: Recipe, weights_out: Path | None = None, progress: bool = True,
          max_seconds: float | None = None, resume: bool = False, patches: PatchSet | None = None,
          validation: Validation | None = None, meta: dict | None = None, curves_pugan: Path | None = None,
          data_workers: int = 1, caller: str = "cadpu.train") -> Path:
    """Run the recipe to its last step (or until `max_seconds`); write the weights and return their path.

    Args:
        recipe: what to train.
        weights_out: where the generator goes (default: <output>/generator.pt); written also when
            `max_seconds` stops the run early.
        progress: show a progress bar.
        max_seconds: stop early, with a checkpoint, after the step in which this much time has
            passed in this call; a later call with `resume` continues.
        resume: continue from the recipe's checkpoint, which must exist; a run already at its last
            step whose weights file exists leaves the file as it is.
        patches: the training pairs; None builds (or reads from the cache) `recipe.data`'s.
        validation: a held-out set scored during the run (`cadpu.validation`); with its
            `keep_best`, the weights written are those of its best score.
        meta: more entries for the written file's meta (e.g. where its data came from).
        curves_pugan: a folder of PU-GAN test meshes for the held-out curves (`recipe.curves_every`).
        data_workers: processes that generate `recipe.data` when it is not cached yet.
        caller: the command the run's messages name (e.g. "kitti-pu finetune"); its checkpoint
            records it, and only the same command resumes it (`checkpoint_caller`).

    Raises:
        FileExistsError: a checkpoint exists and `resume` is False (it would be overwritten).
        FileNotFoundError: `resume` is True and there is no checkpoint.
    """
    from tqdm import tqdm

    weights_out = check_weights_target(weights_path(recipe, weights_out),
                                       "--weights-out" if weights_out else "recipe output")
    if recipe.threads:
        torch.set_num_threads(recipe.threads)
    device = torch.device("cuda" if torch.cuda.is_available() else "cpu")
    checkpoint = recipe.checkpoint_path
    if checkpoint.is_dir():  # found after the training, before (IsADirectoryError, a temporary left)
        raise ValueError(f"recipe checkpoint: {checkpoint} is a folder; give the checkpoint file's path "
                         f"(e.g. {checkpoint / 'run.pt'})")
    if checkpoint.is_file() and not resume:
        raise FileExistsError(f"{checkpoint}: a checkpoint of this recipe exists; pass --resume to "
                              f"continue it, or delete it to start again")
    if resume and not checkpoint.is_file():
        raise FileNotFoundError(f"{checkpoint}: no checkpoint to resume; run without --resume to start")
    state = read_checkpoint(checkpoint, device) if resume else None
    if state is not None and not (isinstance(state, dict) and {"step", "generator", "opt_g"} <= state.keys()):
        raise ValueError(f"{checkpoint}: not a training checkpoint of cadpu.train (a weights file? give it as "
                         "the recipe's init_weights to start from it)")
    if state is not None and (made_by := checkpoint_caller(state, checkpoint)) != caller:
        # resumed by cadpu.train, a fine-tuning run trained on synthetic patches and wrote weights
        # without its provenance (a researcher's trial)
        raise ValueError(f"{checkpoint}: the checkpoint of a `{made_by}` run; continue it with "
                         f"{resume_command(made_by)} ... --resume")
    if state is not None and recipe.steps < state["step"]:
        raise ValueError(f"{checkpoint}: the run is at step {state['step']}, past the recipe's steps "
                         f"({recipe.steps}); give steps of at least {state['step']}")
    if state is not None and state["step"] >= recipe.steps and _written_at(weights_out, state["step"], recipe):
        # nothing to train: rewriting the file would change its checksum (its meta's times), and a
        # pipeline run with these weights would take it for a new model and redo every frame
        print(f"{caller}: the run is at its last step ({state['step']}); {weights_out} is left as it is",
              file=sys.stderr)
        return weights_out
    changes = recipe_changes(state.get("recipe"), recipe, checkpoint) if state is not None else {}
    out = Path(recipe.output)
    out.mkdir(parents=True, exist_ok=True)
    (out / "recipe.yaml").write_text(yaml.safe_dump(dataclasses.asdict(recipe), sort_keys=False))
    # the weights' meta records the recipe's data only where it made the patches; a caller's own
    # (`kitti-pu finetune`'s pairs of real scans) are described by its meta, and the recipe's
    # default read as 200 procedural meshes trained on (a trial)
    patches_given = patches is not None
    if patches is None:
        patches = load_or_build(recipe.data, Path(recipe.cache_dir), progress, data_workers)
    trainer = Trainer(recipe, patches, device)
    elapsed = 0.0
    segments: list[dict] = []
    if state is not None:
        trainer.restore(state)
        elapsed = state["elapsed"]
        # steps so far were of the checkpoint's batch size; samples_at counts every step at this
        # recipe's, so the offset takes the difference
        saved_batch = int((state.get("recipe") or {}).get("batch_size", recipe.batch_size))
        trainer.samples_before = (state.get("samples_before", trainer.samples_before)
                                  + trainer.step_count * (saved_batch - recipe.batch_size))
        segments = list(state.get("segments", []))
        if validation is not None:
            validation.restore(state.get("validation"))
    segment = {"from_step": trainer.step_count, "to_step": trainer.step_count, "seconds": 0.0,
               "hardware": hardware(), "torch": torch.__version__}
    if changes:  # kept in the weights' provenance (meta "segments")
        segment["recipe_changes"] = changes
        print(f"{caller}: resuming at step {trainer.step_count} with a changed recipe: "
              + ", ".join(f"{key} {old!r} -> {new!r}" for key, (old, new) in changes.items()), file=sys.stderr)
    segments.append(segment)
    log_path = out / "log.csv"
    if log_path.is_file() and trainer.step_count > 0:
        _cut_rows(log_path, trainer.step_count)  # removes a file without a header
    new_log = not log_path.is_file() or trainer.step_count == 0
    columns = LOG_COLUMNS if new_log else _header(log_path)
    log = log_path.open("w" if new_log else "a", newline="")
    # a log begun before a column existed keeps its header; rows then leave the new column out
    writer = csv.DictWriter(log, columns, extrasaction="ignore")
    if new_log:
        writer.writeheader()
    resumed_at = trainer.step_count if state is not None else -1
    _cut_rows(out / "validation.csv", resumed_at)
    if validation is not None and trainer.step_count == 0:  # the starting weights are a candidate too
        validation.score(trainer.generator, 0, out / "validation.csv")
    curves = None
    curves_csv = Path(recipe.curves_csv) if recipe.curves_csv else out / "curves.csv"
    # a fresh run replaces the curves only where it records its own: a recipe whose checkpoint is
    # not kept names a curves file of the repository's, which a run with curves off leaves alone
    if state is not None or recipe.curves_every:
        _cut_rows(curves_csv, resumed_at)
    if recipe.curves_every:
        curves = HeldoutCurves(recipe.curves_meshes, recipe.curves_streets, recipe.data.scan_vertical_scale, curves_pugan,
                               recipe.data.sensor, recipe.data.scene_types)
    started = time.perf_counter()
    bar = tqdm(total=recipe.steps, initial=trainer.step_count, disable=not progress, unit="step")
    # a signal stops the run after its step, as --max-seconds does (cadpu.stopping)
    with StopRequest() as stop:
        try:
            while trainer.step_count < recipe.steps:
                terms = trainer.step()
                now = elapsed + time.perf_counter() - started
                writer.writerow({"step": trainer.step_count, "seconds": round(now, 2),
                                 **{k: f"{v:.6g}" for k, v in terms.items()}})
                bar.update(1)
                bar.set_postfix(**{recipe.objective: f"{terms[recipe.objective]:.4f}"}, reg=f"{terms['regularizer']:.3f}")
                if curves is not None and trainer.step_count % recipe.curves_every == 0:
                    curves.record(trainer.generator, trainer.step_count, trainer.samples_at(trainer.step_count), curves_csv)
                if recipe.snapshot_every and trainer.step_count % recipe.snapshot_every == 0:
                    save(trainer.generator, out / "snapshots" / f"step-{trainer.step_count:07d}.pt",
                         {**(meta or {}), "recipe": dataclasses.asdict(recipe), "steps": trainer.step_count,
                          "samples_seen": trainer.samples_at(trainer.step_count),
                          "init_weights": recipe.init_weights, "hardware": hardware()})
                if validation is not None and validation.due(trainer.step_count, recipe.steps):
                    validation.score(trainer.generator, trainer.step_count, out / "validation.csv")
                # The time limit is checked every step, not only at checkpoints: a step can take long
                # (a slow machine, a large batch) and checkpoint_every many of them longer still.
                out_of_time = max_seconds is not None and time.perf_counter() - started > max_seconds
                stopping = out_of_time or stop.requested
                if stopping or trainer.step_count % recipe.checkpoint_every == 0 or trainer.step_count == recipe.steps:
                    log.flush()
                    segment.update(to_step=trainer.step_count, seconds=round(time.perf_counter() - started, 1))
                    _save_checkpoint(trainer, checkpoint, now, segments, validation, caller)
                    plot_log(log_path, out / "losses.png")
                if out_of_time:
                    bar.write(f"{caller}: stopped by --max-seconds at step {trainer.step_count} of {recipe.steps}; "
                              f"continue with --resume", file=sys.stderr)
                if stopping:  # by a signal: TrainingStopped, once the weights are written, says so
                    break
        finally:
            bar.close()
            log.close()
    total_seconds = elapsed + time.perf_counter() - started
    written = trainer.generator if validation is None else validation.weights_to_write(trainer.generator)
    steps_in_written = trainer.step_count if written is trainer.generator else validation.best_step
    meta = {
        **(meta or {}),
        "recipe": {**dataclasses.asdict(recipe), **({"data": None} if patches_given else {})},
        "steps": trainer.step_count, "train_seconds": round(total_seconds, 1), "device": str(device),
        "threads": torch.get_num_threads(), "torch": torch.__version__,
        "patches": len(patches),
        "samples_seen": trainer.samples_at(steps_in_written),
        "init_weights": recipe.init_weights, "init_sha256": trainer.init_checksum, "segments": segments,
    }
    if validation is not None:
        meta.update(heldout_score=validation.best_score, heldout_best_step=validation.best_step,
                    weights_of_step=steps_in_written)
    save(written.cpu(), weights_out, meta)
    plot_log(log_path, out / "losses.png")
    if stop.requested:
        raise TrainingStopped(weights_out, trainer.step_count, stop.signal_name or "", stop.exit_status)
    return weights_out


def _cut_rows(path: Path, step: int) -> None:
    """Drop the rows of a run's CSV (its log, validation scores, held-out curves) past `step`, the
    checkpoint a resume starts from: the steps an interrupted run recorded after its last
    checkpoint are trained again, and were recorded twice (the curves plotted a zig-zag). A run
    started afresh cuts at -1: the rows of a run whose checkpoint was deleted are another run's.
    A missing file is left missing; one without a header is removed (its writer then writes one)."""
    if not path.is_file():
        return
    with path.open(newline="") as rows:
        reader = csv.DictReader(rows)
        kept = [row for row in reader if row.get("step", "").isdigit() and int(row["step"]) <= step]
        columns = reader.fieldnames
    if not columns:
        path.unlink()
        return
    temporary = path.with_name(f".{path.name}.tmp")
    with temporary.open("w", newline="") as rows:
        writer = csv.DictWriter(rows, columns, extrasaction="ignore")
        writer.writeheader()
        writer.writerows(kept)
    temporary.replace(path)


def _header(path: Path) -> tuple[str, ...]:
    """The column names of a CSV file's first line (empty for an empty file)."""
    with path.open(newline="") as rows:
        return tuple(next(csv.reader(rows), ()))


def _written_at(weights: Path, step: int, recipe: Recipe) -> bool:
    """Whether `weights` is the file this recipe's run wrote at `step` (its meta's steps and
    checkpoint), intact; False for a missing, damaged or other file, or one of an earlier step
    (written by `--max-seconds`, before the run went on elsewhere with `--weights-out`)."""
    if not weights.is_file():
        return False
    try:
        _, _, meta = load_generator(weights)
    except WeightsError:
        return False
    return meta.get("steps") == step and (meta.get("recipe") or {}).get("checkpoint") == recipe.checkpoint


def parse_overrides(items: list[str]) -> dict[str, object]:
    """The recipe keys of `--set KEY=VALUE` items (YAML values, `read_yaml`); ValueError naming
    an item without `=` or with a value that is not YAML."""
    overrides = {}
    for item in items:
        key, equals, value = item.partition("=")
        if not equals or not key.strip():
            raise ValueError(f"--set {item}: expected KEY=VALUE, e.g. --set steps=5000")
        try:
            overrides[key.strip()] = read_yaml(value)
        except yaml.YAMLError as error:
            raise ValueError(f"--set {item}: the value is not valid YAML ({first_line_of(error)})") from None
    return overrides


def first_line_of(error: BaseException) -> str:
    """The first line of an error's message (YAML's run over several, with context)."""
    return str(error).strip().splitlines()[0] if str(error).strip() else type(error).__name__


def main(argv: list[str] | None = None) -> None:
    """CLI: python -m cadpu.train RECIPE.yaml [--weights-out PATH] [--set key=value ...]."""
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("recipe", type=Path, help="the recipe's YAML file (configs/train*.yaml)")
    parser.add_argument("--weights-out", type=Path, default=None, metavar="FILE",
                        help="the weights file to write, with FILE.sha256 (default: generator.pt in the recipe's output)")
    parser.add_argument("--max-seconds", type=float, default=None, metavar="S",
                        help="stop after the step that passes S seconds, with a checkpoint and the weights; "
                             "--resume continues")
    parser.add_argument("--resume", action="store_true",
                        help="continue from the recipe's checkpoint (which must exist)")
    parser.add_argument("--curves-pugan", type=Path, default=None, metavar="DIR",
                        help="PU-GAN test meshes to add to the held-out curves (recipe curves_every)")
    parser.add_argument("--data-workers", type=int, default=1, metavar="N",
                        help="processes that generate the training data when it is not cached")
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                        help="override a top-level recipe key (YAML value)")
    args = parser.parse_args(argv)
    if args.max_seconds is not None and not args.max_seconds >= 0:
        parser.error(f"--max-seconds must be 0 or more, got {args.max_seconds}")
    try:
        recipe = Recipe.from_yaml(args.recipe, parse_overrides(args.set))
        before = _file_state(weights_path(recipe, args.weights_out))
        path = train(recipe, args.weights_out, max_seconds=args.max_seconds, resume=args.resume,
                     curves_pugan=args.curves_pugan, data_workers=args.data_workers)
    except (FileExistsError, FileNotFoundError, ValueError, WeightsError) as error:
        print(f"cadpu.train: {error}", file=sys.stderr)
        raise SystemExit(2) from None  # bad recipe, paths or weights, as kitti-pu's exit status 2
    except TrainingStopped as stopped:
        print(f"cadpu.train: {stopped}", file=sys.stderr)
        raise SystemExit(stopped.exit_status) from None
    except KeyboardInterrupt:  # before the steps (building the patches: a 40-line traceback), or a second Ctrl-C
        print("cadpu.train: stopped by SIGINT outside a step; the last checkpoint, if there is one, stands "
              "(continue with --resume)", file=sys.stderr)
        raise SystemExit(STOP_SIGNALS[signal.SIGINT]) from None
    if before is None or _file_state(path) != before:  # a run at its last step leaves the file (said above)
        print(f"weights written to {path}")


if __name__ == "__main__":
    main()
