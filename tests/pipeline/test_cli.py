"""The `kitti-pu` command line (pipeline.cli) through typer's CliRunner, in process: run, info,
preview, config, and the exit codes a scheduler relies on (0 done, 2 bad configuration, 3 some
frames failed). The runs use a real LocalCluster with one single-threaded worker."""

from __future__ import annotations

import importlib.util
import json
import signal
import shutil
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml
from typer.testing import CliRunner, Result

from pipeline.cli import app
from pipeline.config import load_config
from pipeline.summary import EXIT_BAD_CONFIG, EXIT_FRAMES_FAILED, EXIT_OK
from stages import write
from stages.discovery import bin_sequence_name
from stages.frame import Frame
from stages.stored import read_cloud

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


def _invoke(*args: str) -> Result:
    return CliRunner().invoke(app, [str(arg) for arg in args])


def _run_args(folder: Path, out: Path, weights_file: Path) -> list[str]:
    """`kitti-pu run` on one single-threaded worker with the untrained weights."""
    return ["run", str(folder), "--out", str(out), "--weights", str(weights_file), "--workers", "1",
            "--no-progress", "--set", "dask.torch_threads=1", "--set", "upsample.device=cpu"]


@pytest.fixture(scope="module")
def cli_run(template_scans: list[np.ndarray], weights_file: Path,
            tmp_path_factory: pytest.TempPathFactory) -> tuple[Result, Path, Path]:
    """`kitti-pu run` on a .bin folder of two good scans: (result, input folder, output folder)."""
    root = tmp_path_factory.mktemp("cli")
    folder = root / "scans"
    folder.mkdir()
    for index, scan in enumerate(template_scans):
        scan.tofile(folder / f"{index:06d}.bin")
    out = root / "out"
    return _invoke(*_run_args(folder, out, weights_file)), folder, out


def test_run_exits_0_and_prints_the_summary_table(cli_run: tuple[Result, Path, Path]) -> None:
    result, folder, out = cli_run
    assert result.exit_code == EXIT_OK, result.output
    assert "done 2, skipped 0, failed 0 of 2 frames" in result.stdout
    sequence = bin_sequence_name(folder)
    for key in (f"bin/{sequence}/000000", f"bin/{sequence}/000001"):
        assert any(line.startswith(key) and " done " in line for line in result.stdout.splitlines())
    assert f"summary: {out / 'summary.json'}" in result.stdout
    summary = json.loads((out / "summary.json").read_text())
    assert summary["frames_done"] == 2 and summary["exit_code"] == EXIT_OK
    assert len(list(out.glob(f"points/bin/{sequence}/*.parquet"))) == 2
    assert len(list(out.glob(f"ply/bin/{sequence}/*.ply"))) == 2
    # the signals held over the run's last steps are the caller's again (pytest's, here)
    assert signal.getsignal(signal.SIGINT) not in (signal.SIG_IGN, None)
    assert signal.getsignal(signal.SIGTERM) is not signal.SIG_IGN


def test_info_summarises_the_output_folder(cli_run: tuple[Result, Path, Path], weights_file: Path) -> None:
    _, folder, out = cli_run
    summary = json.loads((out / "summary.json").read_text())
    result = _invoke("info", out)
    assert result.exit_code == 0, result.output
    row = next(line.split() for line in result.stdout.splitlines() if line.startswith("bin "))
    generated = sum(frame["generated"] for frame in summary["frames"])
    assert row == ["bin", bin_sequence_name(folder), "2", str(summary["points_out"]), str(generated)]
    assert "last run: done 2, skipped 0, failed 0 of 2 frames" in result.stdout
    # weights of one's own are named by the file the frames record, with the samples it was trained on
    assert f"{weights_file.resolve()}, trained on 0 patch samples" in result.stdout
    # under the "configs ... and models ... per sequence:" header, indented like its config lines
    assert any(line.startswith("  model ") for line in result.stdout.splitlines()), result.stdout


