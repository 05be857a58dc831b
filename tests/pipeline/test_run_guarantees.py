"""What a scheduled run guarantees (issue 21): everything checked before anything runs, one run per
output folder, reruns that notice a changed model or configuration and say so, summaries that add
up to what is on disk, and interrupted runs that still write their summary."""

from __future__ import annotations

import contextlib
import json
import os
import socket
import shutil
import signal
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path
from urllib.parse import urlparse

import numpy as np
import pyarrow.parquet as pq
import pytest
import torch
from distributed import Client
from filelock import FileLock
from typer.testing import CliRunner, Result

from cadpu import weights
from cadpu.network import Generator
from pipeline.cli import app
from pipeline.cluster import local_cluster
from pipeline.config import ConfigError, PipelineConfig, load_config
from pipeline.info import folder_info, format_info
from pipeline.preflight import preflight
from pipeline.runner import LOCK_NAME, RUN_ID_KEY, OutputBusy, _settled, run_pipeline
from pipeline.summary import EXIT_BAD_CONFIG, EXIT_OK, EXIT_OUTPUT_BUSY, RunSummary
from stages import load, write
from stages.discovery import bin_sequence_name

ConfigFactory = Callable[..., PipelineConfig]


def _invoke(*args: object) -> Result:
    return CliRunner().invoke(app, [str(arg) for arg in args])


@pytest.mark.parametrize("setting, message", [
    ("dask.memory_limit=abc", "dask.memory_limit: 'abc' is not 'auto', a size such as '4GiB'"),
    ("dask.memory_limit=true", "dask.memory_limit: True is not 'auto'"),  # it read as 1: all the memory
    # 500 MiB paused the worker and the run waited for ever; 300 MiB failed frames with a CommClosedError
    ("dask.memory_limit=500MiB", "dask.memory_limit: '500MiB' (0.52 GB) is below the 0.95 GB a worker needs"),
    ("dask.memory_limit='0.0001'", "dask.memory_limit: '0.0001' ("),  # a share of memory: it read as 0 bytes
    ("dask.scheduler=notaurl", "dask.scheduler: 'notaurl' is not a Dask scheduler address"),
    # these three crashed with a traceback, exit 1, after creating the output folder
    ("dask.scheduler=tcp://127.0.0.1", "dask.scheduler: 'tcp://127.0.0.1' names no port"),
    ("dask.scheduler=http://127.0.0.1:8786", "the http:// protocol is not one this tool connects with"),
    ("dask.scheduler=tls://127.0.0.1:8786", "the tls:// protocol is not one this tool connects with"),
])
def test_bad_cluster_settings_exit_2_before_anything_is_written(bin_folder: Path, tmp_path: Path, setting: str,
                                                                message: str) -> None:
    out = tmp_path / "out"
    result = _invoke("run", bin_folder, "--out", out, "--no-progress", "--set", setting)
    assert result.exit_code == EXIT_BAD_CONFIG, result.output
    assert message in result.output and not out.exists()


@pytest.mark.skipif(torch.cuda.is_available(), reason="needs a machine without CUDA")
def test_cuda_on_a_machine_without_it_exits_2(bin_folder: Path, tmp_path: Path) -> None:
    result = _invoke("run", bin_folder, "--out", tmp_path / "out", "--set", "upsample.device=cuda")
    assert result.exit_code == EXIT_BAD_CONFIG and "finds no CUDA device" in result.output
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("setting", ["--workers=5", "dask.threads_per_worker=2", "dask.memory_limit=2GB",
                                     "dask.dashboard=true"])
def test_local_cluster_settings_with_an_existing_scheduler_are_refused(bin_folder: Path, tmp_path: Path,
                                                                       setting: str) -> None:
    given = [setting] if setting.startswith("--") else ["--set", setting]
    result = _invoke("run", bin_folder, "--out", tmp_path / "out", "--scheduler", "tcp://127.0.0.1:1", *given)
    # --workers is named as typed too (it named dask.n_workers alone: an external-cluster user's trial)
    key = "n_workers (--workers)" if setting.startswith("--") else setting.partition("=")[0].partition(".")[2]
    assert result.exit_code == EXIT_BAD_CONFIG and f"dask.{key}: sets the tool's own LocalCluster" in result.output


@pytest.mark.parametrize("args, message", [
    (["config", "--set", "tile.patch_size=16"], "needs at least 24 per patch"),
    # the run failed every frame with "need a power-of-two number of parts dividing 800" (a new-user trial)
    (["config", "--set", "tile.patch_size=200", "--set", "upsample.ratio=16"],
     "tile.patch_size: 200 with upsample.ratio 16"),
    (["config", "--set", "upsample.ratio=3"], "upsample.ratio"),
    (["config", "--set", "upsample.weights=nosuch"], "nosuch"),
])
def test_config_checks_the_weights_and_the_ratio(args: list[str], message: str) -> None:
    result = _invoke(*args)
    assert result.exit_code == EXIT_BAD_CONFIG and message in result.output


def test_dry_run_finds_an_output_path_that_is_a_file(bin_folder: Path, tmp_path: Path) -> None:
    taken = tmp_path / "afile"
    taken.write_text("not a folder")
    for out in (taken, taken / "sub"):  # exit 0 on --dry-run, exit 2 on the run
        result = _invoke("run", bin_folder, "--out", out, "--dry-run")
        assert result.exit_code == EXIT_BAD_CONFIG, result.output
        assert f"output.dir: {out} is not writable: {taken} is a file, not a folder" in result.output


@pytest.mark.skipif(not Path("/proc/self").is_dir(), reason="needs Linux's /proc, where nothing can be created")
def test_dry_run_finds_an_output_folder_nothing_can_be_created_in(bin_folder: Path) -> None:
    # --dry-run exited 0 and the run then exited 2 (a new-user trial)
    result = _invoke("run", bin_folder, "--out", "/proc/kitti-pu-out", "--dry-run")
    assert result.exit_code == EXIT_BAD_CONFIG, result.output
    assert ("output.dir: /proc/kitti-pu-out is not writable: nothing can be created in /proc (creating a folder "
            "there failed: ") in result.output  # "(No such file or directory)" alone read as if /proc were missing


def test_dry_run_checks_the_weights(bin_folder: Path, tmp_path: Path) -> None:
    result = _invoke("run", bin_folder, "--out", tmp_path / "out", "--weights", "nosuch", "--dry-run")
    assert result.exit_code == EXIT_BAD_CONFIG and "nosuch" in result.output


def test_patchworkpp_without_its_package_exits_2_before_the_cluster(bin_folder: Path, tmp_path: Path) -> None:
    pytest.importorskip("pytest")  # the test needs pypatchworkpp absent
    import importlib.util

    if importlib.util.find_spec("pypatchworkpp") is not None:
        pytest.skip("pypatchworkpp is installed here")
    result = _invoke("run", bin_folder, "--out", tmp_path / "out", "--ground", "patchworkpp")
    assert result.exit_code == EXIT_BAD_CONFIG and 'pip install "kitti-pu[patchwork]"' in result.output
    assert not (tmp_path / "out").exists()


def test_preview_of_a_scan_instead_of_an_output_exits_2(tmp_path: Path) -> None:
    scan = tmp_path / "000000.bin"
    np.zeros((10, 4), np.float32).tofile(scan)
    result = _invoke("preview", scan)
    assert result.exit_code == EXIT_BAD_CONFIG and "not a kitti-pu output frame" in result.output


