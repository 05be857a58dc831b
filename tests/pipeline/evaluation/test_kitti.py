"""Tests of the 16-to-64-beam evaluation (pipeline.evaluation) and its CLI verb, on a small
simulated scan in KITTI order, with untrained stand-in weights (`weights_file`, conftest.py)."""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from cadpu.synthetic.lidar import LidarModel, mount_pose, simulate_scan
from cadpu.metrics import chamfer_distance, hausdorff_distance, voxel_f1
from cadpu.weights import sha256_of
from cadpu.synthetic.street import make_street
from pipeline.cli import app
from pipeline.config import PipelineConfig
from stages import fill, snap, upsample
from pipeline.evaluation.kitti import evaluate_kitti, evaluate_scan
from pipeline.evaluation.methods import INPUT, COMPARED_METHODS, MIDPOINT, NETWORK, RANGE_IMAGE, TWIN, MidpointUpsampler, thin_scan
from pipeline.evaluation.report import per_scan_comparison
from pipeline.evaluation.scoring import NON_GROUND, REGIONS, WHOLE, Reference, Row, Score
from stages import ground
from stages.discovery import bin_sequence_name
from stages.errors import InputError
from stages.rings import recover_rings

#: A coarse 64-beam sensor (360 firings a turn, 40 m range): about 15k points, evaluated in seconds.
SMALL_SENSOR = LidarModel(azimuth_steps=360, max_range=40.0)


@pytest.fixture(scope="module")
def scan() -> np.ndarray:
    """(N, 4) float32 simulated 64-ring scan of a street, in KITTI order."""
    street = make_street(3, length_m=60.0)
    return simulate_scan(street, mount_pose(street, 10.0), seed=2, model=SMALL_SENSOR).points


@pytest.fixture(scope="module")
def scan_folder(scan: np.ndarray, tmp_path_factory: pytest.TempPathFactory) -> Path:
    folder = tmp_path_factory.mktemp("eval_scans") / "street"
    folder.mkdir()
    scan.astype(np.float32).tofile(folder / "000000.bin")
    return folder


@pytest.fixture(scope="module")
def cli_run(scan_folder: Path, weights_file: Path, tmp_path_factory: pytest.TempPathFactory):
    out = tmp_path_factory.mktemp("eval_out")
    result = CliRunner().invoke(app, ["eval-kitti", str(scan_folder), "--out", str(out), "--weights",
                                      str(weights_file), "--uniform-weights", str(weights_file), "--frames", "1"])
    return result, out


def _rows(out: Path) -> list[dict[str, str]]:
    with (out / "eval_kitti.csv").open() as handle:
        return list(csv.DictReader(handle))


def _get(rows: list[dict[str, str]], method: str, region: str, scan: str = "mean") -> dict[str, str]:
    return next(r for r in rows if r["method"] == method and r["region"] == region and r["scan"] == scan)


def test_cli_prints_the_table_and_writes_csv_and_png(cli_run, scan_folder: Path, weights_file: Path) -> None:
    result, out = cli_run
    assert result.exit_code == 0, result.output
    for method in COMPARED_METHODS:
        assert method in result.output
    assert "non-ground region" in result.output and "whole region" in result.output
    assert (out / "eval_kitti.png").stat().st_size > 10_000
    rows = _rows(out)
    assert len(rows) == 2 * len(COMPARED_METHODS) * len(REGIONS)  # the scan, then the mean
    assert {(r["method"], r["region"]) for r in rows} == {(m, g) for m in COMPARED_METHODS for g in REGIONS}
    assert {r["scan"] for r in rows} == {f"bin/{bin_sequence_name(scan_folder)}/000000", "mean"}
    assert f"{NETWORK} against each method, non-ground region, per scan" in result.output
    assert f"{NETWORK}: {weights_file} (sha256 " in result.output  # which file each network row ran
    assert f"{TWIN}: {weights_file} (sha256 " in result.output
    assert f"{RANGE_IMAGE:<20} CD lower on " in result.output
    # what made the rows, beside them: the CSV alone named no weights nor settings (a trial)
    import json

    record = json.loads((out / "eval_kitti.json").read_text())
    assert f"record: {out / 'eval_kitti.json'}" in result.output
    assert record["weights"][NETWORK].startswith(f"{weights_file} (sha256 ")
    # the whole checksum, and every path absolute (a relative one named nothing from elsewhere: a trial)
    assert record["weights_sha256"] == {NETWORK: sha256_of(weights_file), TWIN: sha256_of(weights_file)}
    assert record["scans"] == [f"bin/{bin_sequence_name(scan_folder)}/000000"] and record["not_evaluated"] == []
    assert record["config"]["snap"] == PipelineConfig().snap.model_dump(mode="json")
    assert record["config"]["upsample"]["weights"] == str(weights_file.resolve())  # what ran, not the default


