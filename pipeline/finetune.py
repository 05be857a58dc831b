"""Self-supervised fine-tuning of CAD-PU weights on a user's own 64-ring scans (`kitti-pu finetune`).

Any full 64-ring scan in KITTI point order supervises itself, the way the 16-to-64-beam evaluation
(`pipeline.evaluation`) scores it: the input is its rings offset, offset + 4, ... and the truth
its points of all 64 rings. Pairs are cut exactly as the simulated street pairs the shipped
weights learned from (`cadpu.scan_data.thinned_scan_pairs`, with the pipeline's
`tile.vertical_scale`), so fine-tuning continues the same task on real data. Per scan:

1. read it as `run` does (`stages.load.scan_points`) and recover its rings from the point order (`stages.rings`);
2. label the ground of the full scan with the configured method (`stages.ground`); the network
   only ever sees non-ground points, so only they make pairs;
3. estimate their normals (the targets of the curvature regularizer) by PCA over their
   `NORMAL_NEIGHBOURS` nearest neighbours, in metres;
4. for each ring offset 0..3, draw random patches of the thinned scan's tiling as inputs, each with
   the full scan's points nearest to it as truth.

A share of the scans is held out (`FinetuneConfig.validation_share`): every `validate_every` steps
each is thinned to 16 rings, densified by the whole chain with the current network and scored
against its full scan (non-ground Chamfer distance, metres: `HeldoutScans`, the figure
`kitti-pu eval-kitti` reports), and the weights written are those of the best mean score
(`cadpu.validation`), the starting weights included; a run on a few scans thus never writes
weights that score worse on scans it did not train on. The pairs' own Chamfer distance is no
proxy for that figure: it is measured in the patches' vertically scaled unit spheres, and the
snap stage and the range check reshape the output after the network. The
objective is the base file's own (its recipe's EMD reduction and beta) without the adversarial
term: the discriminator is not shipped, and a fresh one's first gradients are noise to a trained
generator.
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from cadpu.data import PatchSet
from cadpu.geometry import curvature_and_normals_np
from cadpu.inference import Upsampler
from cadpu.network import Generator
from cadpu.scan_data import RATIO, PatchFrames, thinned_scan_pairs
from cadpu.train import Recipe, checkpoint_caller, read_checkpoint, resume_command, train
from cadpu.validation import Validation, read_validation_log
from cadpu.weights import check_weights_target, load_generator, portable_name, resolve
from stages import ground, load, upsample
from stages.discovery import FrameRef, content_digest, scans_among
from stages.errors import InputError
from stages.rings import hdl64e_rings

from .config import FinetuneConfig, PipelineConfig
from .evaluation.methods import densify_with_pipeline, thin_scan
from .evaluation.scoring import NON_GROUND, Reference
from .preflight import discover_frames

#: Neighbours of the PCA normal of a scan point: 24 span about three rings of a 64-ring scan, so
#: the fitted plane is not a single ring's line.
NORMAL_NEIGHBOURS = 24
STAGE = "finetune"
#: The command a fine-tuning run's checkpoint records (`cadpu.train.checkpoint_caller`).
CALLER = "kitti-pu finetune"
#: A step count no run reaches: fine-tuning never decays its rate nor starts the adversarial term
#: (constant, so that a resume with more steps changes nothing else in the recipe).
NEVER = 2**31 - 1

#: `finetune` settings a resumed run may change: how long, how often it scores and saves, threads.
RESUMABLE_CHANGES = {"steps", "validate_every", "checkpoint_every", "threads"}
#: `finetune` settings added after runs were recorded: left out of the fingerprint at their defaults.
ADDED_SETTINGS = ("objective", "augmentation")


class InterruptedBeforeTraining(KeyboardInterrupt):
    """Ctrl-C while the scans were read and cut into pairs: nothing was trained or recorded."""


@dataclass(frozen=True)
class FinetuneResult:
    """What `finetune` wrote and measured.

    Attributes:
        weights: the weights file (with its `.sha256`). checksum: its sha256.
        run_dir: the run's folder (log.csv, validation.csv, losses.png, checkpoint.pt, data.json).
        steps: steps trained in all. best_step: the step whose weights were written.
        heldout_before / heldout_after: `HeldoutScans`' score (mean non-ground Chamfer distance,
            metres) of the base weights and of the written ones; NaN without held-out scans.
        train_pairs: pairs trained on. heldout_scans: scans held out.
    """

    weights: Path
    checksum: str
    run_dir: Path
    steps: int
    best_step: int
    heldout_before: float
    heldout_after: float
    train_pairs: int
    heldout_scans: int


class HeldoutScans:
    """A `cadpu.validation` scorer: the mean non-ground Chamfer distance (metres) of the pipeline's
    output with the scored network, on scans thinned to every 4th ring, against the full scans.

    Args:
        refs: the held-out scans. config: the pipeline settings the chain runs with.
    """

    def __init__(self, refs: list[FrameRef], config: PipelineConfig) -> None:
        self.config = config
        self.cases = []
        for ref in refs:
            points = load.scan_points(ref.source, config.input)
            thinned, _ = thin_scan(points, ref.source, ratio=RATIO)
            full_ground = ground.segment(points, config.ground.method, config.ground.method_params()).mask
            frame = load.frame_from_points(thinned, dataset="finetune", sequence="heldout", index=ref.index,
                                           source=ref.source)
            self.cases.append((frame, Reference(points, full_ground)))

    def __len__(self) -> int:
        return len(self.cases)

    def __call__(self, generator: Generator) -> float:
        device = str(next(generator.parameters()).device)
        section = self.config.upsample
        settings = {**upsample.upsampler_settings(section), "ratio": RATIO, "device": device, "engine": "eager"}
        upsampler = Upsampler(generator=generator, **settings)
        scores = [reference.score(densify_with_pipeline(frame, upsampler, self.config))[NON_GROUND].chamfer
                  for frame, reference in self.cases]
        return float(np.mean(scores))


def scan_pairs(points: np.ndarray, config: PipelineConfig, count: int, rng: np.random.Generator,
               source: str = "") -> PatchSet:
    """Training pairs from one full 64-ring scan (see the module docstring).

    Args:
        points: (N, 4) scan in KITTI point order, sensor frame, metres.
        config: its ground method and `tile.vertical_scale` are used.
        count: at most this many pairs, split evenly over the ring offsets.
        rng: the random source of the patch draws. source: the file, for errors.

    Returns:
        A `PatchSet` of at most `count` pairs: inputs (P, 256, 3), truth and normals (P, 1024, 3),
        each in its input's unit sphere (z scaled by `tile.vertical_scale` first).

    Raises:
        InputError: the point order shows other than 64 rings (`stages.rings.hdl64e_rings`): not
            a full HDL-64E scan in KITTI order (a 16-ring scan taught a 4-to-16 task: a trial).
    """
    rings = hdl64e_rings(points, RATIO, STAGE, source, "fine-tuning")
    above = ~ground.segment(points, config.ground.method, config.ground.method_params()).mask
    xyz = np.asarray(points[above, :3], dtype=np.float64)
    if len(xyz) < NORMAL_NEIGHBOURS:
        return _empty_pairs()
    _, normals = curvature_and_normals_np(xyz, NORMAL_NEIGHBOURS)
    per_offset = max(1, count // RATIO)
    parts = [thinned_scan_pairs(xyz, rings[above], normals, offset, per_offset, rng, config.tile.vertical_scale)
             for offset in range(RATIO)]
    return PatchSet.concatenate([PatchSet(inputs, truth, truth_normals, np.ones(len(inputs), dtype=bool), frames)
                                 for inputs, truth, truth_normals, frames in parts])


def split_scans(refs: list[FrameRef], share: float) -> tuple[list[FrameRef], list[FrameRef]]:
    """(training scans, held-out scans): round(share x scans), at least one when there are two or
    more, taken evenly spaced through the list (so they span the drive, not only its end)."""
    if len(refs) < 2 or share <= 0:
        return list(refs), []
    held = min(len(refs) - 1, max(1, round(share * len(refs))))
    positions = {int(np.floor(p + 0.5)) for p in np.linspace(0, len(refs) - 1, held + 2)[1:-1]}
    return ([r for i, r in enumerate(refs) if i not in positions],
            [r for i, r in enumerate(refs) if i in positions])


def collect_pairs(refs: list[FrameRef], config: PipelineConfig, per_scan: int, seed: int,
                  log: Callable[[str], None] | None = None) -> PatchSet:
    """The pairs of every scan in `refs` (see `scan_pairs`), each scan with its own seeded draws."""
    sets = []
    for ref in refs:
        points = load.scan_points(ref.source, config.input)
        pairs = scan_pairs(points, config, per_scan, np.random.default_rng([seed, ref.index]), ref.source)
        sets.append(pairs)
        if log is not None:
            log(f"{ref.key}: {len(points):,} points, {len(pairs)} pairs")
    if not sets:
        return _empty_pairs()
    return PatchSet.concatenate(sets)


def finetune(config: PipelineConfig, out: str | Path, weights: str | Path | None = None, resume: bool = False,
             progress: bool = True, max_seconds: float | None = None,
             log: Callable[[str], None] | None = None) -> FinetuneResult:
    """Fine-tune `weights` on the full scans `config.input` selects and write the result to `out`.

    Args:
        config: `input` (path: KITTI raw drive, odometry sequence, folder of .bin scans or one
            .bin; sequences and frames), ground, tiling and `finetune` settings.
        out: the weights file to write (with `out.sha256`); the run's folder is `<out>.run/`.
        weights: the starting weights (None = `config.upsample.weights`).
        resume: continue the run in `<out>.run/` (same scans, settings and base weights).
        progress: a progress bar. max_seconds: stop (after a checkpoint) after this long; resume
            continues. log: called with one line per scan read and per finding.

    Returns:
        The `FinetuneResult`.

    Raises:
        ConfigError: no scans under the input path. InputError: too few training pairs, or a
            bad scan (naming it).
        cadpu.weights.WeightsError: missing or corrupt base weights. ValueError: base weights
            not of ratio 4, or `resume` with other scans or settings than the run's.
        FileExistsError / FileNotFoundError: a run exists without `resume` / none with it.
    """
    options = config.finetune
    base = resolve(weights or config.upsample.weights)
    generator, base_checksum, base_meta = load_generator(base)
    if generator.ratio != RATIO:
        raise ValueError(f"{STAGE}: {base} makes {generator.ratio}x; fine-tuning trains ratio {RATIO} pairs")
    refs = discover_frames(config)
    if len(refs) > options.max_pairs:
        refs = [refs[int(i)] for i in np.linspace(0, len(refs) - 1, options.max_pairs)]
    per_scan = min(options.pairs_per_scan, max(1, options.max_pairs // len(refs)))
    train_refs, heldout_refs = split_scans(refs, options.validation_share)

    out = check_weights_target(out, "--out", shipped_allowed=False)
    if out.resolve() == base.resolve():  # the run compares the base's checksum on every resume
        raise ValueError(f"{STAGE}: --out {out} is the base weights file; write the fine-tuned weights to another file")
    run_dir = out.with_name(f"{out.name}.run")
    data = _data_fingerprint(refs, config, base_checksum)
    _check_run_folder(run_dir, data, resume, options.steps)
    try:
        training = collect_pairs(train_refs, config, per_scan, options.seed, log)
        heldout = HeldoutScans(heldout_refs, config)
    except KeyboardInterrupt:
        raise InterruptedBeforeTraining() from None
    if len(training) < options.batch_size:
        raise InputError(STAGE, str(config.input.path), f"{len(training)} training pairs from {len(train_refs)} scans, "
                                           f"fewer than a batch of {options.batch_size}")
    _record_run(run_dir, data, resume)
    recipe = _recipe(base, base_meta, generator, options, run_dir)
    validation = Validation(heldout, every=options.validate_every) if len(heldout) else None
    parent = {"weights": portable_name(base), "sha256": base_checksum}  # as typed, a relative path was kept (a trial)
    digest_of: dict[str, str] = {}  # each scan hashed once
    meta = {"finetuned_from": parent, "finetune_lineage": [*lineage(base_meta), parent],
            "finetune_scans": trained_scans(base_meta, train_refs),
            "finetune_scan_digests": scan_digests(base_meta, "finetune_scan_digests", train_refs, digest_of),
            "finetune_heldout_scans": selection_scans(base_meta, heldout_refs),
            "finetune_heldout_digests": scan_digests(base_meta, "finetune_heldout_digests", heldout_refs, digest_of),
            "finetune_pairs": len(training)}
    if log is not None:
        # a held-out scan the weights trained on, here or in their base's run, by path or as a copy,
        # chooses the weights all the same: its score is not a held-out one (it went unsaid: a trial)
        seen = scans_among([ref.source for ref in heldout_refs], meta["finetune_scans"],
                           meta["finetune_scan_digests"], digest_of)
        for source, how in seen.items():
            log(f"{STAGE}: warning: held-out scan {source} is {'a scan' if how == 'path' else 'a copy of a scan'} "
                "these weights have trained on (here or in the run of their base): its score, which chooses the "
                "weights written, is not a held-out score")
    written = train(recipe, out, progress=progress, max_seconds=max_seconds, resume=resume, patches=training,
                    validation=validation, meta=meta, caller=CALLER)
    _, checksum, written_meta = load_generator(written)
    steps, scores = read_validation_log(run_dir / "validation.csv")
    before = float(scores[steps == 0][0]) if np.any(steps == 0) else float("nan")
    return FinetuneResult(weights=written, checksum=checksum, run_dir=run_dir, steps=int(written_meta["steps"]),
                          best_step=int(written_meta.get("weights_of_step", written_meta["steps"])),
                          heldout_before=before, heldout_after=float(written_meta.get("heldout_score", float("nan"))),
                          train_pairs=len(training), heldout_scans=len(heldout))


def trained_scans(base_meta: dict, train_refs: list[FrameRef]) -> list[str]:
    """Every scan a fine-tuned file has trained on: those of the fine-tuning runs its base came from
    (the base's meta `finetune_scans`), then this run's training scans, each once, by source path.
    `eval-kitti` warns when it scores one of them."""
    earlier = [str(scan) for scan in base_meta.get("finetune_scans", [])]
    return list(dict.fromkeys(earlier + [r.source for r in train_refs]))


def selection_scans(base_meta: dict, heldout_refs: list[FrameRef]) -> list[str]:
    """Every scan that chose a fine-tuned file's weights (scored to pick the best step): those of
    the runs its base came from (the base's meta `finetune_heldout_scans`), then this run's held-out
    scans, each once. Their scores are not held-out scores of the file: `eval-kitti` warns (it named
    only the training scans, and a base's selection scans were lost: a researcher's trial)."""
    earlier = [str(scan) for scan in base_meta.get("finetune_heldout_scans", [])]
    return list(dict.fromkeys(earlier + [r.source for r in heldout_refs]))


def lineage(meta: dict) -> list[dict]:
    """The files a weights file was fine-tuned through, the first first ({"weights", "sha256"} each):
    its meta's `finetune_lineage`, or for a file of a version before it, its `finetuned_from`
    alone (whose own parents that version did not keep); [] for a file not fine-tuned."""
    if "finetune_lineage" in meta:
        return list(meta["finetune_lineage"])
    return [meta["finetuned_from"]] if "finetuned_from" in meta else []


def scan_digests(base_meta: dict, key: str, refs: list[FrameRef], digest_of: dict[str, str]) -> list[str]:
    """The scans of `refs` by content (`stages.discovery.content_digest`) after those the base's
    meta lists under `key`, each once: `finetune_scan_digests` (trained on) and
    `finetune_heldout_digests` (chose the weights), by which `eval-kitti` warns of a copy elsewhere
    too (by path alone it did not: trials). `digest_of` (source -> digest) is filled as scans are
    hashed, and read for those already hashed."""
    for ref in refs:
        if ref.source not in digest_of:
            digest_of[ref.source] = content_digest(ref.source)
    earlier = [str(digest) for digest in base_meta.get(key, [])]
    return list(dict.fromkeys(earlier + [digest for r in refs if (digest := digest_of[r.source])]))


def _recipe(base: Path, base_meta: dict, generator: Generator, options: FinetuneConfig, run_dir: Path) -> Recipe:
    """The training recipe of a fine-tuning run: the base file's network and objective, the
    `finetune` settings' schedule, no adversarial term, no learning-rate decay."""
    trained_with = base_meta.get("recipe", {})
    network = generator.config
    return Recipe(ratio=network["ratio"], alpha=network["alpha"], frame_k=network["frame_k"],
                  offset_frame=network["offset_frame"], code_spread=network["code_spread"],
                  steps=options.steps, batch_size=options.batch_size, lr_generator=options.lr,
                  decay=1.0, decay_every=NEVER, beta=trained_with.get("beta", Recipe.beta),
                  emd_reduction=trained_with.get("emd_reduction", Recipe.emd_reduction),
                  adversarial_from=NEVER, checkpoint_every=options.checkpoint_every,
                  seed=options.seed, threads=options.threads, output=str(run_dir),
                  init_weights=portable_name(Path(base).resolve()), objective=options.objective,
                  augmentation=options.augmentation)


def _data_fingerprint(refs: list[FrameRef], config: PipelineConfig, base_checksum: str) -> dict[str, Any]:
    """What a resumed run must share with the run it continues: scans, settings that cut the
    pairs, the fine-tuning settings (but `RESUMABLE_CHANGES`) and the base weights; as
    {"fingerprint": a 16-digit hash of all of it (as earlier versions hashed it, so that their runs
    resume), "parts": each part, for saying what differs, the scans as their count and hash}."""
    scans = [[r.source, r.fingerprint] for r in refs]
    settings = {"ground": config.ground.model_dump(mode="json"), "tile": config.tile.model_dump(mode="json"),
                "finetune": config.finetune.model_dump(mode="json", exclude=RESUMABLE_CHANGES)}
    # settings added since runs were recorded are hashed only away from their defaults (so that those resume)
    hashed = {key: value for key, value in settings["finetune"].items()
              if key not in ADDED_SETTINGS or value != FinetuneConfig.model_fields[key].default}
    content = {"scans": scans, "base": base_checksum, **settings, "finetune": hashed}
    parts = {"scans": {"count": len(scans), "sha256": hashlib.sha256(json.dumps(scans).encode()).hexdigest()[:16]},
             "base weights": base_checksum, **settings}
    return {"fingerprint": hashlib.sha256(json.dumps(content, sort_keys=True).encode()).hexdigest()[:16],
            "parts": parts, "scoring": scoring_settings(config)}


def scoring_settings(config: PipelineConfig) -> dict[str, Any]:
    """The settings the held-out scans are densified and scored with besides the ground and tile
    ones (`_data_fingerprint`'s parts): the rest of `PipelineConfig.output_settings` (the weights
    are left out there: they are what is trained). A resume under other ones ranked scores of two
    pipelines against each other to pick the best weights (a trial); runs recorded before this
    was kept resume as they did."""
    return {section: values for section, values in config.output_settings().items() if section not in ("ground", "tile")}


def _differences(before: dict[str, Any], now: dict[str, Any]) -> str:
    """What differs between two runs' `parts`, e.g. "finetune.lr 0.0003 -> 0.01; the scans (6 -> 3)"."""
    said = []
    for name in sorted(set(before) | set(now)):
        old, new = before.get(name), now.get(name)
        if old == new:
            continue
        if name == "scans" and isinstance(old, dict) and isinstance(new, dict):
            said.append(f"the scans ({old.get('count')} -> {new.get('count')}"
                        f"{'' if old.get('count') != new.get('count') else ', other files or contents'})")
        elif isinstance(old, dict) and isinstance(new, dict):
            said += [f"{name}.{key} {old.get(key)!r} -> {new.get(key)!r}" for key in sorted(set(old) | set(new))
                     if old.get(key) != new.get(key)]
        else:
            said.append(f"{name} {old!r} -> {new!r}")
    return "; ".join(said)


def _check_run_folder(run_dir: Path, data: dict[str, Any], resume: bool, steps: int) -> None:
    """Refuse, before any scan is read and nothing written: a resume without a run, of a checkpoint
    that is not a fine-tuning run's or is past `steps`, of another run (naming what differs), and a
    fresh start over a run. (`cadpu.train` refuses the same after the pairs are cut, in its words.)"""
    checkpoint = run_dir / "checkpoint.pt"
    if resume and not checkpoint.is_file():
        raise FileNotFoundError(f"{run_dir}: no checkpoint to resume; run without --resume to start")
    if not resume and checkpoint.is_file():
        raise FileExistsError(f"{run_dir}: a fine-tuning run is there; pass --resume to continue it, "
                              "or choose another --out")
    if not resume:
        return
    state = read_checkpoint(checkpoint, torch.device("cpu"))  # a damaged one was a traceback after the pairs
    if not (isinstance(state, dict) and {"step", "generator", "opt_g"} <= state.keys()):
        raise ValueError(f"{STAGE}: {checkpoint} is not a training checkpoint; delete it to start the run again")
    if (made_by := checkpoint_caller(state, checkpoint)) != CALLER:
        raise ValueError(f"{STAGE}: {checkpoint} is the checkpoint of a `{made_by}` run; continue it with "
                         f"{resume_command(made_by)} ... --resume, or choose another --out")
    if state["step"] > steps:
        raise ValueError(f"{STAGE}: {run_dir} is at step {state['step']}, past --steps {steps}; give --steps of at "
                         f"least {state['step']}")
    record = run_dir / "data.json"
    if not record.is_file():
        return
    stored = json.loads(record.read_text())
    if stored.get("fingerprint") != data["fingerprint"]:
        what = (_differences(stored["parts"], data["parts"]) if isinstance(stored.get("parts"), dict) else
                f"fingerprint {stored.get('fingerprint')}, now {data['fingerprint']}")
        free = ", ".join(f"finetune.{name}" for name in sorted(RESUMABLE_CHANGES))
        raise ValueError(f"{STAGE}: {run_dir} was started with other scans, settings or base weights ({what}); "
                         f"resume it with the same ones (all but {free}), or start a new run with another --out")
    if "scoring" in stored and stored["scoring"] != data["scoring"]:
        raise ValueError(f"{STAGE}: {run_dir} scores its held-out scans with other pipeline settings now "
                         f"({_differences(stored['scoring'], data['scoring'])}), so its scores would not compare; "
                         f"resume it with the ones it was started with, or start a new run with another --out")


def _record_run(run_dir: Path, data: dict[str, Any], resume: bool) -> None:
    """Record the run's `data` (`_data_fingerprint`) in `run_dir/data.json`, once its pairs are cut
    (a run refused or interrupted while cutting them left a folder of data.json alone: a trial);
    a fresh start drops an earlier run's logs first."""
    run_dir.mkdir(parents=True, exist_ok=True)
    if not resume:
        for stale in ("log.csv", "validation.csv"):
            (run_dir / stale).unlink(missing_ok=True)
    (run_dir / "data.json").write_text(json.dumps(data))


def _empty_pairs() -> PatchSet:
    return PatchSet(np.zeros((0, 256, 3), np.float32), np.zeros((0, 1024, 3), np.float32),
                    np.zeros((0, 1024, 3), np.float32), np.zeros(0, dtype=bool), PatchFrames.empty())
