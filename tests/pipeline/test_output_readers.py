"""The outputs of `kitti-pu run --format parquet,ply,kitti`, each opened by the real reader a user
would take: pykitti (raw and odometry) on the KITTI mirror, `kitti-pu run` on the mirror as input,
pandas / pyarrow.dataset / Dask / DuckDB on the Parquet folder, Open3D on the PLY in a fresh
process; and `kitti-pu info` agrees with what the readers count."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq
import pytest
from typer.testing import CliRunner

from pipeline.cli import app
from pipeline.config import PipelineConfig
from pipeline.runner import run_pipeline
from stages import write, write_kitti

DATE, DRIVE = "2011_09_26", "2011_09_26_drive_0001_sync"
PROJECTION = " ".join(["700", "0", "600", "0", "0", "700", "180", "0", "0", "0", "1", "0"])


def _odometry_sequence(base: Path, scans: list[np.ndarray]) -> None:
    """BASE/sequences/00 with the scans, calib.txt, times.txt and poses/00.txt."""
    folder = base / "sequences" / "00"
    (folder / "velodyne").mkdir(parents=True)
    for index, scan in enumerate(scans):
        scan.tofile(folder / "velodyne" / f"{index:06d}.bin")
    (folder / "calib.txt").write_text("\n".join([f"P{i}: {PROJECTION}" for i in range(4)]
                                                + ["Tr: 0 -1 0 0 0 0 -1 -0.08 1 0 0 -0.27"]) + "\n")
    (folder / "times.txt").write_text("".join(f"{0.1 * i:.6e}\n" for i in range(len(scans))))
    (base / "poses").mkdir()
    (base / "poses" / "00.txt").write_text("".join(f"1 0 0 {i} 0 1 0 0 0 0 1 0\n" for i in range(len(scans))))


@pytest.fixture(scope="module")
def mirrored(raw_drive_template: Path, template_scans: list[np.ndarray], make_config: Callable[..., PipelineConfig],
             tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path, PipelineConfig]:
    """One run over a base holding a raw drive and odometry sequence 00, in every format:
    (input base, output folder, config)."""
    root = tmp_path_factory.mktemp("mirror")
    base = Path(shutil.copytree(raw_drive_template, root / "kitti"))
    _odometry_sequence(base, template_scans)
    out = root / "out"
    config = make_config(base, out, output__formats="parquet,ply,kitti")
    summary = run_pipeline(config, progress=False)
    assert summary.count("done") == 4, [f.error for f in summary.frames]
    return base, out, config


def _parquet(out: Path, dataset: str, sequence: str, index: int) -> np.ndarray:
    table = pq.read_table(out / "points" / dataset / sequence / f"{index:06d}.parquet")
    return np.column_stack([table[c].to_numpy() for c in ("x", "y", "z", "reflectance")])


def test_pykitti_raw_opens_the_mirror_and_its_scans_equal_the_parquet(mirrored: tuple[Path, Path, PipelineConfig]) -> None:
    import pykitti

    base, out, _ = mirrored
    original = pykitti.raw(str(base), DATE, "0001")
    mirror = pykitti.raw(str(out / "kitti"), DATE, "0001")
    assert len(mirror.velo_files) == 2
    assert mirror.timestamps == original.timestamps
    np.testing.assert_array_equal(mirror.calib.T_cam0_velo, original.calib.T_cam0_velo)
    for index in range(2):
        np.testing.assert_array_equal(mirror.get_velo(index), _parquet(out, "raw", DRIVE, index))
        assert len(mirror.get_velo(index)) > len(original.get_velo(index))


def test_pykitti_odometry_opens_the_mirror_and_its_scans_equal_the_parquet(mirrored: tuple[Path, Path, PipelineConfig]) -> None:
    import pykitti

    base, out, _ = mirrored
    original = pykitti.odometry(str(base), "00")
    mirror = pykitti.odometry(str(out / "kitti"), "00")
    assert mirror.timestamps == original.timestamps
    np.testing.assert_array_equal(np.asarray(mirror.poses), np.asarray(original.poses))
    np.testing.assert_array_equal(mirror.calib.T_cam0_velo, original.calib.T_cam0_velo)
    for index in range(2):
        scan = mirror.get_velo(index)
        assert scan.dtype == np.float32
        np.testing.assert_array_equal(scan, _parquet(out, "odometry", "00", index))


def test_the_sidecar_holds_generated_ground_and_parent_row_for_row(mirrored: tuple[Path, Path, PipelineConfig]) -> None:
    _, out, _ = mirrored
    scan = out / "kitti" / "sequences" / "00" / "velodyne" / "000001.bin"
    table = pq.read_table(out / "points" / "odometry" / "00" / "000001.parquet")
    with np.load(write_kitti.sidecar_path(scan)) as sidecar:
        assert sidecar["parent"].dtype == np.int64 and sidecar["generated"].dtype == bool
        for name in ("generated", "ground", "parent"):
            np.testing.assert_array_equal(sidecar[name], table[name].to_numpy())
    assert write_kitti.sidecar_path(scan) == out / "kitti" / "sequences" / "00" / "kitti_pu" / "000001.npz"


def test_a_rerun_skips_the_mirror_and_redoes_a_frame_whose_sidecar_is_gone(
        mirrored: tuple[Path, Path, PipelineConfig], tmp_path: Path) -> None:
    _, out, config = mirrored
    copy = Path(shutil.copytree(out, tmp_path / "out"))
    rerun = config.model_copy(update={"output": config.output.model_copy(update={"dir": copy})})
    assert run_pipeline(rerun, progress=False).count("skipped") == 4
    write_kitti.sidecar_path(copy / "kitti" / "sequences" / "00" / "velodyne" / "000000.bin").unlink()
    summary = run_pipeline(rerun, progress=False)
    assert [f.key for f in summary.frames if f.status == "done"] == ["odometry/00/000000"]


def test_kitti_pu_run_accepts_the_mirror_as_input(mirrored: tuple[Path, Path, PipelineConfig],
                                                   weights_file: Path, tmp_path: Path) -> None:
    _, out, _ = mirrored
    result = CliRunner().invoke(app, [
        "run", str(out / "kitti"), "--out", str(tmp_path / "again"), "--sequence", "0", "--last", "0",
        "--weights", str(weights_file), "--workers", "1", "--no-progress", "--set", "dask.torch_threads=1",
        "--set", "upsample.device=cpu", "--set", "upsample.max_patch_radius=0"])
    assert result.exit_code == 0, result.output
    # --no-progress: one line per finished frame, key, status, points, seconds
    line = next(line for line in result.stdout.splitlines() if line.startswith("odometry/00/000000 done "))
    points_in = len(_parquet(out, "odometry", "00", 0))
    assert line.split()[2:5] == [str(points_in), "->", str(pq.read_metadata(
        tmp_path / "again" / "points" / "odometry" / "00" / "000000.parquet").num_rows)]
    assert line.endswith(" s")


def test_every_reader_reads_sequence_00_as_a_string_with_the_counts_info_reports(
        mirrored: tuple[Path, Path, PipelineConfig]) -> None:
    import dask.dataframe as dd
    import duckdb
    import pandas as pd
    import pyarrow.dataset as ds

    _, out, _ = mirrored
    info = json.loads(CliRunner().invoke(app, ["info", str(out), "--json"]).stdout)
    assert info["frames"] == 4 and not info["mixed"]
    odometry = next(s for s in info["sequences"] if s["sequence"] == "00")
    points = str(out / "points")
    tables = {
        "pandas": pd.read_parquet(points),
        "pyarrow": ds.dataset(points).to_table().to_pandas(),
        "dask": dd.read_parquet(points).compute(),
        "duckdb": duckdb.sql(f"SELECT * FROM read_parquet('{points}/*/*/*.parquet')").df(),
    }
    for reader, table in tables.items():
        assert len(table) == info["points"], reader
        assert (table["sequence"] == "00").sum() == odometry["points"], reader
        assert set(table["sequence"]) == {"00", DRIVE}, reader


def test_open3d_reads_every_ply_attribute_after_a_plain_import_in_a_fresh_process(
        mirrored: tuple[Path, Path, PipelineConfig]) -> None:
    _, out, _ = mirrored
    ply = out / "ply" / "odometry" / "00" / "000001.ply"
    code = (
        "import json, sys\n"
        "import open3d\n"  # plain: the install's start-up hook preloads libusb (setup.py)
        "pcd = open3d.t.io.read_point_cloud(sys.argv[1])\n"
        "print(json.dumps({k: [str(pcd.point[k].dtype), pcd.point[k].shape[0]] for k in pcd.point}))\n"
    )
    root = Path(__file__).resolve().parents[2]
    done = subprocess.run([sys.executable, "-c", code, str(ply)], capture_output=True, text=True,
                          env={"PYTHONPATH": str(root), "PATH": "/usr/bin:/bin"}, timeout=120)
    assert done.returncode == 0, done.stderr
    attributes = json.loads(done.stdout)
    rows = pq.read_metadata(out / "points" / "odometry" / "00" / "000001.parquet").num_rows
    assert attributes == {"positions": ["Float32", rows], "reflectance": ["Float32", rows],
                          "generated": ["UInt8", rows], "ground": ["UInt8", rows],
                          "parent": ["Int32", rows], "frame": ["Int32", rows]}


def test_a_mirrored_frame_whose_scan_is_gone_names_the_files_that_block_the_run(
        template_scans: list[np.ndarray], make_config: Callable[..., PipelineConfig], tmp_path: Path) -> None:
    # frame 1's scan deleted, then the sequence copied elsewhere with a corrected time: every run
    # into the output exited 2 saying to write to another output folder, though no run could ever
    # redo frame 1 (a scheduled-run trial)
    from pipeline.config import ConfigError

    first, out = tmp_path / "first", tmp_path / "out"
    _odometry_sequence(first, template_scans)
    assert run_pipeline(make_config(first, out, output__formats="parquet,kitti"), progress=False).count("done") == 2
    (first / "sequences" / "00" / "velodyne" / "000001.bin").unlink()
    moved = Path(shutil.copytree(first, tmp_path / "moved")) / "sequences" / "00"
    (moved / "times.txt").write_text("0.05\n0.1\n")
    mirrored = out / "kitti" / "sequences" / "00" / "velodyne"
    blocking = [mirrored / "000001.bin", write_kitti.sidecar_path(mirrored / "000001.bin")]
    assert all(path.is_file() for path in blocking)
    with pytest.raises(ConfigError) as refused:
        run_pipeline(make_config(moved.parent.parent, out, output__formats="parquet,kitti"), progress=False)
    message = str(refused.value)
    assert f"holds frame 1, mirrored from {first / 'sequences' / '00' / 'velodyne' / '000001.bin'}, which no longer exists" in message
    assert all(str(path) in message for path in blocking)
    for path in blocking:  # as the message says
        path.unlink()
    again = run_pipeline(make_config(moved.parent.parent, out, output__formats="parquet,kitti"), progress=False)
    # frame 0's scan, copied with its bytes, is the same scan: recorded again with its new path and time
    assert [(f.status, f.reason) for f in again.frames] == [("replaced", "source moved")]
    assert "upsample" not in again.frames[0].timings
    assert write.stored_record({"kitti": Path(again.frames[0].outputs["kitti"])})["timestamp"] == "0.05"


def test_a_sequence_of_the_same_name_from_another_folder_is_refused_before_it_rewrites_the_mirrors_times(
        template_scans: list[np.ndarray], make_config: Callable[..., PipelineConfig], tmp_path: Path) -> None:
    # frames 0-1 of one folder's sequence 00, then frame 2 of another folder's sequence 00 with other
    # times and no poses: the run replaced the mirror's times.txt and removed its poses, so pykitti
    # read frames 0-1 with the other folder's times (a trial)
    from pipeline.config import ConfigError
    from pipeline.preflight import preflight

    first, out = tmp_path / "first", tmp_path / "out"
    _odometry_sequence(first, template_scans)
    assert run_pipeline(make_config(first, out, output__formats="parquet,kitti"), progress=False).count("done") == 2
    mirrored = out / "kitti" / "sequences" / "00"
    times, poses = (mirrored / "times.txt").read_bytes(), (out / "kitti" / "poses" / "00.txt").read_bytes()
    second = tmp_path / "second" / "sequences" / "00"
    (second / "velodyne").mkdir(parents=True)
    template_scans[0].tofile(second / "velodyne" / "000002.bin")
    shutil.copy(first / "sequences" / "00" / "calib.txt", second / "calib.txt")
    (second / "times.txt").write_text("5.0\n5.1\n5.2\n")
    with pytest.raises(ConfigError, match=f"output.formats: kitti: {mirrored / 'velodyne'} holds frames of "
                                          f"{first / 'sequences' / '00' / 'velodyne'} \\(frame 0 the first this run "
                                          f"would not redo\\), which read times.txt from "
                                          f"{first / 'sequences' / '00' / 'times.txt'}; this run's "
                                          f"{second / 'times.txt'} differs from it"):
        run_pipeline(make_config(second.parent.parent, out, output__formats="parquet,kitti"), progress=False)
    assert (mirrored / "times.txt").read_bytes() == times
    assert (out / "kitti" / "poses" / "00.txt").read_bytes() == poses
    # the same files in another folder (the dataset moved) are no conflict
    moved = Path(shutil.copytree(first, tmp_path / "moved"))
    preflight(make_config(moved, out, output__formats="parquet,kitti"))
    # nor are lines appended for new frames: the mirrored frames read what they read before
    grown = Path(shutil.copytree(first, tmp_path / "grown")) / "sequences" / "00"
    template_scans[0].tofile(grown / "velodyne" / "000002.bin")
    with (grown / "times.txt").open("a") as appended:
        appended.write("2.000000e-01\n")
    with (grown.parent.parent / "poses" / "00.txt").open("a") as appended:
        appended.write("1 0 0 2 0 1 0 0 0 0 1 0\n")
    preflight(make_config(grown.parent.parent, out, output__formats="parquet,kitti", input__first_frame=2))
    # nor is a sequence without the kitti format
    preflight(make_config(second.parent.parent, out, output__formats="parquet"))
    # a copy without the poses file: it would remove the file the mirrored frames read ("is
    # missing, and would replace" read as a contradiction: a batch user's trial)
    no_poses = Path(shutil.copytree(grown.parent.parent, tmp_path / "no_poses"))
    (no_poses / "poses" / "00.txt").unlink()
    with pytest.raises(ConfigError, match=f"this run's {no_poses / 'poses' / '00.txt'} is missing, and so would "
                                          "remove the file those frames are read with"):
        preflight(make_config(no_poses, out, output__formats="parquet,kitti", input__first_frame=2))
    # a velodyne/ linked into the first tree, beside other metadata (SemanticKITTI reusing the
    # odometry scans) takes its metadata from its own folder: a conflict (the check resolved the
    # link and found one folder, a review)
    linked = tmp_path / "linked" / "sequences" / "00"
    linked.mkdir(parents=True)
    (linked / "velodyne").symlink_to(first / "sequences" / "00" / "velodyne")
    shutil.copy(first / "sequences" / "00" / "calib.txt", linked / "calib.txt")
    (linked / "times.txt").write_text("7.0\n7.1\n")
    with pytest.raises(ConfigError, match=f"which read times.txt from {first / 'sequences' / '00' / 'times.txt'}"):
        preflight(make_config(linked.parent.parent, out, output__formats="parquet,kitti", input__first_frame=1))


def test_a_drive_of_the_same_date_from_another_folder_with_other_calibration_is_refused(
        raw_drive_template: Path, make_config: Callable[..., PipelineConfig], tmp_path: Path) -> None:
    # the date's calib_*.txt is one file for every drive of the date in the mirror: a drive of
    # another base with other calibration rewrote it under the first drive's frames (a review)
    from pipeline.config import ConfigError
    from pipeline.preflight import preflight

    out = tmp_path / "out"
    assert run_pipeline(make_config(raw_drive_template, out, output__formats="parquet,kitti"),
                        progress=False).count("done") == 2
    other = Path(shutil.copytree(raw_drive_template, tmp_path / "other"))
    (other / DATE / DRIVE).rename(other / DATE / DRIVE.replace("0001", "0002"))
    calib = other / DATE / "calib_velo_to_cam.txt"
    calib.write_text(calib.read_text().replace("T: ", "T: 0.5 ", 1))
    with pytest.raises(ConfigError, match=f"holds frames of .*, which read calib_velo_to_cam.txt from "
                                          f"{raw_drive_template / DATE / 'calib_velo_to_cam.txt'}; this run's {calib}"):
        preflight(make_config(other, out, output__formats="parquet,kitti"))
    # the same once the first folder is gone: the file its frames read is found from their records
    # (a glob of the folder found nothing, and the run went ahead: a review)
    gone = Path(shutil.copytree(raw_drive_template, tmp_path / "first"))
    mirror_out = tmp_path / "out_gone"
    assert run_pipeline(make_config(gone, mirror_out, output__formats="kitti"), progress=False).count("done") == 2
    shutil.rmtree(gone)
    # its scans gone too: no run can redo those frames, and the message names their files to remove
    with pytest.raises(ConfigError, match="which no longer exists; it reads calib_velo_to_cam.txt from .* remove "
                                          "its files from the mirror"):
        preflight(make_config(other, mirror_out, output__formats="parquet,kitti"))


def test_semantickitti_labels_reach_the_mirror_each_point_with_its_parents_label(
        template_scans: list[np.ndarray], make_config: Callable[..., PipelineConfig], tmp_path: Path,
        capsys: pytest.CaptureFixture[str]) -> None:
    # the mirror held no labels/, so SemanticKITTI readers of it failed (a trial)
    base, out = tmp_path / "semantic", tmp_path / "out"
    _odometry_sequence(base, template_scans)
    shutil.copy(base / "poses" / "00.txt", base / "sequences" / "00" / "poses.txt")  # SemanticKITTI's copy
    config = make_config(base, out, output__formats="parquet,kitti")
    assert run_pipeline(config, progress=False).count("done") == 2
    mirrored = out / "kitti" / "sequences" / "00"
    assert not (mirrored / "labels").exists()  # the input has none
    assert (mirrored / "poses.txt").read_bytes() == (base / "poses" / "00.txt").read_bytes()
    # labels downloaded later: a rerun redoes no frame and writes them from the sidecars
    labels = base / "sequences" / "00" / "labels"
    labels.mkdir()
    truth = [np.random.default_rng(i).integers(0, 2**32, len(scan), dtype=np.uint32) for i, scan in
             enumerate(template_scans)]
    for index, values in enumerate(truth):
        values.tofile(labels / f"{index:06d}.label")
    again = run_pipeline(config, progress=False)
    assert again.count("skipped") == 2
    for index, values in enumerate(truth):
        _assert_labels_of_parents(mirrored, index, values)
    # corrected labels reach the mirror even when their files are older than the mirror's copy
    # (unpacked from an archive, copied with their times: they were ignored, a review)
    corrected = [values ^ np.uint32(1) for values in truth]
    for index, values in enumerate(corrected):
        values.tofile(labels / f"{index:06d}.label")
        os.utime(labels / f"{index:06d}.label", ns=(1_500_000_000 * 10**9,) * 2)  # 2017
    assert run_pipeline(config, progress=False).count("skipped") == 2
    for index, values in enumerate(corrected):
        _assert_labels_of_parents(mirrored, index, values)
    # a label changed while a run selects other frames stays as it was, and --verify names it (a
    # run of other frames left it stale without a word: a batch user's trial)
    from typer.testing import CliRunner

    from pipeline.cli import app
    assert CliRunner().invoke(app, ["info", str(out), "--verify"]).exit_code == 0
    (truth[0] ^ np.uint32(2)).tofile(labels / "000000.label")
    assert run_pipeline(make_config(base, out, output__formats="parquet,kitti", input__first_frame=1),
                        progress=False).count("skipped") == 1
    verified = CliRunner().invoke(app, ["info", str(out), "--verify"])
    assert verified.exit_code == 3, verified.output
    assert f"1 mirrored frame(s) whose SemanticKITTI labels are not the input's as it is now, e.g. " \
           f"{mirrored / 'velodyne' / '000000.bin'}" in verified.stdout
    assert run_pipeline(config, progress=False).count("skipped") == 2  # selected: brought up to date
    _assert_labels_of_parents(mirrored, 0, truth[0] ^ np.uint32(2))
    assert CliRunner().invoke(app, ["info", str(out), "--verify"]).exit_code == 0
    # labels and SemanticKITTI's poses.txt the input no longer has leave the mirror too
    shutil.move(labels, tmp_path / "labels_away")
    (base / "sequences" / "00" / "poses.txt").unlink()
    assert run_pipeline(config, progress=False).count("skipped") == 2
    assert list((mirrored / "labels").iterdir()) == [] and not (mirrored / "poses.txt").exists()
    shutil.move(tmp_path / "labels_away", labels)
    for index, values in enumerate(truth):
        values.tofile(labels / f"{index:06d}.label")
    # a label file that does not hold one label a return fails its frame alone, naming the file
    values = truth[1][:-3]
    values.tofile(labels / "000001.label")
    fresh = run_pipeline(make_config(base, tmp_path / "fresh", output__formats="parquet,kitti"), progress=False)
    assert [f.status for f in fresh.frames] == ["done", "failed"]
    assert f"[load] {labels / '000001.label'}: {4 * len(values)} bytes: not one 4-byte label" in fresh.frames[1].error
    written = tmp_path / "fresh" / "kitti" / "sequences" / "00"
    assert sorted(p.name for p in (written / "labels").iterdir()) == ["000000.label"]
    _assert_labels_of_parents(written, 0, truth[0])  # written with the frame
    capsys.readouterr()


def _assert_labels_of_parents(mirrored: Path, index: int, labels: np.ndarray) -> None:
    """The mirror's labels of a frame, read as SemanticKITTI reads them, are one per point, each
    point's parent return's."""
    scan = np.fromfile(mirrored / "velodyne" / f"{index:06d}.bin", np.float32).reshape(-1, 4)
    read = np.fromfile(mirrored / "labels" / f"{index:06d}.label", np.uint32)
    parent = np.load(mirrored / "kitti_pu" / f"{index:06d}.npz")["parent"]
    assert len(read) == len(scan) and np.array_equal(read, labels[parent])


def test_labels_that_do_not_fit_fail_their_frame_before_it_runs_and_keep_its_files(
        template_scans: list[np.ndarray], make_config: Callable[..., PipelineConfig], tmp_path: Path,
        capsys: pytest.CaptureFixture[str]) -> None:
    # a finished frame whose labels went wrong was skipped with a warning and exit 0, and under
    # --overwrite its files were deleted after the network ran; labels out of step with their scan
    # (a run killed while it replaced the frame) were never noticed (a trial)
    from pipeline.info import damaged_frame_files

    base, out = tmp_path / "semantic", tmp_path / "out"
    _odometry_sequence(base, template_scans)
    labels = base / "sequences" / "00" / "labels"
    labels.mkdir()
    truth = [np.arange(len(scan), dtype=np.uint32) for scan in template_scans]
    for index, values in enumerate(truth):
        values.tofile(labels / f"{index:06d}.label")
    config = make_config(base, out, output__formats="parquet,kitti")
    assert run_pipeline(config, progress=False).count("done") == 2
    mirrored = out / "kitti" / "sequences" / "00"
    kept = {path: path.read_bytes() for path in sorted(out.rglob("*0001.*")) if path.is_file()}
    truth[1][:-5].tofile(labels / "000001.label")
    for overwrite in (False, True):
        summary = run_pipeline(make_config(base, out, output__formats="parquet,kitti", output__overwrite=overwrite),
                               progress=False)
        failed = summary.frames[1]
        assert failed.status == "failed" and failed.failed_stage == "load", failed
        assert f"{labels / '000001.label'}: {4 * (len(truth[1]) - 5)} bytes: not one 4-byte label" in failed.error
        assert summary.exit_code == 3 and failed.points_out > 0  # its earlier files counted, and kept
        assert {path: path.read_bytes() for path in kept} == kept
    # labels of another point count beside a scan: the frame is not complete, and --verify says so
    truth[1].tofile(labels / "000001.label")
    (mirrored / "labels" / "000001.label").write_bytes(b"\0" * 40)
    # the labels named, not the intact scan beside them (a trial)
    assert damaged_frame_files(out) == [f"{mirrored / 'labels' / '000001.label'} (not one label for each point of "
                                        "000001.bin)"]
    again = run_pipeline(config, progress=False)
    assert [f.status for f in again.frames] == ["skipped", "done"]
    _assert_labels_of_parents(mirrored, 1, truth[1])
    # labels changed on a finished frame: said by --dry-run's plan, on its report, and in one line
    (truth[0] + 7).tofile(labels / "000000.label")
    capsys.readouterr()
    assert planned_label_updates(config) == "1 written"
    updated = run_pipeline(config, progress=False)
    assert updated.frames[0].status == "skipped"
    assert "its SemanticKITTI labels in the KITTI mirror written, from the input's" in updated.frames[0].notes
    assert "labels of finished frames brought up to date with the input's: 1 written" in capsys.readouterr().err
    assert planned_label_updates(config) is None  # done
    (labels / "000000.label").unlink()  # labels withdrawn: removed from the mirror
    assert planned_label_updates(config) == "1 removed"
    run_pipeline(config, progress=False)
    assert not (mirrored / "labels" / "000000.label").exists() and planned_label_updates(config) is None


def planned_label_updates(config: PipelineConfig) -> str | None:
    """What `kitti-pu run --dry-run`'s plan line says of the mirror's labels it would bring up to
    date (the text after the colon), or None when it says nothing of them."""
    from pipeline.preflight import preflight
    from pipeline.runner import plan_frames

    resolved, refs, checksum = preflight(config)
    line = plan_frames(resolved, refs, checksum).describe()
    marker = "SemanticKITTI labels of finished frames to bring up to date in the KITTI mirror: "
    return line.split(marker, 1)[1] if marker in line else None


def test_a_frame_an_earlier_version_mirrored_as_bin_in_capitals_is_kept_not_done_again(
        template_scans: list[np.ndarray], make_config: Callable[..., PipelineConfig], tmp_path: Path) -> None:
    # the mirror now names a ".BIN" input's scan ".bin": a kitti-only mirror of an earlier version
    # had its every frame run through the network again, as "source changed" (a review)
    folder = tmp_path / "upper"
    folder.mkdir()
    template_scans[0].tofile(folder / "000000.BIN")
    out = tmp_path / "out"
    config = make_config(folder, out, output__formats="kitti")
    first = run_pipeline(config, progress=False)
    scan = Path(first.frames[0].outputs["kitti"])
    assert scan.name == "000000.bin"
    scan.rename(scan.with_name("000000.BIN"))  # as versions before 2026-11-26 wrote it
    again = run_pipeline(config, progress=False)
    assert [(f.status, f.reason) for f in again.frames] == [("skipped", None)]
    assert sorted(p.name for p in scan.parent.iterdir() if p.is_file()) == ["000000.bin"]


def test_raw_inputs_whose_poses_or_calibration_would_clash_in_the_mirror_are_refused(
        raw_drive_template: Path, make_config: Callable[..., PipelineConfig], tmp_path: Path) -> None:
    # a drive's first frame copies its OXTS packets whole: another folder's copy of the drive with
    # other packets gave the mirrored frames of the first its poses; and two bases with one date in
    # one run left one calibration for both, silently (a raw-drive user's trial)
    from pipeline.config import ConfigError
    from pipeline.preflight import preflight

    out = tmp_path / "out"
    assert run_pipeline(make_config(raw_drive_template, out, output__formats="kitti", input__last_frame=0),
                        progress=False).count("done") == 1
    turned = Path(shutil.copytree(raw_drive_template, tmp_path / "turned"))
    for packet in sorted((turned / DATE / DRIVE / "oxts" / "data").glob("*.txt")):
        numbers = packet.read_text().split()
        numbers[5] = repr(float(numbers[5]) + 0.1)  # yaw
        packet.write_text(" ".join(numbers) + "\n")
    with pytest.raises(ConfigError, match="holds frame 0 of .*, which reads its pose from OXTS packet 0000000000.txt"):
        preflight(make_config(turned, out, output__formats="kitti", input__first_frame=1))
    preflight(make_config(raw_drive_template, out, output__formats="kitti", input__first_frame=1))  # its own folder
    both = tmp_path / "both"
    shutil.copytree(raw_drive_template, both / "a")
    second = Path(shutil.copytree(raw_drive_template, both / "b")) / DATE
    (second / DRIVE).rename(second / DRIVE.replace("0001", "0002"))
    (second / "calib_velo_to_cam.txt").write_text((second / "calib_velo_to_cam.txt").read_text().replace("T: ", "T: 0.5 ", 1))
    with pytest.raises(ConfigError, match="read calib_velo_to_cam.txt from .* which differ; the mirror keeps one"):
        preflight(make_config(both, tmp_path / "fresh", output__formats="kitti"))
