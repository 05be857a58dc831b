"""Tests of the held-out learning curves (`cadpu.curves`) and of `train` recording them."""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np
import pytest
import torch

from cadpu.curves import CURVE_COLUMNS, HELDOUT_STREET_SEED, HeldoutCurves, plot_curves, read_curves, score_snapshots
from cadpu.data import PatchSet
from cadpu.network import Generator
from cadpu.scan_data import street_scan_patches
from cadpu.synthetic.lidar import LidarModel
from cadpu.train import Recipe, train
from cadpu.validation import heldout_chamfer


def test_curves_record_network_and_baseline_per_set_and_metric(tmp_path: Path) -> None:
    curves = HeldoutCurves(meshes=2, streets=0)
    torch.manual_seed(0)
    generator = Generator(ratio=4)
    first = curves.score(generator)
    assert set(first) == {("meshes", "CD"), ("meshes", "HD"), ("meshes", "P2F")}
    assert curves.score(generator) == first  # deterministic
    with torch.no_grad():
        for parameter in generator.parameters():
            parameter.mul_(1.5)
    assert curves.score(generator) != first
    path = tmp_path / "curves.csv"
    curves.record(generator, 10, 80, path)
    curves.record(generator, 20, 160, path)
    rows = read_curves(path)
    assert list(rows[0]) == list(CURVE_COLUMNS) and len(rows) == 6
    assert [r["samples_seen"] for r in rows if r["metric"] == "CD"] == ["80", "160"]
    # the baseline does not depend on the network
    assert {r["baseline"] for r in rows if r["metric"] == "CD"} == {f"{curves.baseline[('meshes', 'CD')]:.6g}"}
    assert plot_curves(path, tmp_path / "curves.png").stat().st_size > 0


def test_train_records_curves_every_n_steps(tmp_path: Path) -> None:
    recipe = Recipe(steps=2, batch_size=2, checkpoint_every=1, adversarial_from=10, threads=1,
                    output=str(tmp_path / "run"), curves_every=1, curves_meshes=1, curves_streets=0,
                    curves_csv=str(tmp_path / "kept" / "curves.csv"))
    rng = np.random.default_rng(0)
    pairs = PatchSet(rng.normal(size=(4, 256, 3)).astype(np.float32), rng.normal(size=(4, 1024, 3)).astype(np.float32),
                     np.tile(np.float32([0, 0, 1]), (4, 1024, 1)), np.zeros(4, dtype=bool))
    train(recipe, progress=False, patches=pairs)
    rows = read_curves(tmp_path / "kept" / "curves.csv")
    assert sorted({int(r["step"]) for r in rows}) == [1, 2]
    assert {int(r["samples_seen"]) for r in rows} == {2, 4}


def test_held_out_streets_come_from_the_sensor_the_run_trains_on() -> None:
    clean = HeldoutCurves(meshes=0, streets=1, vertical_scale=0.15, sensor="clean")
    expected = street_scan_patches(HELDOUT_STREET_SEED, 2, 20, 0.15, LidarModel.clean())[0]
    assert clean.streets is not None and np.array_equal(clean.streets.inputs, expected)
    measured = HeldoutCurves(meshes=0, streets=1, vertical_scale=0.15)
    assert not np.array_equal(measured.streets.inputs[:len(expected)], expected[:len(measured.streets.inputs)])


def test_held_out_streets_cover_every_scene_type_the_run_trains_on(tmp_path: Path) -> None:
    curves = HeldoutCurves(meshes=0, streets=1, vertical_scale=0.15, scene_types=("urban", "rural"))
    rural = street_scan_patches(HELDOUT_STREET_SEED, 2, 20, 0.15, scene_type="rural")[0]
    assert np.array_equal(curves.street_sets["streets-rural"].inputs, rural)
    assert curves.streets is curves.street_sets["streets"]  # urban keeps the name of the runs before
    torch.manual_seed(0)
    curves.record(Generator(ratio=4, frame_k=24), 0, 0, tmp_path / "curves.csv")
    rows = list(csv.DictReader((tmp_path / "curves.csv").open()))
    assert [(r["set"], r["metric"]) for r in rows] == [("streets", "CD"), ("streets", "snapped CD"),
                                                       ("streets-rural", "CD"), ("streets-rural", "snapped CD")]
    # the street CD is the one recorded before the snapped metric (the curves stay comparable)
    torch.manual_seed(0)
    assert float(rows[0]["network"]) == pytest.approx(heldout_chamfer(Generator(ratio=4, frame_k=24), curves.streets),
                                                      rel=1e-5)
    snapped = {r["set"]: (float(r["network"]), float(r["baseline"])) for r in rows if r["metric"] == "snapped CD"}
    assert all(0 < value < 1 for pair in snapped.values() for value in pair)


def test_snapshots_scored_afterwards_give_the_curves_the_run_would_have_recorded(tmp_path: Path) -> None:
    recipe = Recipe(steps=2, batch_size=2, checkpoint_every=1, adversarial_from=10, threads=1,
                    output=str(tmp_path / "run"), curves_every=1, curves_meshes=1, curves_streets=0,
                    curves_csv=str(tmp_path / "during.csv"), snapshot_every=1)
    rng = np.random.default_rng(0)
    pairs = PatchSet(rng.normal(size=(4, 256, 3)).astype(np.float32), rng.normal(size=(4, 1024, 3)).astype(np.float32),
                     np.tile(np.float32([0, 0, 1]), (4, 1024, 1)), np.zeros(4, dtype=bool))
    train(recipe, progress=False, patches=pairs)
    snapshots = tmp_path / "run" / "snapshots"
    assert sorted(p.name for p in snapshots.glob("*.pt")) == ["step-0000001.pt", "step-0000002.pt"]
    assert score_snapshots(snapshots, HeldoutCurves(meshes=1, streets=0), tmp_path / "after.csv") == 2
    during, after = read_curves(tmp_path / "during.csv"), read_curves(tmp_path / "after.csv")
    assert [(r["step"], r["samples_seen"], r["metric"]) for r in after] == \
        [(r["step"], r["samples_seen"], r["metric"]) for r in during]
    for a, b in zip(after, during):
        assert float(a["network"]) == pytest.approx(float(b["network"]), rel=1e-4)


def test_bad_paths_exit_2_with_one_line_before_any_work(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from cadpu.curves import main

    table = tmp_path / "curves.csv"
    table.write_text("step,samples_seen,set,metric,network,baseline\n1,8,meshes,CD,0.01,0.02\n")
    wrong = tmp_path / "other.csv"
    wrong.write_text("a,b\n1,2\n")
    cases = [([str(tmp_path / "none.csv"), str(tmp_path / "c.png")], "none.csv does not exist"),
             ([str(wrong), str(tmp_path / "c.png")], "other.csv is not a curves CSV: no column step"),
             ([str(table), str(tmp_path / "c.txt")], "c.txt: give a .png file")]
    for argv, message in cases:  # each a traceback, exit 1, before
        with pytest.raises(SystemExit) as stop:
            main(argv)
        assert stop.value.code == 2 and message in capsys.readouterr().err
    main([str(table), str(tmp_path / "c.png")])
    assert (tmp_path / "c.png").is_file()
