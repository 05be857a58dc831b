"""Tests of self-supervised fine-tuning (`pipeline.finetune`, `kitti-pu finetune`) on small
simulated 64-ring scans in KITTI order, starting from untrained stand-in weights (`weights_file`)."""

from __future__ import annotations

import hashlib
import json
import shutil
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from cadpu.inference import Upsampler
from cadpu.scan_data import INPUT_POINTS, TRUTH_POINTS
from cadpu.synthetic.lidar import LidarModel, mount_pose, simulate_scan
from cadpu.synthetic.street import make_street
from cadpu.weights import load_generator, sha256_of
from pipeline.cli import app
from pipeline.config import PipelineConfig, load_config
from pipeline.evaluation.kitti import evaluate_scan
from pipeline.evaluation.methods import NETWORK
from pipeline.evaluation.scoring import NON_GROUND
from pipeline.finetune import HeldoutScans, finetune, scan_pairs, split_scans
from stages import load
from stages.discovery import FrameRef
from stages.errors import InputError
from stages.upsample import upsampler_settings

#: A coarse 64-beam sensor (360 firings a turn, 40 m range): about 15k points a scan.
SMALL_SENSOR = LidarModel(azimuth_steps=360, max_range=40.0)


@pytest.fixture(scope="module")
def scans() -> list[np.ndarray]:
    """Three (N, 4) float32 simulated 64-ring scans of one street, in KITTI order."""
    street = make_street(3, length_m=60.0)
    return [simulate_scan(street, mount_pose(street, x), seed=i, model=SMALL_SENSOR).points.astype(np.float32)
            for i, x in enumerate((8.0, 14.0, 20.0))]


@pytest.fixture()
def scan_folder(scans: list[np.ndarray], tmp_path: Path) -> Path:
    folder = tmp_path / "street"
    folder.mkdir()
    for index, scan in enumerate(scans):
        scan.tofile(folder / f"{index:06d}.bin")
    return folder


def _config(folder: Path, weights: Path, **finetune: object) -> PipelineConfig:
    settings = {"steps": 2, "batch_size": 2, "validate_every": 1, "checkpoint_every": 1, "threads": 1,
                "pairs_per_scan": 8, **finetune}
    return load_config(overrides={"input.path": str(folder), "upsample.weights": str(weights),
                                  **{f"finetune.{k}": v for k, v in settings.items()}})


def test_scan_pairs_have_the_network_shapes_and_unit_normals(scans: list[np.ndarray]) -> None:
    pairs = scan_pairs(scans[0], PipelineConfig(), 8, np.random.default_rng(0))
    assert 0 < len(pairs) <= 8
    assert pairs.inputs.shape[1:] == (INPUT_POINTS, 3) and pairs.truth.shape[1:] == (TRUTH_POINTS, 3)
    assert np.allclose(np.linalg.norm(pairs.truth_normals, axis=-1), 1.0, atol=1e-4)
    # normalised to the input's unit sphere: the input reaches radius 1, the truth stays near it
    assert np.allclose(np.linalg.norm(pairs.inputs, axis=-1).max(axis=1), 1.0, atol=1e-4)
    assert np.linalg.norm(pairs.truth, axis=-1).max() < 3.0


def test_scan_pairs_refuse_a_scan_without_ring_order(scans: list[np.ndarray]) -> None:
    shuffled = scans[0][np.random.default_rng(0).permutation(len(scans[0]))]
    with pytest.raises(InputError, match="finetune.*rings"):
        scan_pairs(shuffled, PipelineConfig(), 8, np.random.default_rng(0), source="x/000000.bin")


def test_scan_pairs_refuse_a_scan_of_fewer_rings_than_kitti_s(scans: list[np.ndarray]) -> None:
    from stages.rings import keep_rings, recover_rings

    # a 16-ring scan gave 79 pairs of a 4-to-16 task, without a word (a training user's trial)
    sixteen = keep_rings(scans[0], recover_rings(scans[0]), 4)
    with pytest.raises(InputError, match="16 laser rings found in the point order; fine-tuning takes full 64-ring "):
        scan_pairs(sixteen, PipelineConfig(), 8, np.random.default_rng(0), source="x/000000.bin")