def test_metrics_are_sane(cli_run) -> None:
    _, out = cli_run
    rows = _rows(out)
    for row in rows:
        assert 0.0 <= float(row["precision"]) <= 1.0 and 0.0 <= float(row["recall"]) <= 1.0
        assert float(row["chamfer"]) >= 0.0 and float(row["hd95"]) <= float(row["hausdorff"])
    for region in REGIONS:
        thinned = _get(rows, INPUT, region)
        assert float(thinned["precision"]) == 1.0  # the input is a subset of the full scan
        assert float(thinned["recall"]) < 0.6  # ... that misses most of its voxels
    # interpolating rings recovers voxels the input misses
    assert float(_get(rows, RANGE_IMAGE, WHOLE)["recall"]) > float(_get(rows, INPUT, WHOLE)["recall"])


def test_full_scan_against_itself_scores_perfectly(scan: np.ndarray) -> None:
    mask = ground.segment(scan).mask
    scores = Reference(scan, mask).score(scan)
    for region in REGIONS:
        assert scores[region].chamfer == 0.0 and scores[region].hausdorff == 0.0
        assert scores[region].f1 == 1.0
    assert scores[NON_GROUND].points == int((~mask).sum())
    assert scores[WHOLE].points == len(scan)


def test_whole_region_score_matches_cadpu_metrics(scan: np.ndarray) -> None:
    reference = scan[:, :3].astype(np.float64)
    predicted = reference[::3] + np.random.default_rng(0).normal(scale=0.05, size=reference[::3].shape)
    score = Reference(scan, np.zeros(len(scan), bool)).score(predicted)[WHOLE]
    assert score.chamfer == pytest.approx(chamfer_distance(predicted, reference))
    assert score.hausdorff == pytest.approx(hausdorff_distance(predicted, reference))
    assert score.hd95 == pytest.approx(hausdorff_distance(predicted, reference, percentile=95))
    assert score.f1 == pytest.approx(voxel_f1(predicted, reference, 0.1).f1)


def test_output_points_are_split_by_their_nearest_full_scan_point() -> None:
    full = np.array([[0.0, 0, 0], [10, 0, 0], [20, 0, 0]])
    is_ground = np.array([True, False, False])
    predicted = np.array([[0.4, 0, 0], [9.8, 0, 0], [20.5, 0, 0], [4.0, 0, 0]])
    scores = Reference(full, is_ground).score(predicted)
    assert scores[NON_GROUND].points == 2  # near the two non-ground points
    assert scores[NON_GROUND].chamfer == pytest.approx(0.5 * (0.35 + 0.35))
    assert scores[WHOLE].points == 4
    empty = Reference(full, is_ground).score(np.zeros((0, 3)))
    assert empty[WHOLE].points == 0 and np.isnan(empty[WHOLE].chamfer) and empty[WHOLE].f1 == 0.0


def test_thin_scan_keeps_every_fourth_ring(scan: np.ndarray) -> None:
    thinned, rings = thin_scan(scan)
    full_rings = recover_rings(scan)
    assert full_rings.max() == 63
    assert set(np.unique(rings).tolist()) == set(range(0, 64, 4))
    assert len(thinned) == int(np.sum(full_rings % 4 == 0))


def test_thin_scan_refuses_a_scan_without_ring_order() -> None:
    azimuth = np.linspace(0.01, 2 * np.pi - 0.01, 500)
    one_ring = np.column_stack([np.cos(azimuth), np.sin(azimuth), np.zeros(500), np.zeros(500)]).astype(np.float32)
    with pytest.raises(InputError, match="rings") as error:
        thin_scan(one_ring, "odd.bin")
    assert error.value.source == "odd.bin"


def test_thin_scan_refuses_a_shuffled_scan(scan: np.ndarray) -> None:
    shuffled = scan[np.random.default_rng(0).permutation(len(scan))]  # every other point "wraps"
    with pytest.raises(InputError, match=r"laser rings found in the point order \(needs 8 to 128"):
        thin_scan(shuffled, "shuffled.bin")


def test_thin_scan_refuses_a_reversed_scan(scan: np.ndarray) -> None:
    # stored in reverse, a scan still shows ring-like runs (a real one read as 13 "rings", one of
    # 107,592 points) and was scored as if the input held every ring
    with pytest.raises(InputError, match="turn backward") as error:
        thin_scan(scan[::-1].copy(), "reversed.bin")
    assert error.value.source == "reversed.bin"
    thin_scan(scan, "forward.bin")  # the same scan in its order is fine


