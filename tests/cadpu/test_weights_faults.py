"""cadpu.weights refuses a weights file with NaN or infinite parameters, as a diverged training
run saves them with a matching checksum (issue 21, item 4)."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

from cadpu import weights
from cadpu.network import Generator


@pytest.mark.parametrize("value", [float("nan"), float("inf")])
def test_non_finite_weights_are_refused_naming_the_file(tmp_path: Path, value: float) -> None:
    torch.manual_seed(0)
    generator = Generator(ratio=4)
    name, parameter = next(iter(generator.named_parameters()))
    with torch.no_grad():
        parameter.view(-1)[3] = value
    path = tmp_path / "diverged.pt"
    # with a matching .sha256, as a diverged run of an earlier version wrote it (`save` refuses now)
    weights.write_file(path, generator.state_dict(), generator.config)
    with pytest.raises(weights.WeightsError, match="non-finite") as info:
        weights.load_generator(path)
    assert str(path) in str(info.value) and name in str(info.value)


def test_finite_weights_still_load(tmp_path: Path) -> None:
    path = tmp_path / "fine.pt"
    weights.save(Generator(ratio=4), path)
    generator, digest, _ = weights.load_generator(path)
    assert digest == weights.sha256_of(path) and not generator.training


def test_a_training_checkpoint_given_as_weights_is_named_as_such(tmp_path: Path) -> None:
    import numpy as np

    checkpoint = tmp_path / "run.pt"  # what cadpu.train writes: optimiser and random states beside the networks
    torch.save({"step": 3, "generator": Generator().state_dict(), "discriminator": {}, "opt_g": {}, "opt_d": {},
                "rng": np.random.default_rng(0).bit_generator.state, "elapsed": 1.0}, checkpoint)
    with pytest.raises(weights.WeightsError, match="run.pt: a training checkpoint of `python -m cadpu.train`"):
        weights.load_generator(checkpoint)
    # a fine-tuning run's checkpoint (`kitti-pu finetune --out tuned.pt` keeps it in tuned.pt.run/)
    # was sent to cadpu.train's generator.pt and --weights-out (a researcher's trial)
    (tmp_path / "tuned.pt.run").mkdir()
    finetuned = tmp_path / "tuned.pt.run" / "checkpoint.pt"
    finetuned.write_bytes(checkpoint.read_bytes())
    with pytest.raises(weights.WeightsError, match=r"the checkpoint of a `kitti-pu finetune` run .* writes its weights "
                                                   rf"to {tmp_path / 'tuned.pt'}, its --out"):
        weights.load_generator(finetuned)
    assert not weights.is_training_checkpoint(tmp_path / "missing.pt")
    other = tmp_path / "other.pt"
    torch.save({"something": 1}, other)
    with pytest.raises(weights.WeightsError, match="other.pt: not a CAD-PU weights file"):
        weights.load_generator(other)


def test_a_file_that_is_not_weights_is_refused_in_one_line(tmp_path: Path) -> None:
    garbage = tmp_path / "garbage.pt"
    garbage.write_text("garbage\n")
    with pytest.raises(weights.WeightsError) as info:
        weights.load_generator(garbage)
    assert "\n" not in str(info.value) and "garbage.pt: not a CAD-PU weights file (not a torch file" in str(info.value)


def test_a_folder_a_cut_file_and_an_empty_checksum_are_each_named_for_what_they_are(tmp_path: Path) -> None:
    # "weights file not found" for the folder, torch's miniz paragraph for the cut file, and a
    # "checksum mismatch" against nothing for the empty .sha256
    with pytest.raises(weights.WeightsError, match=f"{tmp_path}: a folder, not a weights file"):
        weights.load_generator(tmp_path)
    whole = tmp_path / "whole.pt"
    weights.save(Generator(ratio=4), whole)
    cut = tmp_path / "cut.pt"
    cut.write_bytes(whole.read_bytes()[: len(whole.read_bytes()) // 2])
    with pytest.raises(weights.WeightsError) as info:
        weights.load_generator(cut)
    assert str(info.value) == f"{cut}: not a CAD-PU weights file (not a torch file, or one cut short)"
    Path(f"{whole}.sha256").write_text("")
    with pytest.raises(weights.WeightsError, match=r"its checksum file whole.pt.sha256 is empty"):
        weights.load_generator(whole)
