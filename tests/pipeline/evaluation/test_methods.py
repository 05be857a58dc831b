"""pipeline.evaluation.methods: which file the weights under test are compared with, and that
the evaluation names both files (the rows' labels say what they are, not where a file came from)."""

from __future__ import annotations

from pathlib import Path

import torch

from cadpu import weights
from cadpu.network import Generator
from pipeline.config import PipelineConfig
from pipeline.evaluation.methods import NETWORK, TWIN, comparison_weights, load_models


def _saved(path: Path, meta: dict | None = None) -> Path:
    torch.manual_seed(0)
    weights.save(Generator(ratio=4), path, meta)
    return path


def test_a_shipped_file_is_compared_with_its_twin_of_the_other_alpha() -> None:
    path, reason = comparison_weights(weights.LIDAR_UNIFORM_WEIGHTS, None)
    assert path == weights.LIDAR_WEIGHTS and "other alpha" in reason


def test_a_file_of_ones_own_is_compared_with_the_file_it_started_from(tmp_path: Path) -> None:
    tuned = _saved(tmp_path / "tuned.pt", {"init_weights": "cadpu_r4_lidar"})
    assert comparison_weights(tuned, None) == (weights.LIDAR_WEIGHTS, "the file it was trained from")
    scratch = _saved(tmp_path / "scratch.pt")  # trained from a random start: the pipeline's default
    default = weights.resolve(PipelineConfig().upsample.weights)
    assert comparison_weights(scratch, None) == (default, "the pipeline's default")
    gone = _saved(tmp_path / "orphan.pt", {"init_weights": str(tmp_path / "deleted.pt")})
    assert comparison_weights(gone, None)[0] == default
    assert comparison_weights(tuned, "cadpu_r4") == (weights.DEFAULT_WEIGHTS, "--twin-weights")


def test_a_file_whose_starting_file_was_replaced_since_is_compared_with_the_default(tmp_path: Path) -> None:
    # the path alone was kept: another model saved there later was shown as "the file it was trained from"
    base = _saved(tmp_path / "base.pt")
    tuned = _saved(tmp_path / "tuned.pt", {"init_weights": str(base), "init_sha256": weights.sha256_of(base)})
    assert comparison_weights(tuned, None) == (base, "the file it was trained from")
    torch.manual_seed(1)
    weights.save(Generator(ratio=4), base)  # another model at the same path
    path, reason = comparison_weights(tuned, None)
    assert path == weights.resolve(PipelineConfig().upsample.weights) and "has changed since" in reason


def test_load_models_names_each_file_with_its_checksum(tmp_path: Path) -> None:
    tuned = _saved(tmp_path / "tuned.pt", {"init_weights": "cadpu_r4_lidar_alpha1"})
    models, described = load_models(tuned, None, PipelineConfig())
    assert set(models) == {NETWORK, TWIN}
    assert described[NETWORK] == f"{tuned} (sha256 {weights.sha256_of(tuned)[:12]})"
    assert described[TWIN].startswith(f"{weights.LIDAR_UNIFORM_WEIGHTS} (sha256 ")
    assert described[TWIN].endswith("; the file it was trained from)")


def test_a_shipped_file_given_by_a_relative_path_or_as_a_copy_is_known_by_its_twin(tmp_path: Path,
                                                                                monkeypatch) -> None:
    # "cadpu/weights/cadpu_r4.pt" was taken for a file of one's own, and compared with itself (its
    # meta's init_weights names it), with identical rows (a trial)
    import shutil

    monkeypatch.chdir(weights.DEFAULT_WEIGHTS.parent.parent.parent)
    relative = weights.DEFAULT_WEIGHTS.relative_to(Path.cwd())
    assert comparison_weights(relative, None) == (weights.UNIFORM_WEIGHTS,
                                                  "the shipped file of the same data with the other alpha")
    copy = Path(shutil.copy(weights.LIDAR_WEIGHTS, tmp_path / "mine.pt"))
    assert comparison_weights(copy, None)[0] == weights.LIDAR_UNIFORM_WEIGHTS


def test_a_twin_of_the_same_weights_is_said_to_be_so(tmp_path: Path) -> None:
    tuned = _saved(tmp_path / "tuned.pt")
    _, described = load_models(tuned, tuned, PipelineConfig())
    assert described[TWIN].endswith("--twin-weights; the same weights as CAD-PU, so their rows are the same)")


def test_both_models_take_every_setting_of_the_upsample_section() -> None:
    # the offset scale was left out here: the alpha 0.5 twin took its file's own (1.4), and
    # --set upsample.offset_scale reached neither row
    config = PipelineConfig.model_validate({"upsample": {"offset_scale": 1.2, "oversample": 2, "seed": 3}})
    models, _ = load_models("cadpu_r4_lidar_alpha1", "cadpu_r4_lidar", config)
    for model in models.values():
        assert (model.offset_scale, model.oversample, model.seed) == (1.2, 2, 3)
    defaults, _ = load_models("cadpu_r4_lidar_alpha1", "cadpu_r4_lidar", PipelineConfig())
    assert [(model.offset_scale, model.oversample) for model in defaults.values()] == [(1.0, 1), (1.0, 1)]