@pytest.mark.parametrize("kept", ["every fourth ring", "every second ring", "one laser missing"])
def test_thin_scan_refuses_a_scan_of_other_than_64_rings(scan: np.ndarray, kept: str) -> None:
    # a 16- or 32-ring scan was thinned to 4 or 8 rings and scored as the 16-to-64 evaluation, and a
    # scan missing a laser was thinned to lasers 0, 4, 8, 13, ... (a trial)
    rings = recover_rings(scan)
    keep = {"every fourth ring": rings % 4 == 0, "every second ring": rings % 2 == 0,
            "one laser missing": rings != 30}[kept]
    found = {"every fourth ring": 16, "every second ring": 32, "one laser missing": 63}[kept]
    with pytest.raises(InputError, match=f"{found} laser rings found in the point order; the evaluation takes "
                                         "full 64-ring scans"):
        thin_scan(scan[keep], "odd.bin")


def test_the_input_range_limits_reach_the_thinned_scan(scan: np.ndarray, weights_file: Path) -> None:
    # with input.min_range below the default, the thinned frame dropped the near points again with
    # the default limits while its ring ids still counted them: a ValueError traceback (a trial)
    from cadpu.inference import Upsampler

    near = scan.copy()
    rings = recover_rings(near)
    close = np.flatnonzero(rings == 8)[:10]
    near[close, :3] *= 0.3 / np.linalg.norm(near[close, :3], axis=1, keepdims=True)  # 0.3 m out
    config = PipelineConfig().model_copy(update={"input": PipelineConfig().input.model_copy(update={"min_range": 0.1})})
    model = Upsampler(weights_file, oversample=1)
    rows, _ = evaluate_scan(near, "near", {TWIN: model, NETWORK: model}, config, "near.bin")
    assert {row.method for row in rows} == set(COMPARED_METHODS)


def test_pipeline_methods_densify_the_object_points(scan: np.ndarray, weights_file: Path) -> None:
    from cadpu.inference import Upsampler

    # every patch upsampled, every generated point kept
    config = PipelineConfig(upsample=upsample.Options(max_patch_radius=0), snap=snap.Options(enabled=False),
                            fill=fill.Options(enabled=False))
    model = Upsampler(weights_file, ratio=4, oversample=config.upsample.oversample)
    rows, clouds = evaluate_scan(scan, "street", {NETWORK: model}, config)
    assert [(r.method, r.region) for r in rows] == [(m, g) for m in (INPUT, RANGE_IMAGE, MIDPOINT, NETWORK)
                                                    for g in REGIONS]
    assert all(isinstance(r, Row) for r in rows)
    input_ground = ground.segment(clouds.input).mask
    objects, on_ground = int((~input_ground).sum()), int(input_ground.sum())
    assert objects >= 256  # enough for the pipeline to tile and upsample
    assert len(clouds.outputs[MIDPOINT]) == 4 * objects + on_ground  # inputs + 3 midpoints each
    # the inputs kept, and about 4 generated each (curvature-adaptive: a point's share varies)
    generated = len(clouds.outputs[NETWORK]) - objects - on_ground
    assert 0.85 * 4 * objects < generated < 1.15 * 4 * objects
    assert len(clouds.outputs[RANGE_IMAGE]) > len(clouds.input)


def test_with_ring_snapping_every_pipeline_method_keeps_the_input_and_adds_ring_points(scan: np.ndarray,
                                                                                      weights_file: Path) -> None:
    from cadpu.inference import Upsampler

    config = PipelineConfig(upsample=upsample.Options(max_patch_radius=0),
                            snap=snap.Options(range_tolerance=None))
    rows, clouds = evaluate_scan(scan, "street", {NETWORK: Upsampler(weights_file, ratio=4, oversample=1)}, config)
    thinned = clouds.input.astype(np.float32)
    for method in (MIDPOINT, NETWORK):
        output = clouds.outputs[method]
        # the midpoint baseline's own copies of its inputs are moved to virtual rings, so the input is re-added
        assert len(np.intersect1d(output.view("V12"), thinned.view("V12"))) == len(np.unique(thinned.view("V12")))
        assert len(output) > 2 * len(thinned)


def test_midpoint_adapter_has_the_upsampler_interface() -> None:
    patches = np.random.default_rng(1).normal(size=(2, 32, 3)).astype(np.float32)
    points, parents = MidpointUpsampler(4).upsample_patches(patches)
    assert points.shape == (2, 128, 3) and parents.shape == (2, 128)
    assert np.allclose(points[:, :32], patches)  # the inputs come first
    assert parents.max() == 31