def test_relative_paths_are_resolved_before_the_workers_see_them(bin_folder: Path, tmp_path: Path,
                                                                 monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.chdir(bin_folder.parent)
    config = load_config(overrides={"input.path": bin_folder.name, "output.dir": "out"})
    resolved, refs, _ = preflight(config)
    assert resolved.input.path == bin_folder and resolved.output.dir == bin_folder.parent / "out"
    assert all(Path(ref.source).is_absolute() for ref in refs)


def test_a_second_run_on_a_locked_output_folder_is_refused(bin_folder: Path, make_config: ConfigFactory,
                                                           tmp_path: Path) -> None:
    out = tmp_path / "out"
    out.mkdir()
    with FileLock(out / LOCK_NAME):
        with pytest.raises(OutputBusy, match="another kitti-pu run is writing"):
            run_pipeline(make_config(bin_folder, out), progress=False)
        result = _invoke("run", bin_folder, "--out", out, "--no-progress")
        assert result.exit_code == EXIT_OUTPUT_BUSY and "another kitti-pu run" in result.output
        # said at once, before the scans and the weights are read: it took 10 s, and a run with a
        # bad setting exited 2 instead (a new-user trial)
        result = _invoke("run", bin_folder, "--out", out, "--weights", tmp_path / "nosuch.pt")
        assert result.exit_code == EXIT_OUTPUT_BUSY, result.output
    assert not list(out.glob("points/**/*.parquet"))


def _weights_at(path: Path, seed: int) -> Path:
    """An untrained generator drawn with `seed`, saved (with its checksum) at `path`."""
    torch.manual_seed(seed)
    weights.save(Generator(ratio=4), path)
    return path


def test_reruns_replace_frames_of_another_model_or_config_and_skip_with_stored_counts(
        bin_folder: Path, make_config: ConfigFactory, tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    out = tmp_path / "out"
    model = _weights_at(tmp_path / "model.pt", seed=4)
    first = run_pipeline(make_config(bin_folder, out, upsample__weights=str(model)), progress=False)
    assert first.count("done") == 2
    again = run_pipeline(make_config(bin_folder, out, upsample__weights=str(model)), progress=False)
    assert [f.status for f in again.frames] == ["skipped", "skipped"]
    assert [(f.points_in, f.points_out) for f in again.frames] == [(f.points_in, f.points_out) for f in first.frames]
    assert again.to_dict()["points_out_on_disk"] == first.to_dict()["points_out"]
    # the same weights path with new contents (a retrained or upgraded model): not skipped
    _weights_at(model, seed=5)
    seen: list[str] = []  # what --no-progress prints as each frame ends says what the summary says
    replaced = run_pipeline(make_config(bin_folder, out, upsample__weights=str(model)), progress=False,
                            on_report=lambda report: seen.append(report.status))
    assert [(f.status, f.reason) for f in replaced.frames] == [("replaced", "model changed")] * 2
    assert seen == ["replaced"] * 2
    assert "(model changed) and will be done again" in capsys.readouterr().err  # not "are done": one may fail
    changed_config = make_config(bin_folder, out, upsample__weights=str(model), tile__overlap=2.0)
    assert {f.reason for f in run_pipeline(changed_config, progress=False).frames} == {"config changed"}


def test_a_frame_the_cluster_lost_but_complete_on_disk_is_reported_done(bin_folder: Path,
                                                                        make_config: ConfigFactory,
                                                                        tmp_path: Path) -> None:
    config = make_config(bin_folder, tmp_path / "out")
    summary = run_pipeline(config, progress=False)
    refs = load.discover(bin_folder)
    formats = tuple(config.output.formats)
    paths = write.output_paths(Path(config.output.dir), refs[0].dataset, refs[0].sequence, refs[0].index, formats)
    run_id = write.stored_record(paths)[RUN_ID_KEY]
    lost = _settled(refs[0], None, None, Path(config.output.dir), formats, summary.config_hash,
                    summary.model_checksum, run_id)
    assert lost.status == "done" and lost.points_out == summary.frames[0].points_out
    assert "complete on disk" in lost.notes[0]
    never = _settled(refs[0], None, None, tmp_path / "elsewhere", formats, summary.config_hash,
                     summary.model_checksum, run_id)
    assert never.status == "interrupted" and not never.outputs


def test_under_overwrite_an_unreached_frame_is_not_reported_done_but_its_earlier_files_are_counted(
        bin_folder: Path, make_config: ConfigFactory, tmp_path: Path) -> None:
    config = make_config(bin_folder, tmp_path / "out", output__overwrite=True)
    first = run_pipeline(config, progress=False)
    ref = load.discover(bin_folder)[0]
    # a later --overwrite run (another run id) stopped before it reached the frame: its complete
    # files are the first run's
    unreached = _settled(ref, None, None, Path(config.output.dir), tuple(config.output.formats),
                         first.config_hash, first.model_checksum, run_id="a-later-run")
    assert unreached.status == "interrupted"
    assert unreached.points_out == first.frames[0].points_out and unreached.outputs
    assert "earlier run stay in the folder" in unreached.notes[0]
    # every stored count, not the first three only (ground, fill and dropped were 0: an operator's trial)
    for count in ("points_in", "ground", "generated", "ground_filled", "dropped"):
        assert getattr(unreached, count) == getattr(first.frames[0], count), count
    assert first.frames[0].ground  # so that the comparison above can fail


def _rows_on_disk(out: Path) -> int:
    return sum(pq.read_metadata(path).num_rows for path in out.glob("points/**/*.parquet"))


def test_a_replaced_scan_that_fails_leaves_nothing_of_the_earlier_scan(bin_folder: Path,
                                                                       make_config: ConfigFactory,
                                                                       tmp_path: Path) -> None:
    out = tmp_path / "out"
    run_pipeline(make_config(bin_folder, out, output__formats="parquet,ply,kitti"), progress=False)
    scan = sorted(bin_folder.glob("*.bin"))[0]
    scan.write_bytes(scan.read_bytes()[:1003])  # the scan replaced by a broken one
    again = run_pipeline(make_config(bin_folder, out), progress=False)  # parquet and ply only
    failed = again.frames[0]
    assert failed.status == "failed" and not failed.outputs
    assert "earlier scan of this name were removed" in failed.notes[0]
    assert not list(out.glob("*/bin/*/000000.*"))
    # nor in the format this run does not write (the mirror's scan and sidecar stayed)
    assert not list(out.glob("kitti/**/000000.*"))
    assert again.to_dict()["points_out_on_disk"] == _rows_on_disk(out) == again.frames[1].points_out


def test_under_overwrite_a_replaced_scan_that_fails_leaves_nothing_of_the_earlier_scan(
        bin_folder: Path, make_config: ConfigFactory, tmp_path: Path) -> None:
    # with --overwrite the earlier scan's files stayed and were counted as the frame's own
    out = tmp_path / "out"
    run_pipeline(make_config(bin_folder, out, output__formats="parquet,ply"), progress=False)
    scan = sorted(bin_folder.glob("*.bin"))[0]
    scan.write_bytes(scan.read_bytes()[:1003])
    again = run_pipeline(make_config(bin_folder, out, output__formats="parquet", output__overwrite=True),
                         progress=False)
    failed = again.frames[0]
    assert failed.status == "failed" and not failed.outputs and failed.points_out == 0
    assert "earlier scan of this name were removed" in failed.notes[0]
    assert not list(out.glob("*/bin/*/000000.*"))  # the PLY this run does not write included
    assert again.to_dict()["points_out_on_disk"] == _rows_on_disk(out) == again.frames[1].points_out


def test_an_unreached_frame_counts_its_files_in_formats_the_run_does_not_write(
        bin_folder: Path, make_config: ConfigFactory, tmp_path: Path) -> None:
    # a PLY run that never reached a frame whose Parquet file is on disk reported 0 points for it
    config = make_config(bin_folder, tmp_path / "out", output__formats="parquet")
    first = run_pipeline(config, progress=False)
    ref = load.discover(bin_folder)[0]
    unreached = _settled(ref, None, None, Path(config.output.dir), ("ply",), first.config_hash,
                         first.model_checksum, run_id="a-later-run")
    assert unreached.status == "interrupted"
    assert unreached.points_out == first.frames[0].points_out and "parquet" in unreached.outputs
    assert "earlier run stay in the folder" in unreached.notes[0]


def test_a_run_sweeps_the_temporary_of_a_writer_killed_during_it(bin_folder: Path, make_config: ConfigFactory,
                                                                  tmp_path: Path) -> None:
    # a worker killed mid-write left OUT/.tmp/.PID@HOST~...part until the next run swept it
    import socket

    out = tmp_path / "out"
    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True,
                          text=True, check=True).stdout.strip()
    left = out / ".tmp" / f".{dead}@{socket.gethostname()}~0123abcd~000000.parquet.part"

    def killed_writer(_: object) -> None:  # called during the run, after the start's sweep
        left.parent.mkdir(parents=True, exist_ok=True)
        left.write_bytes(b"half a frame")

    run_pipeline(make_config(bin_folder, out), progress=False, on_report=killed_writer)
    assert not left.exists()


def test_a_replaced_frame_leaves_no_file_of_the_earlier_config_in_another_format(
        bin_folder: Path, make_config: ConfigFactory, tmp_path: Path) -> None:
    out = tmp_path / "out"
    first = run_pipeline(make_config(bin_folder, out, output__formats=["parquet", "ply", "kitti"]), progress=False)
    picture = write.preview_path(out, "bin", first.frames[0].sequence, first.frames[0].index)
    picture.parent.mkdir(parents=True)
    picture.write_bytes(b"a preview of the first run's output")
    changed = run_pipeline(make_config(bin_folder, out, output__formats=["parquet"], tile__overlap=2.0),
                           progress=False)
    assert {(f.status, f.reason) for f in changed.frames} == {("replaced", "config changed")}
    assert not list(out.glob("ply/**/*.ply")) and not list(out.glob("kitti/**/*.bin"))
    assert any("removed its ply file" in note for note in changed.frames[0].notes)
    assert not picture.exists()
    # files of the same configuration in another format stay
    run_pipeline(make_config(bin_folder, out, output__formats=["ply"], tile__overlap=2.0), progress=False)
    assert len(list(out.glob("points/**/*.parquet"))) == len(list(out.glob("ply/**/*.ply"))) == 2


def test_a_ply_only_folder_notices_a_changed_config(bin_folder: Path, make_config: ConfigFactory,
                                                    tmp_path: Path) -> None:
    out = tmp_path / "out"
    run_pipeline(make_config(bin_folder, out, output__formats=["ply"]), progress=False)
    again = run_pipeline(make_config(bin_folder, out, output__formats=["ply"], tile__overlap=2.0), progress=False)
    assert {(f.status, f.reason) for f in again.frames} == {("replaced", "config changed")}
    same = run_pipeline(make_config(bin_folder, out, output__formats=["ply"], tile__overlap=2.0), progress=False)
    assert {f.status for f in same.frames} == {"skipped"} and same.frames[0].points_out == again.frames[0].points_out


def test_nothing_to_do_with_a_scheduler_records_that_it_was_not_contacted(bin_folder: Path,
                                                                          make_config: ConfigFactory,
                                                                          tmp_path: Path) -> None:
    out = tmp_path / "out"
    run_pipeline(make_config(bin_folder, out), progress=False)
    config = make_config(bin_folder, out, dask__scheduler="tcp://127.0.0.1:9", dask__n_workers=None,
                         dask__threads_per_worker=None)
    summary = run_pipeline(config, progress=False)
    assert summary.exit_code == EXIT_OK and summary.scheduler.endswith("(not contacted: nothing to do)")
    assert summary.workers == 0


def test_a_cluster_without_dashboard_leaves_port_8787_alone() -> None:
    probe = socket.socket()
    if probe.connect_ex(("127.0.0.1", 8787)) == 0:
        probe.close()
        pytest.skip("something else listens on 8787")
    probe.close()
    with local_cluster(1, dashboard=False):
        probe = socket.socket()
        listening = probe.connect_ex(("127.0.0.1", 8787)) == 0
        probe.close()
    assert not listening


def test_a_dashboard_listens_on_loopback_only_and_the_run_says_where(bin_folder: Path, weights_file: Path,
                                                                    tmp_path: Path) -> None:
    with local_cluster(1, dashboard=True) as cluster, Client(cluster) as client:
        host = urlparse(client.dashboard_link).hostname
    assert host == "127.0.0.1"  # it listened on every interface, on a port nobody was told
    result = _invoke("run", bin_folder, "--out", tmp_path / "out", "--weights", weights_file, "--workers", "1",
                     "--no-progress", "--set", "dask.dashboard=true", "--set", "dask.torch_threads=1",
                     "--set", "upsample.device=cpu", "--last", "0")
    assert result.exit_code == 0, result.output
    assert "kitti-pu: Dask dashboard at http://127.0.0.1:" in result.output


def test_sigint_writes_the_summary_and_exits_130(raw_drive: Path, weights_file: Path, tmp_path: Path) -> None:
    out = tmp_path / "out"
    command = [sys.executable, "-c", "from pipeline.cli import app; app()", "run", str(raw_drive), "--out", str(out),
               "--weights", str(weights_file), "--workers", "1", "--no-progress", "--set", "dask.torch_threads=1",
               "--set", "upsample.device=cpu"]
    # With SIGINT at its default in the child: a process started where SIGINT is ignored (a
    # background job, nohup) inherits that, Python then leaves it ignored, and the run would finish
    # unaware of the signal (this test failed that way when pytest itself ran in the background).
    process = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                               cwd=Path(__file__).resolve().parents[2], env={**os.environ, "PYTHONUNBUFFERED": "1"},
                               preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    deadline = time.monotonic() + 120
    while not (out / LOCK_NAME).exists() and time.monotonic() < deadline:  # the run has started
        time.sleep(0.1)
    time.sleep(1.0)
    process.send_signal(signal.SIGINT)
    stdout, stderr = process.communicate(timeout=120)
    assert process.returncode == 130, stderr
    assert "interrupted by SIGINT:" in stderr and "frames done" in stderr
    summary = json.loads((out / "summary.json").read_text())
    # the record tells a scheduler what the process's status did: interrupted, 130
    assert summary["interrupted"] is True and summary["interrupted_by"] == "SIGINT"
    assert summary["exit_code"] == 130
    assert "(stopped by SIGINT) of" in format_info(folder_info(out)) and "(exit 130," in format_info(folder_info(out))
    on_disk = len(list(out.glob("points/**/*.parquet")))
    assert summary["frames_done"] == on_disk
    assert {frame["status"] for frame in summary["frames"]} <= {"done", "interrupted"}


def test_a_scan_replaced_in_place_is_redone_not_skipped(bin_folder: Path, make_config: ConfigFactory,
                                                        template_scans: list[np.ndarray], tmp_path: Path) -> None:
    out = tmp_path / "out"
    first = run_pipeline(make_config(bin_folder, out), progress=False)
    scans = sorted(bin_folder.glob("*.bin"))
    template_scans[1][::2].astype(np.float32).tofile(scans[0])  # another scan under the first one's name
    again = run_pipeline(make_config(bin_folder, out), progress=False)
    assert [(f.status, f.reason) for f in again.frames] == [("replaced", "source changed"), ("skipped", None)]
    assert again.frames[0].points_in == len(template_scans[1][::2]) != first.frames[0].points_in


def test_a_scheduler_found_unreachable_once_running_leaves_no_output_folder(
        bin_folder: Path, make_config: ConfigFactory, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    import pipeline.runner

    def unreachable(config: PipelineConfig, plan: object) -> None:
        raise ConfigError("dask.scheduler: cannot reach tcp://127.0.0.1:1 (timed out)")

    monkeypatch.setattr(pipeline.runner, "open_client", unreachable)
    out = tmp_path / "new" / "out"
    with pytest.raises(ConfigError, match="cannot reach"):
        run_pipeline(make_config(bin_folder, out), progress=False)
    assert not out.exists()
    kept = tmp_path / "kept"
    (kept / "mine.txt").parent.mkdir()
    (kept / "mine.txt").write_text("a folder the user had")
    with pytest.raises(ConfigError):
        run_pipeline(make_config(bin_folder, kept), progress=False)
    assert (kept / "mine.txt").is_file()


def test_an_unreachable_scheduler_stops_the_run_before_it_writes_added_formats(
        bin_folder: Path, make_config: ConfigFactory, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    import shutil

    import pipeline.runner

    out = tmp_path / "out"
    run_pipeline(make_config(bin_folder, out, **{"input.last_frame": 0}), progress=False)
    summary_before = (out / "summary.json").read_text()
    shutil.copy(bin_folder / "000000.bin", bin_folder / "000002.bin")  # a new scan for the network

    def unreachable(config: PipelineConfig, plan: object) -> None:
        raise ConfigError("dask.scheduler: cannot reach tcp://127.0.0.1:1 (timed out)")

    monkeypatch.setattr(pipeline.runner, "open_client", unreachable)
    with pytest.raises(ConfigError, match="cannot reach"):
        run_pipeline(make_config(bin_folder, out, **{"output.formats": ["parquet", "kitti"]}), progress=False)
    # frame 0's KITTI files were written from its Parquet file first, then the run exited 2
    # saying nothing ran, its summary the previous run's (a new-user trial)
    assert not (out / "kitti").exists()
    assert (out / "summary.json").read_text() == summary_before


def test_a_cluster_lost_before_any_frame_leaves_the_frames_interrupted_not_failed(
        bin_folder: Path, make_config: ConfigFactory, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    import contextlib

    import pipeline.runner
    from distributed.comm.core import CommClosedError

    @contextlib.contextmanager
    def lost(config: PipelineConfig, plan: object):  # noqa: ANN202
        # what the client raised when the scheduler was killed as it set the workers up (a new-user trial)
        raise CommClosedError("in <TCP (closed) ConnectionPool.register_worker_plugin local=tcp://127.0.0.1:1>")
        yield

    monkeypatch.setattr(pipeline.runner, "open_client", lost)
    summary = run_pipeline(make_config(bin_folder, tmp_path / "out"), progress=False)
    # every frame was "failed" with failed_stage None, and `info` listed them as failures
    assert {frame.status for frame in summary.frames} == {"interrupted"}
    assert all("the cluster was lost (CommClosedError" in frame.notes[0] for frame in summary.frames)
    assert summary.exit_code == 3


class LateSignal(Exception):
    """Raised by the test's own handler: a signal the run did not hold."""


@pytest.mark.parametrize("signum", [signal.SIGINT, signal.SIGTERM])
def test_a_signal_after_the_frames_leaves_the_summary_and_the_result_agreeing(
        bin_folder: Path, tmp_path: Path, make_config: ConfigFactory, monkeypatch: pytest.MonkeyPatch,
        signum: int) -> None:
    def raising(number: int, frame: object) -> None:
        raise LateSignal(number)

    write_json = RunSummary.write_json

    def signalled_while_writing(self: RunSummary, path: Path, **options: bool) -> None:
        os.kill(os.getpid(), signum)  # as a scheduler's Ctrl-C or kill lands in the run's last steps
        write_json(self, path, **options)

    monkeypatch.setattr(RunSummary, "write_json", signalled_while_writing)
    config = make_config(bin_folder, tmp_path / "out")
    saved = {number: signal.signal(number, raising) for number in (signal.SIGINT, signal.SIGTERM)}
    try:
        summary = run_pipeline(config, progress=False)  # LateSignal here when the run does not hold it
        handlers_after = {number: signal.getsignal(number) for number in saved}
    finally:
        for number, handler in saved.items():
            signal.signal(number, handler)
    assert summary.exit_code == EXIT_OK
    assert json.loads((tmp_path / "out" / "summary.json").read_text())["exit_code"] == EXIT_OK
    assert all(handler is raising for handler in handlers_after.values())  # the caller's handlers are back


def test_a_signal_while_the_cluster_closes_after_the_frames_is_dropped(
        bin_folder: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    import contextlib

    import pipeline.runner

    real = pipeline.runner.open_client

    @contextlib.contextmanager
    def signalled_on_close(config: PipelineConfig, plan: object):  # noqa: ANN202
        with real(config, plan) as client:
            yield client
            os.kill(os.getpid(), signal.SIGINT)  # a real Ctrl-C as the cluster starts to close

    monkeypatch.setattr(pipeline.runner, "open_client", signalled_on_close)
    result = _invoke("run", bin_folder, "--out", tmp_path / "out", "--no-progress")
    # it escaped the run once: "stopped by SIGINT before the run began; no frame was processed", with
    # both frames written and summary.json the previous run's (a new-user trial); then it exited 130,
    # "interrupted by SIGINT: 2 of 2 frames done", which a scheduler reads as a run to repeat (an
    # operator's trial: a timeout's signal just after the last frame)
    assert result.exit_code == 0, result.output
    assert "interrupted" not in result.output and "before the run began" not in result.output
    summary = json.loads((tmp_path / "out" / "summary.json").read_text())
    assert summary["interrupted_by"] is None and summary["frames_done"] == 2 and summary["exit_code"] == 0


def test_an_output_folder_inside_the_input_is_not_read_as_input(template_scans: list[np.ndarray], tmp_path: Path,
                                                                make_config: ConfigFactory) -> None:
    base = tmp_path / "odometry"
    (base / "sequences" / "00" / "velodyne").mkdir(parents=True)
    for index, scan in enumerate(template_scans):
        scan.tofile(base / "sequences" / "00" / "velodyne" / f"{index:06d}.bin")
    (base / "sequences" / "00" / "times.txt").write_text("0.0\n0.1\n")
    projection = " ".join(["700", "0", "600", "0", "0", "700", "180", "0", "0", "0", "1", "0"])
    (base / "sequences" / "00" / "calib.txt").write_text("\n".join([f"P{i}: {projection}" for i in range(4)]
                                                                   + ["Tr: 0 -1 0 0 0 0 -1 -0.08 1 0 0 -0.27"]) + "\n")
    config = make_config(base, base, output__formats="parquet,kitti")  # the mirror: base/kitti/sequences/00
    first = run_pipeline(config, progress=False)
    assert first.count("done") == 2, [f.error for f in first.frames]
    # the KITTI mirror under the input was discovered as scans: "two scans would write the same
    # output", exit 2, on every later run of a scheduled job
    again = run_pipeline(config, progress=False)
    assert [f.status for f in again.frames] == ["skipped", "skipped"]


#: Runs `kitti-pu ARGS` through its entry point, sending this process SIGNAL when the module
#: IMPORTER imports its sibling MODULE (`from .MODULE import ...`): a signal that arrives while the
#: program loads its modules, at a moment a test can name.
_SIGNAL_DURING_IMPORT = """
import builtins, os, signal, sys
import pipeline.entry
importer, module, number = sys.argv[1], sys.argv[2], int(sys.argv[3])
real_import = builtins.__import__
def importing(name, globals=None, locals=None, fromlist=(), level=0):
    if level == 1 and name == module and (globals or {}).get("__name__") == importer:
        builtins.__import__ = real_import
        os.kill(os.getpid(), number)
    return real_import(name, globals, locals, fromlist, level)
builtins.__import__ = importing
sys.argv = ["kitti-pu", *sys.argv[4:]]
pipeline.entry.main()
"""


@pytest.mark.parametrize("importer, module, signum, code, line", [
    # the command line's modules
    ("pipeline.entry", "cli", signal.SIGTERM, 143, "kitti-pu: stopped by SIGTERM while starting; nothing was done"),
    ("pipeline.entry", "cli", signal.SIGINT, 130, "kitti-pu: stopped by SIGINT while starting; nothing was done"),
    # the runner's (Dask, torch), which `run` loads
    ("pipeline.cli", "runner", signal.SIGTERM, 143,
     "kitti-pu: stopped by SIGTERM before the run began; no frame was processed"),
    ("pipeline.cli", "runner", signal.SIGINT, 130,
     "kitti-pu: stopped by SIGINT before the run began; no frame was processed"),
])
def test_a_signal_while_the_program_starts_exits_with_its_status_and_one_line(
        bin_folder: Path, tmp_path: Path, importer: str, module: str, signum: int, code: int, line: str) -> None:
    # SIGTERM in the first seconds ended the program without a word (status -15), SIGINT in a
    # traceback from inside an import (a scheduled-run trial)
    done = subprocess.run([sys.executable, "-c", _SIGNAL_DURING_IMPORT, importer, module, str(int(signum)),
                           "run", str(bin_folder), "--out", str(tmp_path / "out"), "--no-progress"],
                          capture_output=True, text=True, timeout=300)
    assert done.returncode == code, done.stderr[-2000:]
    assert done.stderr.strip() == line
    assert not (tmp_path / "out" / "points").exists()


@pytest.mark.parametrize("signum, code", [(signal.SIGTERM, 143), (signal.SIGINT, 130)])
def test_a_signal_while_the_run_loads_its_weights_exits_with_its_status_not_a_traceback(
        bin_folder: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch, signum: int, code: int) -> None:
    from pipeline import preflight

    real = preflight.check_weights

    def signalled(config):  # noqa: ANN001, ANN202
        os.kill(os.getpid(), signum)  # a real signal, at the moment a cron timeout hit it (a new-user trial)
        return real(config)

    monkeypatch.setattr(preflight, "check_weights", signalled)
    result = _invoke("run", bin_folder, "--out", tmp_path / "out")
    # SIGTERM exited 1 (the status of a crash) with a traceback ending in runner.Terminated
    assert result.exit_code == code, result.output
    name = "SIGTERM" if signum == signal.SIGTERM else "SIGINT"
    assert f"kitti-pu: stopped by {name} before the run began; no frame was processed" in result.output
    assert not (tmp_path / "out" / "points").exists()


def _drive_written(raw_drive: Path, make_config: ConfigFactory, out: Path) -> tuple[RunSummary, list]:
    """The summary of a first run over the two-frame `raw_drive` into `out`, both frames done, and
    each frame's cloud as its Parquet file stores it."""
    from stages.stored import read_cloud

    first = run_pipeline(make_config(raw_drive, out), progress=False)
    assert first.count("done") == 2
    return first, [read_cloud("parquet", Path(frame.outputs["parquet"])) for frame in first.frames]


def test_a_dataset_moved_or_touched_is_recorded_again_without_the_network(raw_drive: Path,
                                                                            make_config: ConfigFactory,
                                                                            tmp_path: Path) -> None:
    # a dataset copied elsewhere with its times (cp -rp), or a scan touched, redid every frame
    # through the network as "source changed": hours on a full KITTI set (a batch user's trial)
    from stages.stored import read_cloud

    out = tmp_path / "out"
    first, before = _drive_written(raw_drive, make_config, out)
    moved_base = tmp_path / "moved"
    shutil.copytree(raw_drive, moved_base)  # copy2: sizes and modification times kept, new paths
    moved = run_pipeline(make_config(moved_base, out), progress=False)
    assert [(f.status, f.reason) for f in moved.frames] == [("replaced", "source moved")] * 2
    for frame, points in zip(moved.frames, before):
        assert "upsample" not in frame.timings  # recorded anew from the stored points
        assert any("its new record (timestamp, pose, scan path) written in parquet, ply" in note for note in frame.notes)
        after = read_cloud("parquet", Path(frame.outputs["parquet"]))
        assert np.array_equal(after.xyz, points.xyz) and np.array_equal(after.parent, points.parent)
        for name in ("parquet", "ply"):
            record = write.stored_record({name: Path(frame.outputs[name])})
            assert record["source"] == frame.source and str(moved_base) in frame.source
            assert not write.fingerprint_differs(record[write.SOURCE_KEY], load.source_fingerprint(frame.source))
    scans = [Path(frame.source) for frame in moved.frames]
    os.utime(scans[0], ns=(scans[0].stat().st_atime_ns, scans[0].stat().st_mtime_ns + 10**9))  # touched
    changed = np.fromfile(scans[1], np.float32)
    changed[3] = np.float32(0.5) if changed[3] != np.float32(0.5) else np.float32(0.25)  # a reflectance: same size
    changed.tofile(scans[1])
    again = run_pipeline(make_config(moved_base, out), progress=False)
    assert [(f.status, f.reason) for f in again.frames] == [("replaced", "source touched"),
                                                             ("replaced", "source changed")]
    assert "upsample" not in again.frames[0].timings and "upsample" in again.frames[1].timings
    assert [f.status for f in run_pipeline(make_config(moved_base, out), progress=False).frames] == ["skipped"] * 2


def test_a_move_half_recorded_by_a_killed_run_is_recorded_again_in_every_format(raw_drive: Path,
                                                                                   make_config: ConfigFactory,
                                                                                   tmp_path: Path) -> None:
    # a kill between the renames of a moved frame's formats left Parquet on the new path and PLY on
    # the old: the rerun wrote the missing KITTI copy and reported the frame done, its PLY naming a
    # path gone (frame 0), or ran the network for a frame it called "source moved" (frame 1); a
    # broken link among the moved scans crashed the whole run (a JSONDecodeError; an operator's trial)
    formats = ["parquet", "ply", "kitti"]
    out, recorded = tmp_path / "out", tmp_path / "recorded"
    first = run_pipeline(make_config(raw_drive, out, output__formats=formats), progress=False)
    assert first.count("done") == 2
    moved_base = tmp_path / "moved"
    shutil.copytree(raw_drive, moved_base)
    shutil.copytree(out, recorded)
    assert run_pipeline(make_config(moved_base, recorded, output__formats=formats), progress=False).count("replaced") == 2
    for frame in first.frames:  # the state the kill left: Parquet recorded anew, PLY not; frame 0's KITTI copy gone
        shutil.copy2(recorded / Path(frame.outputs["parquet"]).relative_to(out), frame.outputs["parquet"])
    Path(first.frames[0].outputs["kitti"]).unlink()
    again = run_pipeline(make_config(moved_base, out, output__formats=formats), progress=False)
    assert [(f.status, f.reason) for f in again.frames] == [("replaced", "source moved")] * 2
    for frame in again.frames:
        assert "upsample" not in frame.timings
        for name in formats:
            assert write.stored_record({name: Path(frame.outputs[name])})["source"] == frame.source, name
    scan = Path(again.frames[0].source)
    scan.unlink()
    scan.symlink_to(tmp_path / "nowhere" / scan.name)  # a broken link: its frame fails, the other is done
    broken = run_pipeline(make_config(moved_base, tmp_path / "out3", output__formats=formats), progress=False)
    assert [f.status for f in broken.frames] == ["failed", "done"]
    assert "cannot read scan" in broken.frames[0].error
    shutil.copytree(out, tmp_path / "out4")
    rerun = run_pipeline(make_config(moved_base, tmp_path / "out4", output__formats=formats), progress=False)
    assert [f.status for f in rerun.frames] == ["failed", "skipped"]


def test_a_corrected_timestamp_or_pose_redoes_only_the_frames_it_changes(raw_drive: Path,
                                                                          make_config: ConfigFactory,
                                                                          tmp_path: Path) -> None:
    from stages.stored import read_cloud

    out = tmp_path / "out"
    first, stored = _drive_written(raw_drive, make_config, out)
    points_before = stored[1]
    drive = next(raw_drive.glob("*/*_sync"))
    stamps = drive / "oxts" / "timestamps.txt"
    lines = stamps.read_text().splitlines(keepends=True)
    lines[1] = lines[1][:17] + "59.000000000\n"  # frame 1's time of day, corrected
    stamps.write_text("".join(lines))
    told: list[tuple[str, str | None]] = []
    again = run_pipeline(make_config(raw_drive, out), progress=False,
                         on_report=lambda report: told.append((report.status, report.reason)))
    assert [(f.status, f.reason) for f in again.frames] == [("skipped", None), ("replaced", "timestamp changed")]
    # its per-frame line said "done" while the table and summary.json said "replaced" (an operator's trial)
    assert told == [("skipped", None), ("replaced", "timestamp changed")]
    stored = write.stored_record({"parquet": Path(again.frames[1].outputs["parquet"])})
    assert stored["timestamp"] == repr(load.frame_metadata(load.discover(raw_drive)[1])[0])
    # recorded anew from the stored points, in every format, without the network (no stage but
    # load and the writers reads a timestamp or pose; the network took about a second a frame)
    assert any("its new record (timestamp, pose, scan path) written in parquet, ply from its parquet file" in note
               for note in again.frames[1].notes), again.frames[1].notes
    assert "upsample" not in again.frames[1].timings
    assert write.stored_record({"ply": Path(again.frames[1].outputs["ply"])})["timestamp"] == stored["timestamp"]
    points_after = read_cloud("parquet", Path(again.frames[1].outputs["parquet"]))
    assert np.array_equal(points_after.xyz, points_before.xyz) and np.array_equal(points_after.parent, points_before.parent)
    packet = drive / "oxts" / "data" / f"{1:010d}.txt"
    numbers = packet.read_text().split()
    numbers[0] = repr(float(numbers[0]) + 1e-5)  # frame 1's latitude, about a metre north
    packet.write_text(" ".join(numbers) + "\n")
    moved = run_pipeline(make_config(raw_drive, out), progress=False)
    assert [(f.status, f.reason) for f in moved.frames] == [("skipped", None), ("replaced", "pose changed")]
    # the frames now record what the dataset says, and a line for a frame still to come (the drive
    # grows) changes none of them: the next run has nothing to do
    with stamps.open("a") as grown:
        grown.write(lines[1][:17] + "59.100000000\n")
    assert [f.status for f in run_pipeline(make_config(raw_drive, out), progress=False).frames] == ["skipped"] * 2


def info_verified(out: Path) -> bool:
    """Whether every frame file of `out` reads whole (`kitti-pu info --verify`)."""
    from pipeline.info import damaged_frame_files

    return damaged_frame_files(out) == []


def test_a_renamed_scan_leaves_one_copy_of_its_frame_in_the_kitti_mirror(bin_folder: Path,
                                                                         make_config: ConfigFactory,
                                                                         tmp_path: Path) -> None:
    # the mirror names a scan after its input file: the old name's copy stayed beside the new one,
    # four scans for three frames, and KITTI readers of the mirror read the frame twice
    out = tmp_path / "out"
    formats = ["parquet", "kitti"]
    run_pipeline(make_config(bin_folder, out, output__formats=formats), progress=False)
    (bin_folder / "000001.bin").rename(bin_folder / "1.bin")
    again = run_pipeline(make_config(bin_folder, out, output__formats=formats), progress=False)
    assert [(f.status, f.reason) for f in again.frames] == [("skipped", None), ("replaced", "source changed")]
    assert any("under an earlier name (000001.bin)" in note for note in again.frames[1].notes)
    mirror = Path(again.frames[1].outputs["kitti"]).parent
    assert sorted(p.name for p in mirror.glob("*.bin")) == ["000000.bin", "1.bin"]
    assert sorted(p.name for p in (mirror / "kitti_pu").glob("*.npz")) == ["000000.npz", "1.npz"]
    # a rename of the suffix's case alone, over a mirror of an earlier version that kept the
    # input's ".BIN": the two copies share one sidecar, which must stay
    (mirror / "000000.bin").rename(mirror / "000000.BIN")
    (bin_folder / "000000.bin").rename(bin_folder / "000000.BIN")
    cased = run_pipeline(make_config(bin_folder, out, output__formats=formats), progress=False)
    assert [f.status for f in cased.frames] == ["replaced", "skipped"]
    assert sorted(p.name for p in mirror.iterdir() if p.is_file()) == ["000000.bin", "1.bin"]  # as readers glob
    assert sorted(p.name for p in (mirror / "kitti_pu").glob("*.npz")) == ["000000.npz", "1.npz"]
    assert info_verified(out)
    # in KITTI format alone: the rename is a replacement too (reported "done", no warning, before)
    kitti_only = make_config(bin_folder, out, output__formats=["kitti"])
    (bin_folder / "1.bin").rename(bin_folder / "01.bin")
    alone = run_pipeline(kitti_only, progress=False)
    assert [(f.status, f.reason) for f in alone.frames] == [("skipped", None), ("replaced", "source changed")]
    assert sorted(p.name for p in mirror.iterdir() if p.is_file()) == ["000000.bin", "01.bin"]


def test_info_warns_of_a_sequence_from_two_input_folders_and_of_a_scan_held_twice(
        raw_drive: Path, make_config: ConfigFactory, tmp_path: Path) -> None:
    # another copy of the drive run into the same folder replaced frame 0 with its own scan, and the
    # drive's scans run again as a plain folder were kept as a second sequence: info said nothing
    out = tmp_path / "out"
    run_pipeline(make_config(raw_drive, out), progress=False)
    assert not any(line.startswith("warning") for line in format_info(folder_info(out)).splitlines())
    other = Path(shutil.copytree(raw_drive, tmp_path / "other_copy"))
    run_pipeline(make_config(other, out, input__last_frame=0), progress=False)
    scans = next(raw_drive.glob("*/*_sync")) / "velodyne_points" / "data"
    run_pipeline(make_config(scans, out, input__first_frame=1), progress=False)
    info = folder_info(out)
    (raw,) = [entry for entry in info["sequences"] if entry["dataset"] == "raw"]
    assert sorted(raw["input_folders"].values()) == [1, 1]
    scan = str(scans / f"{1:010d}.bin")
    assert list(info["scans_twice"]) == [scan] and len(info["scans_twice"][scan]) == 2
    assert f"bin/{bin_sequence_name(scans)}/000001" in info["scans_twice"][scan]  # keys as everywhere else
    text = format_info(info)
    assert f"warning: raw {raw['sequence']} holds frames of 2 input folders" in text
    assert "warning: 1 scan(s) are in the folder as more than one frame" in text and scan in text


def test_a_corrected_timestamp_leaves_no_file_of_the_old_one_in_a_format_the_rerun_does_not_write(
        raw_drive: Path, make_config: ConfigFactory, tmp_path: Path) -> None:
    # the PLY kept the old timestamp beside the Parquet file's new one, and a later run adding PLY
    # back redid the frame through the network
    out = tmp_path / "out"
    run_pipeline(make_config(raw_drive, out, output__formats=["parquet", "ply"]), progress=False)
    stamps = next(raw_drive.glob("*/*_sync")) / "oxts" / "timestamps.txt"
    lines = stamps.read_text().splitlines(keepends=True)
    lines[1] = lines[1][:17] + "59.000000000\n"
    stamps.write_text("".join(lines))
    again = run_pipeline(make_config(raw_drive, out, output__formats=["parquet"]), progress=False)
    assert [(f.status, f.reason) for f in again.frames] == [("skipped", None), ("replaced", "timestamp changed")]
    assert any("removed its ply file" in note for note in again.frames[1].notes)
    plys = sorted(p.name for p in out.glob("ply/**/*.ply"))
    assert plys == [f"{0:06d}.ply"]  # frame 0's stays: its record still matches


def test_a_file_of_another_format_is_judged_against_the_scan_as_the_new_files_read_it(
        bin_folder: Path, make_config: ConfigFactory, template_scans: list[np.ndarray], tmp_path: Path) -> None:
    # a scan replaced after the run found it: the new Parquet file records the scan it read, while
    # the PLY of the old scan matched the fingerprint taken at discovery, and stayed for good
    from pipeline.chain import Chain
    from pipeline.runner import _remove_stale_formats

    out = tmp_path / "out"
    both = make_config(bin_folder, out, output__formats=["parquet", "ply"])
    run_pipeline(both, progress=False)
    discovered = load.discover(bin_folder, kind="bin")[0]  # as the run found it
    template_scans[1][::2].astype(np.float32).tofile(Path(discovered.source))  # replaced, then read
    parquet_only = make_config(bin_folder, out, output__formats=["parquet"], output__overwrite=True)
    Chain(parquet_only, {"model_checksum": weights.sha256_of(Path(parquet_only.upsample.weights))}).run(discovered)
    notes = _remove_stale_formats(discovered, out, ("parquet",), parquet_only.output_hash(),
                                  weights.sha256_of(Path(parquet_only.upsample.weights)))
    assert notes and "removed its ply file" in notes[0]
    assert not list(out.glob("ply/**/000000.ply"))


def test_an_unreachable_scheduler_stops_a_run_of_added_formats_before_it_writes_them(
        bin_folder: Path, make_config: ConfigFactory, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    # every frame finished: only formats to add, one from a stored file damaged inside, which then
    # needed the network; the other frame's files were written, and the run exited 2 "nothing ran"
    import pipeline.runner

    out = tmp_path / "out"
    run_pipeline(make_config(bin_folder, out, output__formats=["parquet"]), progress=False)
    summary_before = (out / "summary.json").read_text()
    stored = sorted(out.glob("points/**/*.parquet"))[1]
    damaged = bytearray(stored.read_bytes())
    damaged[2000] ^= 0xFF  # a page's bytes: its footer still reads, its CRC does not
    stored.write_bytes(bytes(damaged))

    def unreachable(config: PipelineConfig, plan: object) -> None:
        raise ConfigError("dask.scheduler: cannot reach tcp://127.0.0.1:1 (timed out)")

    monkeypatch.setattr(pipeline.runner, "open_client", unreachable)
    config = make_config(bin_folder, out, output__formats=["parquet", "kitti"],
                         dask__scheduler="tcp://127.0.0.1:1", dask__n_workers=None, dask__threads_per_worker=None)
    with pytest.raises(ConfigError, match="cannot reach"):
        run_pipeline(config, progress=False)
    assert not (out / "kitti").exists()
    assert (out / "summary.json").read_text() == summary_before


def test_the_kitti_mirror_takes_up_corrected_metadata_that_redoes_no_frame(
        template_scans: list[np.ndarray], make_config: ConfigFactory, tmp_path: Path) -> None:
    # every frame was skipped, so the mirror kept the old calibration and times for good; a poses
    # file removed from the input stayed in the mirror, beside frames that now record no pose
    base = tmp_path / "odometry"
    sequence = base / "sequences" / "00"
    (sequence / "velodyne").mkdir(parents=True)
    for index, scan in enumerate(template_scans):
        scan.tofile(sequence / "velodyne" / f"{index:06d}.bin")
    calib = "\n".join([*(f"P{i}: 700 0 600 0 0 700 180 0 0 0 1 0" for i in range(4)),
                       "Tr: 0 -1 0 0 0 0 -1 -0.08 1 0 0 -0.27"]) + "\n"
    (sequence / "calib.txt").write_text(calib)
    (sequence / "times.txt").write_text("0.0\n0.1\n")
    (base / "poses").mkdir()
    (base / "poses" / "00.txt").write_text("1 0 0 0 0 1 0 0 0 0 1 0\n1 0 0 1 0 1 0 0 0 0 1 0\n")
    out = tmp_path / "out"
    config = make_config(base, out, output__formats=["parquet", "kitti"])
    assert run_pipeline(config, progress=False).count("done") == 2
    mirror = out / "kitti" / "sequences" / "00"
    (sequence / "calib.txt").write_text(calib.replace("-0.27", "-0.25"))  # Tr corrected: no pose recorded here
    (sequence / "times.txt").write_text("0.0\n0.1\n0.2\n")  # a frame still to come
    assert [f.status for f in run_pipeline(config, progress=False).frames] == ["replaced", "replaced"]
    assert (mirror / "calib.txt").read_text() == (sequence / "calib.txt").read_text()
    assert (mirror / "times.txt").read_text() == "0.0\n0.1\n0.2\n"
    (sequence / "times.txt").write_text("0.0\n0.1\n0.2\n0.3\n")  # grows again: no frame redone
    assert [f.status for f in run_pipeline(config, progress=False).frames] == ["skipped", "skipped"]
    assert (mirror / "times.txt").read_text() == "0.0\n0.1\n0.2\n0.3\n"
    (base / "poses" / "00.txt").unlink()
    assert {f.reason for f in run_pipeline(config, progress=False).frames} == {"pose changed"}
    assert not (out / "kitti" / "poses" / "00.txt").exists()


def test_a_finished_frame_whose_timestamp_became_unreadable_is_kept_and_said(raw_drive: Path,
                                                                              make_config: ConfigFactory,
                                                                              tmp_path: Path) -> None:
    # its stored file stayed and the rerun said nothing (exit 0, the table empty): the damaged line
    # of the dataset went unnoticed until a frame was added after it
    out = tmp_path / "out"
    assert run_pipeline(make_config(raw_drive, out), progress=False).count("done") == 2
    stamps = next(raw_drive.glob("*/*_sync")) / "oxts" / "timestamps.txt"
    lines = stamps.read_text().splitlines(keepends=True)
    lines[1] = "garbage\n"
    stamps.write_text("".join(lines))
    again = run_pipeline(make_config(raw_drive, out), progress=False)
    assert [f.status for f in again.frames] == ["skipped", "skipped"]
    assert again.frames[0].notes == []
    (note,) = again.frames[1].notes
    assert note.startswith("kept as stored, though its timestamp or pose cannot be read now") and str(stamps) in note
    assert again.frames[1].key in again.table() and again.frames[0].key not in again.table()


def test_a_run_killed_before_it_settled_leaves_a_mark_and_the_next_removes_the_old_formats(
        bin_folder: Path, make_config: ConfigFactory, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    # killed (kill -9) while it replaced the frames with another configuration in Parquet alone: their
    # PLY files of the old configuration stayed for good, the next run skipped the frames, and
    # `info --verify` said "verified" (a scheduled-run trial)
    import pipeline.runner
    from pipeline.info import damaged_frame_files

    out = tmp_path / "out"
    assert run_pipeline(make_config(bin_folder, out, output__formats=["parquet", "ply"]), progress=False).count("done") == 2
    changed = make_config(bin_folder, out, output__formats=["parquet"], tile__patch_size=128)

    def killed(*args: object, **kwargs: object) -> None:
        raise SystemExit(137)  # the process ends here, its frames written, none settled

    with monkeypatch.context() as patched:
        patched.setattr(pipeline.runner, "_settled", killed)
        with pytest.raises(SystemExit):
            run_pipeline(changed, progress=False)
    plys = sorted((out / "ply").rglob("*.ply"))
    assert len(plys) == 2
    info = folder_info(out)
    (mark,) = info["unfinished_runs"]
    assert "did not finish (killed?)" in format_info(info)
    damaged = damaged_frame_files(out)
    assert sorted(entry.split(" (")[0] for entry in damaged) == [str(path) for path in plys]
    assert all("records another configuration than its parquet file" in entry for entry in damaged)
    # a run of frame 0 alone checks frame 0, and leaves frame 1 to a later run: the mark was
    # cleared, and frame 1's old PLY stayed for good (a review)
    first_only = run_pipeline(make_config(bin_folder, out, output__formats=["parquet"], tile__patch_size=128,
                                          input__last_frame=0), progress=False)
    assert [f.status for f in first_only.frames] == ["skipped"]
    assert any("removed its ply file" in note for note in first_only.frames[0].notes)
    assert [path.name for path in sorted((out / "ply").rglob("*.ply"))] == ["000001.ply"]
    (left,) = folder_info(out)["unfinished_runs"]
    assert left["mark"] == mark["mark"] and left["frames"] == [again_key := first_only.frames[0].key.replace("000000", "000001")]
    again = run_pipeline(changed, progress=False)
    assert [f.status for f in again.frames] == ["skipped"] * 2 and again.frames[1].key == again_key
    assert any("removed its ply file" in note for note in again.frames[1].notes) and not again.frames[0].notes
    assert not list((out / "ply").rglob("*.ply")) and not Path(mark["mark"]).exists()
    assert folder_info(out)["unfinished_runs"] == [] and damaged_frame_files(out) == []


def test_a_frame_redone_for_a_damaged_stored_file_says_so_and_info_names_changed_scans(
        bin_folder: Path, make_config: ConfigFactory, tmp_path: Path) -> None:
    # the dry-run said "to write in added formats", the run found the stored file damaged, redid
    # the frame through the network and reported it "done" without a word: the only sign of the
    # disk's damage was lost; and `info` said nothing of a scan changed since its frame was made
    out = tmp_path / "out"
    run_pipeline(make_config(bin_folder, out, output__formats=["parquet"]), progress=False)
    stored = sorted(out.glob("points/**/*.parquet"))[1]
    damaged = bytearray(stored.read_bytes())
    damaged[2000] ^= 0xFF  # a page's bytes: its footer still reads, its CRC does not
    stored.write_bytes(bytes(damaged))
    again = run_pipeline(make_config(bin_folder, out, output__formats=["parquet", "ply"]), progress=False)
    assert [(f.status, f.reason) for f in again.frames] == [("done", None), ("replaced", "stored files damaged")]
    assert folder_info(out)["sources_changed"] == []
    scan = bin_folder / "000001.bin"
    os.utime(scan, ns=(scan.stat().st_atime_ns, scan.stat().st_mtime_ns + 10**9))  # touched, or rewritten
    info = folder_info(out)
    assert info["sources_changed"] == [str(scan)]
    assert "1 frame(s) whose scan has changed since they were made" in format_info(info)


def test_a_finished_frame_whose_pose_packet_became_unreadable_keeps_its_pose(raw_drive: Path,
                                                                             make_config: ConfigFactory,
                                                                             tmp_path: Path) -> None:
    # a damaged OXTS packet read as "no pose": the frame was "replaced (pose changed)" and its
    # stored pose wiped, the note naming the packet lost (a review)
    out = tmp_path / "out"
    first = run_pipeline(make_config(raw_drive, out), progress=False)
    stored_pose = write.stored_record({"parquet": Path(first.frames[1].outputs["parquet"])})["pose"]
    assert stored_pose
    packet = next(raw_drive.glob("*/*_sync")) / "oxts" / "data" / f"{1:010d}.txt"
    packet.write_text("garbage\n")
    again = run_pipeline(make_config(raw_drive, out), progress=False)
    assert [(f.status, f.reason) for f in again.frames] == [("skipped", None), ("skipped", None)]
    (note,) = again.frames[1].notes
    assert note.startswith("kept as stored, though its timestamp or pose cannot be read now: pose unknown") \
        and str(packet) in note
    assert write.stored_record({"parquet": Path(first.frames[1].outputs["parquet"])})["pose"] == stored_pose


def test_a_new_timestamp_with_a_format_added_is_recorded_without_the_network_and_keeps_the_preview(
        raw_drive: Path, make_config: ConfigFactory, tmp_path: Path) -> None:
    # with a format added in the same run the frame went through the network, and a re-recorded
    # frame lost its preview, though its points are the same (a review)
    out = tmp_path / "out"
    first = run_pipeline(make_config(raw_drive, out, output__formats=["parquet"]), progress=False)
    picture = write.preview_path(out, first.frames[1].dataset, first.frames[1].sequence, first.frames[1].index)
    picture.parent.mkdir(parents=True)
    picture.write_bytes(b"a preview of frame 1")  # as `kitti-pu preview` leaves it
    stamps = next(raw_drive.glob("*/*_sync")) / "oxts" / "timestamps.txt"
    lines = stamps.read_text().splitlines(keepends=True)
    lines[1] = lines[1][:17] + "59.000000000\n"
    stamps.write_text("".join(lines))
    again = run_pipeline(make_config(raw_drive, out, output__formats=["parquet", "ply"]), progress=False)
    assert [(f.status, f.reason) for f in again.frames] == [("done", None), ("replaced", "timestamp changed")]
    assert "upsample" not in again.frames[1].timings, again.frames[1].timings
    assert write.stored_record({"ply": Path(again.frames[1].outputs["ply"])})["timestamp"] == \
        repr(load.frame_metadata(load.discover(raw_drive)[1])[0])
    assert picture.is_file()


def test_info_on_a_folder_whose_only_run_was_killed_before_a_frame_says_so(tmp_path: Path) -> None:
    # `kill -9` of a run before its first frame left its mark alone: info said the folder "holds no
    # kitti-pu output" and exited 2, where the README promises a warning of the unfinished run (a trial)
    from pipeline.run_marks import leave_mark

    out = tmp_path / "out"
    assert leave_mark(out, "abcdef123456", "0123456789abcdef", ["odometry/00/000000"]) is not None
    info = folder_info(out)
    assert info["frames"] == 0 and len(info["unfinished_runs"]) == 1
    assert "did not finish (killed?)" in format_info(info)
    assert "per sequence" not in format_info(info)  # no header over an empty list
    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(ConfigError, match="holds no kitti-pu output"):  # and a folder without a mark is none
        folder_info(empty)


def test_a_frame_found_complete_on_disk_gets_its_report_line(
        bin_folder: Path, make_config: ConfigFactory, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    import pipeline.runner

    real = pipeline.runner._process

    def reports_lost(*args: object, **kwargs: object):  # noqa: ANN202
        for _ in real(*args, **kwargs):  # every frame written by the workers, no report reaching the run
            pass
        raise KeyboardInterrupt  # a Ctrl-C as the reports were on their way

    monkeypatch.setattr(pipeline.runner, "_process", reports_lost)
    told: list[tuple[str, str]] = []
    with pytest.raises(pipeline.runner.RunInterrupted) as stopped:
        run_pipeline(make_config(bin_folder, tmp_path / "out"), progress=False,
                     on_report=lambda report: told.append((report.key, report.status)))
    summary = stopped.value.summary
    assert [frame.status for frame in summary.frames] == ["done", "done"]
    assert all("complete on disk" in frame.notes[-1] for frame in summary.frames)
    # the summary counted both frames done, but the per-frame lines (`kitti-pu run --no-progress`)
    # left them out: an operator's log had no line for frames the table counted (a trial under load)
    assert told == [(frame.key, "done") for frame in summary.frames]


def test_a_mark_a_full_disk_cuts_short_is_not_left_as_a_killed_run(tmp_path: Path,
                                                                   monkeypatch: pytest.MonkeyPatch) -> None:
    import errno

    from pipeline.run_marks import leave_mark, unfinished_runs

    def full_disk(self: Path, text: str, *args: object, **kwargs: object) -> int:
        self.touch()  # the file is made, its bytes are not
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(Path, "write_text", full_disk)
    assert leave_mark(tmp_path, "abcdef123456", "0123456789abcdef", ["odometry/00/000000"]) is None
    monkeypatch.undo()
    # the empty mark stayed, and info and the next run said a run "did not finish (killed?)"
    assert unfinished_runs(tmp_path) == []


def test_a_worker_lost_mid_run_is_said_and_its_frames_are_done_by_the_other(
        template_scans: list, make_config: ConfigFactory, tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
        capsys: pytest.CaptureFixture[str]) -> None:
    # a worker killed mid-run had its frames redone, exit 0, and nothing said it (a new user's trial)
    import distributed

    import pipeline.runner as runner_module

    monkeypatch.setattr(runner_module, "WORKER_CHECK_SECONDS", 0.05)
    folder = tmp_path / "scans"
    folder.mkdir()
    for index in range(6):
        template_scans[index % len(template_scans)].tofile(folder / f"{index:06d}.bin")
    killed: list[str] = []

    def kill_a_worker(frame_report: object) -> None:
        if killed:
            return
        client = distributed.default_client()
        killed.append(next(iter(client.scheduler_info()["workers"])))
        with contextlib.suppress(Exception):  # the worker dies before it answers
            client.run(lambda: os.kill(os.getpid(), signal.SIGKILL), workers=killed)

    summary = run_pipeline(make_config(folder, tmp_path / "out", dask__n_workers=2), progress=False,
                           on_report=kill_a_worker)
    assert [frame.status for frame in summary.frames] == ["done"] * 6
    assert "workers stopped running (lost, restarting or paused); their frames in flight go to the others" in \
        capsys.readouterr().err