def test_info_keeps_the_timings_of_the_last_run_that_did_frames(cli_run: tuple[Result, Path, Path],
                                                                  weights_file: Path, tmp_path: Path) -> None:
    _, folder, out = cli_run
    copy = Path(shutil.copytree(out, tmp_path / "out"))
    rerun = _invoke(*_run_args(folder, copy, weights_file))  # every frame skipped: no timings
    assert rerun.exit_code == 0 and "skipped 2" in rerun.stdout, rerun.output
    result = _invoke("info", copy)
    # the medians line was gone after a run that did nothing, as an hourly scheduled run often is
    assert result.exit_code == 0 and "the last run that did frames (" in result.stdout, result.stdout
    assert "median ms per frame: load " in result.stdout


def test_info_names_the_settings_each_config_hash_stands_for(cli_run: tuple[Result, Path, Path],
                                                              weights_file: Path, tmp_path: Path) -> None:
    # a folder handed on said only "config 9cc2eca0b6edfc58 (1 frames)": which settings made the
    # frames could not be told, and no command printed the hash of a configuration to compare
    _, folder, out = cli_run
    copy = Path(shutil.copytree(out, tmp_path / "out"))
    changed = ["--set", "fill.enabled=false", "--set", "snap.range_tolerance=0.1"]
    rerun = _invoke(*_run_args(folder, copy, weights_file), "--first", "1", *changed)
    assert rerun.exit_code == 0 and "done 1 (1 replaced)" in rerun.stdout, rerun.output
    default_hash = load_config().output_hash()
    other_hash = load_config(overrides={"fill.enabled": False, "snap.range_tolerance": 0.1}).output_hash()
    printed = _invoke("config", *changed)
    assert f"# config hash: {other_hash} " in printed.stdout
    if importlib.util.find_spec("openvino") is None:  # an engine not installed: a run falls back to eager, and
        fallback = _invoke("config", "--set", "upsample.engine=openvino")  # records eager's hash (a review)
        assert f"# config hash: {default_hash} " in fallback.stdout, fallback.output
    assert yaml.safe_load(printed.stdout)["fill"]["enabled"] is False  # the line keeps the output YAML
    text = _invoke("info", copy).stdout
    assert f"config {default_hash}: the default settings" in text
    assert f"config {other_hash}: fill.enabled=false, snap.range_tolerance=0.1" in text
    settings = json.loads(_invoke("info", copy, "--json").stdout)["config_settings"]
    assert settings == {default_hash: {}, other_hash: {"fill.enabled": False, "snap.range_tolerance": 0.1}}
    summary = json.loads((copy / "summary.json").read_text())  # and the run's summary, beside its hash
    assert summary["config_hash"] == other_hash and summary["output_settings"]["fill"] == {"enabled": False}


def test_info_counts_frames_in_words() -> None:
    from pipeline.info import _counts

    assert _counts({"9cc2eca0b6edfc58aa": 1, "1f2e3d4c": 2}) == "1f2e3d4c (2 frames), 9cc2eca0b6edfc58 (1 frame)"


def test_info_on_a_folder_without_output_exits_2(tmp_path: Path) -> None:
    result = _invoke("info", tmp_path)
    assert result.exit_code == EXIT_BAD_CONFIG
    assert "holds no kitti-pu output" in result.stderr and str(tmp_path) in result.stderr
    missing = _invoke("info", tmp_path / "nonexist")  # "holds no kitti-pu output", before
    assert missing.exit_code == EXIT_BAD_CONFIG and f"{tmp_path / 'nonexist'} does not exist" in missing.stderr


def test_info_on_an_outputs_data_folder_names_the_output_folder(cli_run: tuple[Result, Path, Path]) -> None:
    _, _, out = cli_run
    result = _invoke("info", out / "points")
    assert result.exit_code == EXIT_BAD_CONFIG
    assert f"{out / 'points'} is a data folder of the output {out}; give that folder" in result.stderr


