"""Tests of held-out scoring during training (`cadpu.validation`) and of `train` with it."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from cadpu.data import PatchSet
from cadpu.network import Generator
from cadpu.train import Recipe, train
from cadpu.validation import PatchChamfer, Validation, heldout_chamfer, read_validation_log
from cadpu.weights import load_generator


def _pairs(count: int = 4, seed: int = 0) -> PatchSet:
    rng = np.random.default_rng(seed)
    inputs = rng.normal(size=(count, 256, 3)).astype(np.float32)
    inputs /= np.linalg.norm(inputs, axis=-1).max(axis=1)[:, None, None]
    truth = np.repeat(inputs, 4, axis=1) + rng.normal(scale=0.01, size=(count, 1024, 3)).astype(np.float32)
    normals = np.tile(np.array([0.0, 0.0, 1.0], np.float32), (count, 1024, 1))
    return PatchSet(inputs, truth, normals, np.zeros(count, dtype=bool))


def test_heldout_chamfer_is_deterministic_and_sees_the_weights() -> None:
    torch.manual_seed(0)
    generator, pairs = Generator(ratio=4), _pairs()
    score = heldout_chamfer(generator, pairs)
    assert heldout_chamfer(generator, pairs) == score
    with torch.no_grad():
        for parameter in generator.parameters():
            parameter.add_(torch.randn_like(parameter))
    assert heldout_chamfer(generator, pairs) != score
    with pytest.raises(ValueError, match="empty"):
        heldout_chamfer(generator, PatchSet(*(a[:0] for a in (pairs.inputs, pairs.truth, pairs.truth_normals,
                                                                 pairs.scanline))))


def test_validation_writes_the_weights_of_the_best_score_and_survives_a_restore(tmp_path: Path) -> None:
    torch.manual_seed(0)
    generator = Generator(ratio=4)
    scores = iter([3.0, 1.0, 2.0])
    validation = Validation(lambda g: next(scores), every=1)
    log = tmp_path / "validation.csv"
    snapshots = []
    for step in range(3):
        with torch.no_grad():
            next(generator.parameters()).fill_(float(step))
        snapshots.append(next(generator.parameters()).clone())
        validation.score(generator, step, log)
    assert validation.best_step == 1 and validation.best_score == 1.0
    best = validation.weights_to_write(generator)
    assert torch.equal(next(best.parameters()), snapshots[1])
    assert torch.equal(next(generator.parameters()), snapshots[2])  # the training network is untouched
    steps, logged = read_validation_log(log)
    assert list(steps) == [0, 1, 2] and list(logged) == [3.0, 1.0, 2.0]
    restored = Validation(lambda g: 0.0)
    restored.restore(validation.state())
    assert restored.best_step == 1 and torch.equal(next(restored.weights_to_write(generator).parameters()), snapshots[1])


def test_train_with_validation_scores_step_zero_and_writes_the_best(tmp_path: Path) -> None:
    recipe = Recipe(steps=3, batch_size=2, checkpoint_every=1, adversarial_from=10, threads=1,
                    output=str(tmp_path / "run"))
    validation = Validation(PatchChamfer(_pairs(2, seed=1)), every=1)
    path = train(recipe, progress=False, patches=_pairs(4), validation=validation, meta={"origin": "test"})
    steps, scores = read_validation_log(tmp_path / "run" / "validation.csv")
    assert list(steps) == [0, 1, 2, 3]
    _, _, meta = load_generator(path)
    best = int(steps[np.argmin(scores)])
    assert meta["weights_of_step"] == best and meta["samples_seen"] == best * 2 and meta["origin"] == "test"
    assert meta["heldout_score"] == pytest.approx(scores.min(), rel=1e-4)


def test_the_held_out_snapped_chamfer_is_the_training_objective_unaugmented() -> None:
    from cadpu.losses import snapped_chamfer
    from cadpu.scan_data import street_scan_pairs
    from cadpu.validation import generated, heldout_snapped_chamfer, snapped_chamfers

    inputs, truth, normals, frames = street_scan_pairs(4, 1, 5, 0.15)
    pairs = PatchSet(inputs, truth, normals, np.ones(len(inputs), dtype=bool), frames)
    torch.manual_seed(0)
    generator = Generator(ratio=4, frame_k=24)
    outputs = generated(generator, inputs)
    count = len(inputs)
    expected = snapped_chamfer(torch.from_numpy(outputs), torch.from_numpy(truth), torch.eye(3).repeat(count, 1, 1),
                               torch.ones(count), *(torch.from_numpy(getattr(frames, name)) for name in
                                                    ("centroid", "scale", "vertical_scale", "truth_ring",
                                                     "ring_elevations"))).item()
    assert snapped_chamfers(outputs, pairs, batch_size=2) == pytest.approx(expected, rel=1e-5)
    assert heldout_snapped_chamfer(generator, pairs) == pytest.approx(expected, rel=1e-5)
    # the truth scores itself near 0 (rings drift within a patch: a truth point can lie nearer another ring)
    assert snapped_chamfers(truth, pairs) < 0.2 * expected
    with pytest.raises(ValueError, match="no frames"):
        snapped_chamfers(outputs, PatchSet(inputs, truth, normals, np.ones(count, dtype=bool)))
