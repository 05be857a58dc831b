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
    weights.save(generator, path)  # with a matching .sha256
    with pytest.raises(weights.WeightsError, match="non-finite") as info:
        weights.load_generator(path)
    assert str(path) in str(info.value) and name in str(info.value)


def test_finite_weights_still_load(tmp_path: Path) -> None:
    path = tmp_path / "fine.pt"
    weights.save(Generator(ratio=4), path)
    generator, digest, _ = weights.load_generator(path)
    assert digest == weights.sha256_of(path) and not generator.training