def test_preview_writes_a_png(cli_run: tuple[Result, Path, Path], tmp_path: Path) -> None:
    _, folder, out = cli_run
    parquet = out / "points" / "bin" / bin_sequence_name(folder) / "000000.parquet"
    png = tmp_path / "views" / "frame0.png"
    result = _invoke("preview", parquet, "--png", png)
    assert result.exit_code == 0, result.output
    assert result.stdout.strip() == str(png)
    assert png.read_bytes()[:8] == PNG_MAGIC and png.stat().st_size > 10_000
    assert [p.name for p in png.parent.iterdir()] == ["frame0.png"]  # no temporary left


def test_preview_takes_a_frame_in_every_output_format(cli_run: tuple[Result, Path, Path], tmp_path: Path) -> None:
    _, folder, out = cli_run
    ply = out / "ply" / "bin" / bin_sequence_name(folder) / "000000.ply"
    result = _invoke("preview", ply)  # "is not a kitti-pu output frame (.parquet)", exit 2, before
    assert result.exit_code == 0, result.output
    png = out / "preview" / "bin" / bin_sequence_name(folder) / "000000.png"
    assert result.stdout.strip() == str(png) and png.read_bytes()[:8] == PNG_MAGIC
    png.unlink()
    mirrored = tmp_path / "mirror"
    write.write_frame(read_cloud("ply", ply), Frame(points=np.zeros((0, 4), np.float32), dataset="bin",
                                                    sequence="s", index=0, source=str(folder / "000000.bin")),
                      mirrored, {}, formats=("kitti",))
    scan = next(mirrored.glob("kitti/**/*.bin"))
    kitti_png = tmp_path / "kitti.png"
    result = _invoke("preview", scan, "--png", kitti_png)
    assert result.exit_code == 0, result.output
    assert kitti_png.read_bytes()[:8] == PNG_MAGIC


def test_preview_of_a_missing_file_exits_2(tmp_path: Path) -> None:
    result = _invoke("preview", tmp_path / "none.parquet")
    assert result.exit_code == EXIT_BAD_CONFIG and "none.parquet" in result.stderr


def test_preview_of_a_file_of_another_kind_names_the_formats_only(tmp_path: Path) -> None:
    times = tmp_path / "times.txt"
    times.write_text("0.0\n")
    result = _invoke("preview", times)
    assert result.exit_code == EXIT_BAD_CONFIG, result.output
    assert "not a kitti-pu output frame (one of .parquet, .ply, .bin)" in result.stderr
    assert "sidecar" not in result.stderr  # it told a .txt to have a .bin's sidecar, times.npz


def test_rerun_with_a_bad_scan_skips_done_frames_and_exits_3(
        cli_run: tuple[Result, Path, Path], weights_file: Path, tmp_path: Path,
        capfd: pytest.CaptureFixture[str]) -> None:
    _, folder, _ = cli_run
    folder_copy = Path(shutil.copytree(folder, tmp_path / "scans"))  # another folder: another sequence
    out_copy = tmp_path / "out"
    assert _invoke(*_run_args(folder_copy, out_copy, weights_file)).exit_code == 0
    truncated = folder_copy / "000002.bin"
    truncated.write_bytes((folder_copy / "000000.bin").read_bytes()[:1001])
    result = _invoke(*_run_args(folder_copy, out_copy, weights_file))
    assert result.exit_code == EXIT_FRAMES_FAILED, result.output
    assert "done 0, skipped 2, failed 1 of 3 frames" in result.stdout
    assert f"error: [load] {truncated}: size 1001 bytes is not a multiple of 16" in result.stdout
    assert not list(out_copy.glob("points/**/000002.parquet"))
    # a bad input is reported once, in the tool's words: no Dask worker traceback in a cron log,
    # and without a progress bar only the frame's line names it (no second "failed:" line)
    assert "Compute Failed" not in capfd.readouterr().err
    assert result.output.count("size 1001 bytes is not a multiple of 16") == 2  # frame line and table