def test_bad_inputs_name_what_is_wrong(tmp_path: Path, scan_folder: Path, weights_file: Path) -> None:
    runner = CliRunner()
    missing = runner.invoke(app, ["eval-kitti", str(tmp_path / "nowhere"), "--weights", str(weights_file),
                                  "--uniform-weights", str(weights_file)])
    assert missing.exit_code == 2 and "does not exist" in missing.output
    no_weights = runner.invoke(app, ["eval-kitti", str(scan_folder), "--out", str(tmp_path), "--weights",
                                     str(tmp_path / "none.pt"), "--uniform-weights", str(weights_file)])
    assert no_weights.exit_code == 2 and "none.pt" in no_weights.output
    with pytest.raises(InputError, match="frames"):
        evaluate_kitti(scan_folder, tmp_path, weights_file, weights_file, frames=0)
    # a file of another trained ratio: a traceback, exit 1, before
    import torch

    from cadpu import weights
    from cadpu.network import Generator

    torch.manual_seed(0)
    sixteen = tmp_path / "r16.pt"
    weights.save(Generator(ratio=16), sixteen)
    for option in ("--weights", "--twin-weights"):
        other = "--twin-weights" if option == "--weights" else "--weights"
        result = runner.invoke(app, ["eval-kitti", str(scan_folder), "--out", str(tmp_path / "ev"), option, str(sixteen),
                                     other, str(weights_file)])
        assert result.exit_code == 2 and f"{sixteen}: ratio 4 is not the trained ratio 16 or a power of it" in result.output


def _row(scan: str, method: str, chamfer: float, f1: float, region: str = NON_GROUND) -> Row:
    return Row(scan, method, region, Score(100, chamfer, 1.0, 0.5, 0.5, 0.5, f1), 0.0)


def test_per_scan_comparison_counts_the_scans_where_the_network_is_better() -> None:
    rows = [_row("a", NETWORK, 0.08, 0.55), _row("a", RANGE_IMAGE, 0.09, 0.54), _row("a", INPUT, 0.08, 0.45),
            _row("b", NETWORK, 0.07, 0.50), _row("b", RANGE_IMAGE, 0.06, 0.52), _row("b", INPUT, 0.09, 0.45),
            _row("b", RANGE_IMAGE, 0.01, 0.99, region=WHOLE),  # another region: not counted
            _row("mean", NETWORK, 0.075, 0.525), _row("mean", RANGE_IMAGE, 0.01, 0.99)]
    lines = per_scan_comparison(rows).splitlines()
    assert lines[0] == f"{NETWORK} against each method, non-ground region, per scan"
    # range-image: CD lower on a only, F1 higher on a only; input: CD tied on a (not better), lower on b
    assert lines[1].split() == [*RANGE_IMAGE.split(), "CD", "lower", "on", "1/2", "F1", "higher", "on", "1/2"]
    assert lines[2].split() == [*INPUT.split(), "CD", "lower", "on", "1/2", "F1", "higher", "on", "2/2"]
    assert len(lines) == 3
    assert per_scan_comparison([_row("a", INPUT, 0.1, 0.4)]) == ""


def test_a_bad_scan_is_left_out_and_reported_while_the_others_are_scored(scan: np.ndarray, weights_file: Path,
                                                                         tmp_path: Path) -> None:
    folder = tmp_path / "scans"
    folder.mkdir()
    scan.astype(np.float32).tofile(folder / "000000.bin")
    scan[np.random.default_rng(0).permutation(len(scan))].astype(np.float32).tofile(folder / "000001.bin")
    out = tmp_path / "out"
    result = CliRunner().invoke(app, ["eval-kitti", str(folder), "--out", str(out), "--weights", str(weights_file),
                                      "--uniform-weights", str(weights_file)])
    assert result.exit_code == 3, result.output  # it stopped at the bad scan with exit 2, scoring nothing
    assert "1 scan not evaluated" in result.output and "000001.bin" in result.output
    assert {r["scan"] for r in _rows(out)} == {f"bin/{bin_sequence_name(folder)}/000000", "mean"}
    only_bad = tmp_path / "bad"
    only_bad.mkdir()
    (folder / "000001.bin").rename(only_bad / "000000.bin")
    nothing = CliRunner().invoke(app, ["eval-kitti", str(only_bad), "--out", str(out), "--weights", str(weights_file),
                                       "--uniform-weights", str(weights_file)])
    assert nothing.exit_code == 2 and "no scan could be evaluated" in nothing.output