def test_split_holds_out_scans_spread_through_the_list() -> None:
    refs = [FrameRef("bin", "s", i, f"{i:06d}.bin", i) for i in range(8)]
    train, held = split_scans(refs, 0.25)
    assert [r.index for r in held] == [2, 5] and len(train) == 6
    assert split_scans(refs[:1], 0.25) == (refs[:1], [])
    assert [r.index for r in split_scans(refs[:3], 0.25)[1]] == [1]
    assert split_scans(refs, 0.0)[1] == []


def test_heldout_score_is_the_non_ground_chamfer_eval_kitti_reports(scan_folder: Path, weights_file: Path) -> None:
    config = load_config(overrides={"upsample.weights": str(weights_file)})
    ref = load.discover(scan_folder)[0]
    scorer = HeldoutScans([ref], config)
    generator = load_generator(weights_file)[0]
    score = scorer(generator)
    assert scorer(generator) == score  # deterministic: two scores differ only through the weights
    network = Upsampler(weights_file, **{**upsampler_settings(config.upsample), "engine": "eager"})
    rows, _ = evaluate_scan(load.read_scan(ref.source), ref.key, {NETWORK: network}, config, ref.source)
    expected = next(r.score.chamfer for r in rows if r.method == NETWORK and r.region == NON_GROUND)
    assert score == pytest.approx(expected, rel=1e-6)


def test_finetune_writes_weights_with_provenance_and_resumes(scan_folder: Path, weights_file: Path,
                                                              tmp_path: Path) -> None:
    out = tmp_path / "tuned.pt"
    result = finetune(_config(scan_folder, weights_file), out, progress=False)
    generator, checksum, meta = load_generator(out)
    assert checksum == result.checksum == sha256_of(out)
    assert meta["finetuned_from"]["sha256"] == sha256_of(weights_file)
    assert meta["init_weights"] == str(weights_file.resolve())  # found from any folder (eval-kitti's twin)
    assert meta["finetune_heldout_scans"] == [str(scan_folder / "000001.bin")]
    assert sorted(meta["finetune_scans"]) == [str(scan_folder / "000000.bin"), str(scan_folder / "000002.bin")]
    assert result.steps == 2 and result.train_pairs > 0 and result.heldout_scans == 1
    # the written weights are those of the best held-out score, step 0 (the base) included
    steps, scores = np.loadtxt(result.run_dir / "validation.csv", delimiter=",", skiprows=1, usecols=(0, 1)).T
    assert list(steps) == [0, 1, 2]
    assert result.best_step == int(steps[np.argmin(scores)]) == meta["weights_of_step"]
    assert result.heldout_after == pytest.approx(scores.min(), rel=1e-4)
    assert result.heldout_before == pytest.approx(scores[0], rel=1e-4)
    assert meta["samples_seen"] == result.best_step * 2

    with pytest.raises(FileExistsError, match="--resume"):
        finetune(_config(scan_folder, weights_file), out, progress=False)
    resumed = finetune(_config(scan_folder, weights_file, steps=3), out, resume=True, progress=False)
    assert resumed.steps == 3
    # it named a fingerprint, not the setting (a new-user trial)
    with pytest.raises(ValueError, match=r"other scans, settings or base weights \(finetune.lr 0.0003 -> 0.01\); "
                                         r"resume it with the same ones \(all but finetune.checkpoint_every"):
        finetune(_config(scan_folder, weights_file, steps=4, lr=1e-2), out, resume=True, progress=False)