def test_unknown_set_key_exits_2_naming_it(bin_folder: Path, tmp_path: Path) -> None:
    result = _invoke("run", bin_folder, "--out", tmp_path / "out", "--set", "tile.overlapp=2")
    assert result.exit_code == EXIT_BAD_CONFIG
    assert "tile.overlapp: unknown key" in result.stderr
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("sets, message", [
    (["tile.overlap=["], "--set 'tile.overlap=[': the value is not valid YAML at line 1, column 2"),
    (["tile=5", "tile.overlap=1"], "--set tile.overlap: tile is set to 5 by another --set"),
])
def test_set_items_that_cannot_be_read_exit_2_naming_them(sets: list[str], message: str) -> None:
    # tracebacks, exit 1, before (a review)
    result = _invoke("config", *[part for item in sets for part in ("--set", item)])
    assert result.exit_code == EXIT_BAD_CONFIG, result.output
    assert message in result.stderr and "Traceback" not in result.stderr


def test_missing_weights_exit_2_naming_the_file(bin_folder: Path, tmp_path: Path) -> None:
    missing = tmp_path / "absent.pt"
    result = _invoke("run", bin_folder, "--out", tmp_path / "out", "--weights", missing, "--no-progress")
    assert result.exit_code == EXIT_BAD_CONFIG
    assert f"upsample.weights: {missing}: weights file not found" in result.stderr


def test_dry_run_lists_the_frames_and_writes_nothing(bin_folder: Path, tmp_path: Path) -> None:
    result = _invoke("run", bin_folder, "--out", tmp_path / "out", "--dry-run")
    assert result.exit_code == 0, result.output
    sequence = bin_sequence_name(bin_folder)
    assert f"# 2 frames: first bin/{sequence}/000000, last bin/{sequence}/000001; bin/{sequence}: 2" in result.stdout
    assert not (tmp_path / "out").exists()
    assert "# a run now: 2 to run through the network, of which 0 replace finished files; 0 to write in added " \
           "formats from their stored files; 0 finished, skipped" in result.stdout