def test_eval_kitti_refuses_an_out_file_and_another_ratio_before_any_scan(tmp_path: Path) -> None:
    scans = tmp_path / "scans"
    scans.mkdir()
    np.zeros((10, 4), np.float32).tofile(scans / "000000.bin")
    taken = tmp_path / "summary.json"
    taken.write_text("{}")
    # an --out that is a file ended in a FileExistsError traceback after every scan was scored
    result = CliRunner().invoke(app, ["eval-kitti", str(scans), "--out", str(taken)])
    assert result.exit_code == 2 and f"--out: {taken} is not writable: {taken} is a file, not a folder" in result.stderr, \
        result.output
    assert taken.read_text() == "{}"
    # one below a file: a NotADirectoryError traceback after the first scan was scored (a trial)
    result = CliRunner().invoke(app, ["eval-kitti", str(scans), "--out", str(taken / "sub")])
    assert result.exit_code == 2 and f"--out: {taken / 'sub'} is not writable" in result.stderr, result.output
    # ratio 16 thinned to 4 rings but labelled the rows "16-ring input" against "the full 64-ring scan"
    result = CliRunner().invoke(app, ["eval-kitti", str(scans), "--out", str(tmp_path / "e"),
                                      "--set", "upsample.ratio=16"])
    assert result.exit_code == 2 and "upsample.ratio must be 4 here" in result.stderr, result.output
    assert not (tmp_path / "e").exists()


def test_scans_the_weights_were_fine_tuned_on_are_flagged(scan_folder: Path, tmp_path: Path) -> None:
    # a fine-tuned file scored on its own training scans looked like a held-out result
    import torch

    from cadpu import weights
    from cadpu.network import Generator

    torch.manual_seed(0)
    tuned = tmp_path / "tuned.pt"
    scan = next(scan_folder.glob("*.bin"))
    weights.save(Generator(ratio=4), tuned, {"finetune_scans": [str(scan)]})
    said: list[str] = []
    result = evaluate_kitti(scan_folder, tmp_path / "ev", tuned, tuned, log=said.append)
    assert any(line.startswith("eval-kitti: warning: 1 of the 1 scans are scans the weights were fine-tuned on")
               for line in said)
    assert "warning: 1 of these scans trained the fine-tuned weights" in result.table
    # a copy of the training scan elsewhere, known by its content: no warning before (a trial)
    from stages.discovery import content_digest

    copied = tmp_path / "copy"
    copied.mkdir()
    (copied / scan.name).write_bytes(scan.read_bytes())
    weights.save(Generator(ratio=4), tuned, {"finetune_scans": [str(scan)], "finetune_scan_digests": [content_digest(scan)]})
    said.clear()
    evaluate_kitti(copied, tmp_path / "ev2", tuned, tuned, log=said.append)
    assert any("1 of the 1 scans are scans the weights were fine-tuned on" in line for line in said)


def test_scans_that_chose_the_fine_tuned_weights_are_flagged_and_recorded(scan_folder: Path, tmp_path: Path) -> None:
    # the scan whose score picked the fine-tuned file's best step was scored as if held out, and
    # eval_kitti.json kept no trace of either warning (a researcher's trial)
    import json

    import torch

    from cadpu import weights
    from cadpu.network import Generator

    torch.manual_seed(0)
    tuned = tmp_path / "tuned.pt"
    scan = next(scan_folder.glob("*.bin"))
    weights.save(Generator(ratio=4), tuned, {"finetune_scans": [], "finetune_heldout_scans": [str(scan)]})
    said: list[str] = []
    result = evaluate_kitti(scan_folder, tmp_path / "ev", tuned, tuned, log=said.append)
    assert any(line.startswith("eval-kitti: warning: 1 of the 1 scans chose the weights when they were fine-tuned")
               for line in said), said
    assert "warning: 1 of these scans chose the fine-tuned weights: not held-out scores" in result.table
    record = json.loads(result.record_path.read_text())
    assert record["chose_the_weights"] == [str(scan)] and record["fine_tuned_on"] == []


def test_a_fine_tune_of_a_fine_tuned_file_keeps_the_scans_that_chose_its_base() -> None:
    from pipeline.finetune import selection_scans
    from stages.load import FrameRef

    heldout = [FrameRef(dataset="bin", sequence="s", index=3, source="/data/000003.bin")]
    assert selection_scans({"finetune_heldout_scans": ["/data/000001.bin"]}, heldout) == ["/data/000001.bin",
                                                                                          "/data/000003.bin"]
    assert selection_scans({}, heldout) == ["/data/000003.bin"]