def test_a_resume_without_a_run_is_refused_before_any_work_and_leaves_nothing(
        scan_folder: Path, weights_file: Path, tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    out = tmp_path / "never.pt"
    with pytest.raises(FileNotFoundError, match="no checkpoint to resume"):
        finetune(_config(scan_folder, weights_file), out, resume=True, progress=False)
    assert not out.exists() and not out.with_name("never.pt.run").exists()  # no run folder with a data.json
    # a damaged checkpoint: refused naming it, before any pair is cut (a traceback after them before: a trial)
    run_dir = out.with_name("never.pt.run")
    run_dir.mkdir()
    (run_dir / "checkpoint.pt").write_bytes(b"PK\x03\x04 cut short")
    capsys.readouterr()
    with pytest.raises(ValueError, match=f"{run_dir / 'checkpoint.pt'}: not a readable checkpoint"):
        finetune(_config(scan_folder, weights_file), out, resume=True, progress=False)
    assert "pairs" not in capsys.readouterr().out


def test_an_out_path_that_is_a_folder_is_refused_before_any_work(scan_folder: Path, weights_file: Path,
                                                                  tmp_path: Path) -> None:
    folder = tmp_path / "here" / "ftdir"
    folder.mkdir(parents=True)
    with pytest.raises(ValueError, match=f"--out: {folder} is a folder"):  # after the training, before
        finetune(_config(scan_folder, weights_file), folder, progress=False)
    assert sorted(p.name for p in folder.parent.iterdir()) == ["ftdir"]  # no run folder, no temporary


def test_an_out_path_that_is_the_base_weights_is_refused_before_any_work(scan_folder: Path, weights_file: Path,
                                                                         tmp_path: Path) -> None:
    # it replaced the base file, and every resume was then refused for changed base weights
    base = tmp_path / "base.pt"
    shutil.copy(weights_file, base)
    shutil.copy(f"{weights_file}.sha256", f"{base}.sha256")
    before = base.read_bytes()
    with pytest.raises(ValueError, match=f"--out {base} is the base weights file"):
        finetune(_config(scan_folder, base), base, weights=base, progress=False)
    assert base.read_bytes() == before and not base.with_name("base.pt.run").exists()


def test_a_resume_with_more_steps_changes_only_the_steps(scan_folder: Path, weights_file: Path, tmp_path: Path,
                                                         capsys: pytest.CaptureFixture) -> None:
    out = tmp_path / "tuned.pt"
    finetune(_config(scan_folder, weights_file), out, progress=False)
    capsys.readouterr()
    finetune(_config(scan_folder, weights_file, steps=3), out, resume=True, progress=False)
    said = capsys.readouterr().err
    assert "steps 2 -> 3" in said and "decay_every" not in said and "adversarial_from" not in said
    assert said.startswith("kitti-pu finetune: resuming at step 2")  # not "cadpu.train", a command not run
    # the pipeline settings its held-out scans are scored with, changed: refused before any work
    # (scores of two pipelines were ranked against each other to pick the best weights: a trial)
    config = _config(scan_folder, weights_file, steps=4)
    changed = config.model_copy(update={"snap": config.snap.model_copy(update={"range_tolerance": None})})
    with pytest.raises(ValueError, match=r"scores its held-out scans with other pipeline settings now "
                                         r"\(snap.range_tolerance 0.05 -> None\)"):
        finetune(changed, out, resume=True, progress=False)


def test_a_chained_finetune_records_the_scans_of_every_run_before_it(scan_folder: Path, weights_file: Path,
                                                                     tmp_path: Path) -> None:
    # a file fine-tuned from a fine-tuned file recorded only its own scans, so eval-kitti's "not
    # held out" warning missed those the first run trained on (a trial)
    first = tmp_path / "first.pt"
    finetune(_config(scan_folder, weights_file, steps=1), first, progress=False)
    other = tmp_path / "other"
    other.mkdir()
    shutil.copy(scan_folder / "000001.bin", other / "000000.bin")
    shutil.copy(scan_folder / "000002.bin", other / "000001.bin")
    second = tmp_path / "second.pt"
    finetune(_config(other, first, steps=1, validation_share=0.0), second, progress=False)
    assert load_generator(second)[2]["finetune_scans"] == [
        str(scan_folder / "000000.bin"), str(scan_folder / "000002.bin"),
        str(other / "000000.bin"), str(other / "000001.bin")]
    # and by content, each once: other/000000.bin is a copy of a scan the first run did not train on
    from stages.discovery import content_digest

    assert load_generator(second)[2]["finetune_scan_digests"] == [
        content_digest(scan_folder / f"{index:06d}.bin") for index in (0, 2, 1)]


def test_cli_finetunes_and_run_uses_the_file(scan_folder: Path, weights_file: Path, tmp_path: Path) -> None:
    out = tmp_path / "tuned.pt"
    common = ["--set", "finetune.batch_size=2", "--set", "finetune.pairs_per_scan=4", "--set", "finetune.threads=1"]
    result = CliRunner().invoke(app, ["finetune", str(scan_folder), "--out", str(out), "--weights", str(weights_file),
                                      "--steps", "1", "--no-progress", "--last", "1", *common])
    assert result.exit_code == 0, result.output
    assert f"--weights {out}" in result.output and "held-out non-ground Chamfer" in result.output
    # one training scan (000000) and one held out (000001): --last selects
    assert load_generator(out)[2]["finetune_scans"] == [str(scan_folder / "000000.bin")]
    configured = CliRunner().invoke(app, ["config", "--set", f"upsample.weights={out}"])
    assert configured.exit_code == 0, configured.output

    missing = CliRunner().invoke(app, ["finetune", str(tmp_path / "nowhere"), "--out", str(out), *common])
    assert missing.exit_code == 2 and "nowhere" in missing.output
    shuffled_folder = tmp_path / "shuffled"
    shuffled_folder.mkdir()
    for name in ("000000.bin", "000001.bin"):
        points = np.fromfile(scan_folder / name, np.float32).reshape(-1, 4)
        points[np.random.default_rng(0).permutation(len(points))].tofile(shuffled_folder / name)
    shuffled = CliRunner().invoke(app, ["finetune", str(shuffled_folder), "--out", str(tmp_path / "s.pt"), "--weights",
                                        str(weights_file), "--steps", "1", "--no-progress", *common])
    assert shuffled.exit_code == 2, shuffled.output
    assert "kitti-pu: [finetune] " in shuffled.output and "laser rings found" in shuffled.output  # named once

    # one scan: nothing to hold out, said in words, not "nan m"
    single = CliRunner().invoke(app, ["finetune", str(scan_folder), "--out", str(tmp_path / "one.pt"), "--weights",
                                      str(weights_file), "--steps", "1", "--no-progress", "--last", "0", *common])
    assert single.exit_code == 0, single.output
    assert "no scan held out" in single.output and "nan" not in single.output


def test_a_shipped_base_is_recorded_by_its_name() -> None:
    from cadpu.weights import LIDAR_UNIFORM_WEIGHTS, portable_name

    assert portable_name(LIDAR_UNIFORM_WEIGHTS) == "cadpu_r4_lidar_alpha1"


def test_finetune_trains_the_snapped_objective_and_its_settings_change_the_fingerprint(
        scan_folder: Path, weights_file: Path, tmp_path: Path) -> None:
    out = tmp_path / "tuned.pt"
    config = _config(scan_folder, weights_file, objective="snapped_chamfer", augmentation="azimuth")
    result = finetune(config, out, progress=False)
    recipe = load_generator(out)[2]["recipe"]
    assert (recipe["objective"], recipe["augmentation"]) == ("snapped_chamfer", "azimuth")
    logged = np.genfromtxt(result.run_dir / "log.csv", delimiter=",", names=True)
    assert np.isnan(logged["emd"]).all() and np.isfinite(logged["snapped_chamfer"]).all()
    with pytest.raises(ValueError, match=r"finetune.objective 'snapped_chamfer' -> 'emd'"):
        finetune(_config(scan_folder, weights_file, steps=3, augmentation="azimuth"), out, resume=True, progress=False)


def test_the_fingerprint_of_default_settings_is_the_one_recorded_before_the_objective_existed(
        scan_folder: Path, weights_file: Path) -> None:
    from pipeline.finetune import RESUMABLE_CHANGES, _data_fingerprint

    config = _config(scan_folder, weights_file)
    before = {"ground": config.ground.model_dump(mode="json"), "tile": config.tile.model_dump(mode="json"),
              "finetune": config.finetune.model_dump(mode="json",
                                                     exclude=RESUMABLE_CHANGES | {"objective", "augmentation"})}
    content = {"scans": [], "base": "x", **before}
    expected = hashlib.sha256(json.dumps(content, sort_keys=True).encode()).hexdigest()[:16]
    assert _data_fingerprint([], config, "x")["fingerprint"] == expected


def test_an_out_path_among_the_shipped_weights_is_refused_before_any_work(
        scan_folder: Path, weights_file: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    # `--out cadpu/weights/cadpu_r4.pt` replaced the shipped file and its .sha256, so Upsampler()
    # then loaded the fine-tuned network with a checksum that matched (a trial). The package's
    # folder is stood in for by a copy, so that the code before the fix overwrites nothing real.
    import cadpu.weights as weights_module

    shipped = tmp_path / "package_weights"
    shipped.mkdir()
    for name in ("cadpu_r4.pt", "cadpu_r4.pt.sha256"):
        shutil.copy(weights_module.WEIGHTS_DIR / name, shipped / name)
    monkeypatch.setattr(weights_module, "WEIGHTS_DIR", shipped)
    before = (shipped / "cadpu_r4.pt").read_bytes()
    for out in (shipped / "cadpu_r4.pt", shipped / "mine.pt"):
        with pytest.raises(ValueError, match=f"--out: {out} is in the folder of the weights shipped with kitti-pu"):
            finetune(_config(scan_folder, weights_file), out, progress=False)
    assert (shipped / "cadpu_r4.pt").read_bytes() == before
    assert sorted(p.name for p in shipped.iterdir()) == ["cadpu_r4.pt", "cadpu_r4.pt.sha256"]


def test_an_out_path_that_holds_a_checkpoint_or_another_file_is_refused_before_any_work(
        scan_folder: Path, weights_file: Path, tmp_path: Path) -> None:
    # `--out other.pt.run/checkpoint.pt` replaced that run's checkpoint with weights, and the run
    # could no longer be resumed (a trial); any other file was replaced as silently
    first = tmp_path / "first.pt"
    finetune(_config(scan_folder, weights_file, steps=1), first, progress=False)
    checkpoint = tmp_path / "first.pt.run" / "checkpoint.pt"
    notes = tmp_path / "notes.txt"
    notes.write_text("my notes")
    for target, said in ((checkpoint, "a training checkpoint, which it would destroy"), (notes, "not a weights file")):
        before = target.read_bytes()
        with pytest.raises(ValueError, match=f"--out: {target} exists and is {said}; give another file"):
            finetune(_config(scan_folder, weights_file, steps=1), target, progress=False)
        assert target.read_bytes() == before
    # an existing weights file is replaced, as before: a new run writing its result where an old one was
    shutil.rmtree(tmp_path / "first.pt.run")
    assert finetune(_config(scan_folder, weights_file, steps=1), first, progress=False).weights == first
    # and so are an empty placeholder (mktemp's) and weights whose meta merely names an optimiser's
    # state (their bytes were searched for it: a reviewer's find)
    from cadpu.weights import check_weights_target, save

    placeholder = tmp_path / "placeholder.pt"
    placeholder.touch()
    named = tmp_path / "named.pt"
    save(load_generator(weights_file)[0], named, {"origin": "/data/opt_gnss_run/discriminator"})
    for target in (placeholder, named):
        assert check_weights_target(target, "--out") == target


def test_a_fine_tuning_checkpoint_is_resumed_by_finetune_alone(scan_folder: Path, weights_file: Path,
                                                               tmp_path: Path) -> None:
    # `python -m cadpu.train FILE.run/recipe.yaml --resume` went on training it on synthetic
    # patches and wrote weights without its provenance (a researcher's trial)
    from cadpu.train import Recipe, train

    out = tmp_path / "tuned.pt"
    finetune(_config(scan_folder, weights_file, steps=1), out, progress=False)
    recipe = Recipe.from_yaml(tmp_path / "tuned.pt.run" / "recipe.yaml", {"steps": 2})
    with pytest.raises(ValueError, match=r"the checkpoint of a `kitti-pu finetune` run; continue it with "
                                         r"kitti-pu finetune \.\.\. --resume"):
        train(recipe, tmp_path / "elsewhere.pt", progress=False, resume=True)
    assert not (tmp_path / "elsewhere.pt").exists()
    # and the other way: a checkpoint of python -m cadpu.train where a fine-tuning run keeps its own
    import torch

    checkpoint = tmp_path / "tuned.pt.run" / "checkpoint.pt"
    torch.save({**torch.load(checkpoint, weights_only=False), "caller": "cadpu.train"}, checkpoint)
    with pytest.raises(ValueError, match=r"is the checkpoint of a `cadpu.train` run; continue it with "
                                         r"python -m cadpu.train \.\.\. --resume, or choose another --out"):
        finetune(_config(scan_folder, weights_file, steps=2), out, resume=True, progress=False)


def test_a_resume_past_its_steps_is_refused_in_finetune_s_words_before_any_scan_is_read(
        scan_folder: Path, weights_file: Path, tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    # it said "past the recipe's steps" after every scan had been read and cut (a trial)
    out = tmp_path / "tuned.pt"
    finetune(_config(scan_folder, weights_file, steps=2), out, progress=False)
    capsys.readouterr()
    with pytest.raises(ValueError, match=f"{tmp_path / 'tuned.pt.run'} is at step 2, past --steps 1; give --steps "
                                         "of at least 2"):
        finetune(_config(scan_folder, weights_file, steps=1), out, resume=True, progress=False)
    assert "pairs" not in capsys.readouterr().out


def test_a_run_refused_or_interrupted_while_its_scans_are_cut_leaves_no_run_folder(
        scan_folder: Path, weights_file: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    # both left FILE.run/ holding a data.json alone, and Ctrl-C exited 130 without a word (a trial)
    import pipeline.finetune as finetune_module

    shuffled_folder = tmp_path / "shuffled"
    shuffled_folder.mkdir()
    for name in ("000000.bin", "000001.bin"):
        points = np.fromfile(scan_folder / name, np.float32).reshape(-1, 4)
        points[np.random.default_rng(0).permutation(len(points))].tofile(shuffled_folder / name)
    with pytest.raises(InputError, match="laser rings found"):
        finetune(_config(shuffled_folder, weights_file), tmp_path / "refused.pt", progress=False)
    assert not (tmp_path / "refused.pt.run").exists()

    def interrupted(*args: object, **kwargs: object) -> None:
        raise KeyboardInterrupt

    monkeypatch.setattr(finetune_module, "collect_pairs", interrupted)
    result = CliRunner().invoke(app, ["finetune", str(scan_folder), "--out", str(tmp_path / "stopped.pt"),
                                      "--weights", str(weights_file), "--no-progress"])
    assert result.exit_code == 130
    assert "finetune: interrupted before training began" in result.output
    assert not (tmp_path / "stopped.pt.run").exists() and not (tmp_path / "stopped.pt").exists()
    # once training has begun, a Ctrl-C outside its steps (here at the last save) is not "nothing trained"
    import cadpu.train

    monkeypatch.undo()
    monkeypatch.setattr(cadpu.train, "save", interrupted)
    result = CliRunner().invoke(app, ["finetune", str(scan_folder), "--out", str(tmp_path / "late.pt"), "--weights",
                                      str(weights_file), "--no-progress", "--steps", "1",
                                      "--set", "finetune.batch_size=2", "--set", "finetune.pairs_per_scan=4"])
    assert result.exit_code == 130
    assert "finetune: interrupted; the run's last checkpoint, if it has one, stands" in result.output
    assert (tmp_path / "late.pt.run" / "checkpoint.pt").is_file()


def test_held_out_scans_the_weights_trained_on_are_said_and_recorded_by_content(
        scan_folder: Path, weights_file: Path, tmp_path: Path) -> None:
    # a held-out scan that was a copy of a training scan chose the weights unsaid, and eval-kitti
    # knew the scans that chose them by path alone (a trial)
    from pipeline.evaluation.kitti import _scans_that_chose
    from stages.discovery import content_digest

    copied = tmp_path / "copied"
    shutil.copytree(scan_folder, copied)
    shutil.copy(copied / "000000.bin", copied / "000001.bin")  # 000001 is the one held out of three
    said: list[str] = []
    out = tmp_path / "tuned.pt"
    finetune(_config(copied, weights_file, steps=1), out, progress=False, log=said.append)
    assert [line for line in said if "warning" in line] == [
        f"finetune: warning: held-out scan {copied / '000001.bin'} is a copy of a scan these weights have trained on "
        "(here or in the run of their base): its score, which chooses the weights written, is not a held-out score"]
    meta = load_generator(out)[2]
    assert meta["finetune_heldout_digests"] == [content_digest(copied / "000001.bin")]

    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    shutil.copy(copied / "000001.bin", elsewhere / "000007.bin")
    refs = load.discover(elsewhere)
    assert _scans_that_chose(refs, {NETWORK: Upsampler(out)}) == [str(elsewhere / "000007.bin")]


def test_a_fine_tuned_file_records_its_lineage_by_absolute_path_and_no_synthetic_data(
        scan_folder: Path, weights_file: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    # a trial: finetuned_from kept the path as typed (relative), a file tuned from a tuned file named
    # only its parent, the recipe said 200 procedural meshes, the hardware only "x86_64", and
    # `kitti-pu info` gave a tuned file's samples as though trained on them alone
    from cadpu.train import processor_name
    from pipeline.info import describe_model

    shutil.copy(weights_file, tmp_path / "base.pt")
    shutil.copy(f"{weights_file}.sha256", tmp_path / "base.pt.sha256")
    monkeypatch.chdir(tmp_path)
    finetune(_config(scan_folder, Path("base.pt"), steps=1), Path("first.pt"), progress=False)
    finetune(_config(scan_folder, Path("first.pt"), steps=1), Path("second.pt"), progress=False)
    meta = load_generator(tmp_path / "second.pt")[2]
    assert meta["finetuned_from"] == {"weights": str(tmp_path / "first.pt"), "sha256": sha256_of(tmp_path / "first.pt")}
    assert meta["finetune_lineage"] == [{"weights": str(tmp_path / "base.pt"), "sha256": sha256_of(weights_file)},
                                        meta["finetuned_from"]]
    assert meta["recipe"]["data"] is None  # its data are the scans its own keys name
    # a base fine-tuned by a version before the lineage was kept: its own parent is not lost
    from cadpu.weights import save

    generator, _, first_meta = load_generator(tmp_path / "first.pt")
    save(generator, tmp_path / "older.pt", {k: v for k, v in first_meta.items() if k != "finetune_lineage"})
    finetune(_config(scan_folder, Path("older.pt"), steps=1), Path("third.pt"), progress=False)
    assert [entry["weights"] for entry in load_generator(tmp_path / "third.pt")[2]["finetune_lineage"]] == [
        str(tmp_path / "base.pt"), str(tmp_path / "older.pt")]
    assert processor_name() in meta["segments"][0]["hardware"] and processor_name() not in ("", "x86_64")
    described = describe_model(sha256_of(tmp_path / "second.pt"), str(tmp_path / "second.pt"))
    assert (described["finetuned_from"], described["finetune_scans"]) == (str(tmp_path / "first.pt"), 2)
    # and `kitti-pu info` of a frame the file made says so
    from pipeline.chain import Chain
    from pipeline.info import folder_info, format_info

    made = load_config(overrides={"input.path": str(scan_folder), "upsample.weights": str(tmp_path / "second.pt"),
                                  "output.dir": str(tmp_path / "out")})
    Chain(made).run(load.discover(scan_folder)[0])
    shown = format_info(folder_info(tmp_path / "out"))
    assert f"(fine-tuned from {tmp_path / 'first.pt'}; 2 real scans over its fine-tuning runs)" in shown


def test_a_run_stopped_by_max_seconds_says_so_in_its_result_line(scan_folder: Path, weights_file: Path,
                                                                 tmp_path: Path) -> None:
    # its result line read as a finished run's, exit 0 and all (a trial); a stderr line alone said it stopped
    result = CliRunner().invoke(app, ["finetune", str(scan_folder), "--out", str(tmp_path / "t.pt"), "--weights",
                                      str(weights_file), "--steps", "3", "--max-seconds", "0", "--no-progress",
                                      "--set", "finetune.batch_size=2", "--set", "finetune.pairs_per_scan=4"])
    assert result.exit_code == 0, result.output
    assert "; 1 step of 3 (stopped by --max-seconds; --resume continues);" in result.stdout


def test_a_run_whose_starting_weights_scored_best_says_the_file_holds_them_unchanged(
        scan_folder: Path, weights_file: Path, tmp_path: Path) -> None:
    # "0.0776 m before, 0.0776 m with the weights of step 0" left the user to work out that the new
    # file was the base network (a trial). A rate of 1e-12 leaves the step's score the base's, and a
    # tie keeps the earlier step.
    result = CliRunner().invoke(app, ["finetune", str(scan_folder), "--out", str(tmp_path / "t.pt"), "--weights",
                                      str(weights_file), "--steps", "1", "--no-progress", "--set", "finetune.lr=1e-12",
                                      "--set", "finetune.batch_size=2", "--set", "finetune.pairs_per_scan=4"])
    assert result.exit_code == 0, result.output
    assert load_generator(tmp_path / "t.pt")[2]["weights_of_step"] == 0
    assert "with the weights of step 0; no step scored better than the starting weights, so the file holds them " \
           "unchanged" in result.stdout