def test_an_empty_input_or_output_path_is_refused_not_read_as_the_working_folder(
        bin_folder: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    # `kitti-pu run "$UNSET"` read the working folder, and `--out ""` wrote into it (a hostile-input trial)
    here = tmp_path / "here"
    here.mkdir()
    monkeypatch.chdir(here)
    for arguments, key in (([""], "input.path"), ([str(bin_folder), "--out", ""], "output.dir")):
        result = _invoke("run", *arguments)
        assert result.exit_code == 2 and f"{key} is empty (an unset variable?)" in result.output, result.output
    assert list(here.iterdir()) == []


def test_dry_run_says_what_a_rerun_would_do(cli_run: tuple[Result, Path, Path], weights_file: Path,
                                           tmp_path: Path) -> None:
    _, folder, out = cli_run
    copy = Path(shutil.copytree(out, tmp_path / "out"))
    for stale in copy.glob("ply/**/000001.ply"):
        stale.unlink()  # frame 1 to be written in PLY from its Parquet; frame 2 finished
    args = _run_args(folder, copy, weights_file)
    result = _invoke(*args, "--dry-run")
    assert result.exit_code == 0, result.output
    assert "# a run now: 0 to run through the network, of which 0 replace finished files; 1 to write in added " \
           "formats from their stored files; 1 finished, skipped" in result.stdout
    from filelock import FileLock

    with FileLock(copy / ".kitti-pu.lock"):  # another run writing there: the run would exit 4
        busy = _invoke(*args, "--dry-run")
    assert f"# warning: another kitti-pu run is writing to {copy}: a run now would do nothing and exit 4" in busy.stdout
    changed = _invoke(*args, "--dry-run", "--set", "tile.seed=3")
    assert "# a run now: 2 to run through the network, of which 2 replace finished files (2 config changed)" \
        in changed.stdout, changed.stdout


def test_config_prints_the_resolved_yaml(tmp_path: Path) -> None:
    override = tmp_path / "mine.yaml"
    override.write_text("upsample:\n  ratio: 16\n")
    result = _invoke("config", "-c", override, "--set", "tile.overlap=2.0")
    assert result.exit_code == 0, result.output
    printed = yaml.safe_load(result.stdout)
    assert printed["upsample"]["ratio"] == 16 and printed["tile"]["overlap"] == 2.0
    expected = load_config([override], {"tile.overlap": 2.0}).model_dump(mode="json")
    assert printed == expected


def test_config_rejects_a_bad_value_naming_the_key() -> None:
    result = _invoke("config", "--set", "upsample.ratio=1")
    assert result.exit_code == EXIT_BAD_CONFIG
    assert "upsample.ratio" in result.stderr


def test_set_null_clears_a_setting_from_a_file(tmp_path: Path) -> None:
    mine = tmp_path / "mine.yaml"
    mine.write_text("upsample:\n  batch_size: 16\n")
    result = _invoke("config", "-c", mine, "--set", "upsample.batch_size=null")
    assert result.exit_code == 0, result.output
    assert yaml.safe_load(result.stdout)["upsample"]["batch_size"] is None
    # a bad null is refused naming the key (the patch-radius limit is a number; 0 = no limit)
    result = _invoke("config", "--set", "upsample.max_patch_radius=null")
    assert result.exit_code == EXIT_BAD_CONFIG and "upsample.max_patch_radius" in result.stderr


def test_demo_without_open3d_exits_2_naming_the_extra_and_writes_nothing(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setitem(sys.modules, "open3d", None)  # how Python marks a module that cannot be imported
    result = _invoke("demo", "--out", tmp_path / "demo", "--no-progress")
    assert result.exit_code == EXIT_BAD_CONFIG
    assert 'LiDAR with Open3D, the optional open3d extra: pip install "kitti-pu[open3d]"' in result.output
    assert not (tmp_path / "demo").exists()


def test_a_commands_error_is_named_once() -> None:
    from pipeline.cli_common import command_error
    from stages.errors import InputError

    assert command_error("finetune", InputError("finetune", "x.bin", "bad")) == "[finetune] x.bin: bad"
    assert command_error("eval-kitti", InputError("load", "x.bin", "bad")) == "[load] x.bin: bad"
    missing = FileNotFoundError(2, "No such file or directory", "w.pt")  # "[Errno 2] ...": not a stage's
    assert command_error("finetune", missing).startswith("finetune: [Errno 2]")
    assert command_error("finetune", ValueError("finetune: twice")) == "finetune: twice"


def test_a_rerun_without_progress_logs_no_line_per_skipped_frame(cli_run: tuple[Result, Path, Path],
                                                                  weights_file: Path, tmp_path: Path) -> None:
    _, folder, out = cli_run
    copy = Path(shutil.copytree(out, tmp_path / "out"))
    result = _invoke(*_run_args(folder, copy, weights_file))
    assert result.exit_code == 0, result.output
    # one "KEY skipped N -> M points" line per frame, before: 47,000 lines an hour for a full set
    assert not [line for line in result.stdout.splitlines() if " skipped " in line and "->" in line]
    assert "done 0, skipped 2, failed 0 of 2 frames" in result.stdout


def test_demo_arguments_are_checked_before_anything_runs(tmp_path: Path) -> None:
    afile = tmp_path / "afile"
    afile.write_text("")
    result = _invoke("demo", "--out", afile)  # a NotADirectoryError traceback, exit 1, before
    assert result.exit_code == EXIT_BAD_CONFIG and f"{afile} is a file, not a folder" in result.stderr
    assert _invoke("demo", "--frames", "0", "--out", tmp_path / "d").exit_code == EXIT_BAD_CONFIG


def test_dry_run_warns_of_missing_metadata_only_for_frames_a_run_would_load(
        template_scans: list[np.ndarray], weights_file: Path, tmp_path: Path) -> None:
    sequence = tmp_path / "odo" / "sequences" / "00"
    (sequence / "velodyne").mkdir(parents=True)
    template_scans[0].tofile(sequence / "velodyne" / "000000.bin")
    projections = [f"P{i}: 700 0 600 {tx} 0 700 180 0 0 0 1 0" for i, tx in enumerate((0, -380, 45, -340))]
    (sequence / "calib.txt").write_text("\n".join([*projections, "Tr: 0 -1 0 0 0 0 -1 -0.08 1 0 0 -0.27"]) + "\n")
    (sequence / "times.txt").write_text("0.0\n")
    args = _run_args(tmp_path / "odo", tmp_path / "out", weights_file)
    assert _invoke(*args).exit_code == 0
    (sequence / "calib.txt").unlink()
    # "calib.txt missing: its 1 frame would fail", before, of a frame the run then skipped (exit 0)
    finished = _invoke(*args, "--dry-run")
    assert "would fail" not in finished.stdout and "1 finished, skipped" in finished.stdout, finished.stdout
    template_scans[1].tofile(sequence / "velodyne" / "000001.bin")  # a new frame would load, and fail
    grown = _invoke(*args, "--dry-run")
    assert "calib.txt missing: its 1 frame would fail" in grown.stdout, grown.stdout


def test_finetune_refuses_a_negative_time_limit_before_anything_runs(tmp_path: Path) -> None:
    # accepted, and one step was trained (cadpu.train refuses it)
    result = _invoke("finetune", tmp_path, "--out", tmp_path / "w.pt", "--max-seconds", "-1")
    assert result.exit_code == 2 and "Invalid value for '--max-seconds'" in result.output
    assert not (tmp_path / "w.pt.run").exists()


@pytest.mark.parametrize("command", ["run", "demo", "info", "preview", "config", "eval-kitti", "finetune"])
def test_every_option_name_shows_whole_in_an_80_column_help(command: str) -> None:
    import re

    from typer.testing import CliRunner

    # eval-kitti's "--twin-weights,--uniform-we…" (a new user's trial): its former name is hidden now
    result = CliRunner().invoke(app, [command, "-h"], env={"COLUMNS": "80"})
    assert result.exit_code == 0, result.output
    names = re.findall(r"^│[ *]+(-[^ ]+)", result.output, flags=re.MULTILINE)  # "*": a required one
    assert names and not [name for name in names if name.endswith("…")], result.output


def test_the_command_list_does_not_break_a_description_where_its_docstring_wraps() -> None:
    import typer.main
    from typer.testing import CliRunner

    # "the model and" / "the configurations ..." on two lines of the list (a new user's trial)
    for name, command in typer.main.get_command(app).commands.items():
        assert "\n" not in (command.help or "").split("\n\n")[0], name
    listed = CliRunner().invoke(app, ["-h"], env={"COLUMNS": "200"}).output
    assert "the model and the configurations that made each sequence" in listed


def test_no_progress_prints_a_line_for_each_frame_whose_work_ended_and_none_for_the_others(
        capsys: pytest.CaptureFixture[str]) -> None:
    from pipeline.cli_common import echo_frame_line
    from pipeline.summary import FrameReport

    # a lost scheduler printed "interrupted" lines for the frames the cluster cancelled but not for
    # those never sent, and a Ctrl-C none: read as if only those were interrupted (an operator's trial)
    for status in ("done", "replaced", "failed", "skipped", "interrupted"):
        echo_frame_line(FrameReport(key=f"bin/s/{status}", dataset="bin", sequence="s", index=0, status=status))
    printed = capsys.readouterr().out.splitlines()
    assert [line.split()[:2] for line in printed] == [["bin/s/done", "done"], ["bin/s/replaced", "replaced"],
                                                       ["bin/s/failed", "failed"]]
