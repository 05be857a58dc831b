"""The run summary, `kitti-pu info` and `kitti-pu preview` under faults (issue 21, items 2, 6, 10
and 12): summary.json has the data files' mode, a summary that cannot be written is one clear
error and exit 3, `info` reads a folder holding a killed writer's leftovers, and a preview never
lands inside the Hive folder. Real files, real readers, the real CLI."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pandas as pd
import pyarrow.dataset as pads
import pytest
from typer.testing import CliRunner

from pipeline.cli import app
from pipeline.info import folder_info, format_info, parquet_files
from pipeline.summary import EXIT_FRAMES_FAILED, FrameReport, RunSummary, SummaryWriteError
from stages import write
from stages.frame import Frame, StitchedCloud

REPO = Path(__file__).resolve().parents[2]


def _summary(frames: int = 3) -> RunSummary:
    reports = [FrameReport(key=f"bin/s/{i:06d}", dataset="bin", sequence="s", index=i, status="done")
               for i in range(frames)]
    return RunSummary(frames=reports, wall_seconds=1.0, config_hash="c", model_checksum="m" * 64, ratio=4,
                      workers=1, scheduler="local", output_dir="out")


def _output(out: Path, index: int = 0) -> Path:
    """A kitti-pu output folder holding one written frame; returns its Parquet file."""
    rng = np.random.default_rng(index)
    n = 2000
    cloud = StitchedCloud(xyz=rng.uniform(-20, 20, (n, 3)).astype(np.float32),
                          reflectance=rng.uniform(0, 1, n).astype(np.float32), generated=rng.random(n) < 0.5,
                          ground=np.zeros(n, bool), parent=np.arange(n))
    frame = Frame(points=np.zeros((n, 4), np.float32), dataset="odometry", sequence="04", index=index)
    return write.write_frame(cloud, frame, out, {})["parquet"]


def test_summary_json_has_the_mode_of_the_data_files(tmp_path: Path) -> None:
    parquet = _output(tmp_path / "out")
    path = _summary().write_json(tmp_path / "out" / "summary.json")
    assert path.stat().st_mode & 0o777 == parquet.stat().st_mode & 0o777


def test_a_full_disk_while_writing_the_summary_is_one_clear_error(tmp_path: Path) -> None:
    script = textwrap.dedent("""
        import resource, signal, sys
        from pathlib import Path
        from pipeline.summary import FrameReport, RunSummary, SummaryWriteError
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
        frames = [FrameReport(key=f"bin/s/{i:06d}", dataset="bin", sequence="s", index=i, status="done")
                  for i in range(200)]
        summary = RunSummary(frames=frames, wall_seconds=1.0, config_hash="c", model_checksum="m",
                             ratio=4, workers=1, scheduler="local", output_dir="out")
        resource.setrlimit(resource.RLIMIT_FSIZE, (4096, resource.RLIM_INFINITY))
        try:
            summary.write_json(Path(sys.argv[1]))
        except SummaryWriteError as error:
            print(error)
    """)
    target = tmp_path / "summary.json"
    result = subprocess.run([sys.executable, "-c", script, str(target)], capture_output=True, text=True,
                            env={**os.environ, "PYTHONPATH": str(REPO)}, timeout=120)
    assert result.returncode == 0 and not result.stderr, result.stderr
    assert result.stdout.count("\n") == 1 and str(target) in result.stdout and "too large" in result.stdout
    assert list(tmp_path.iterdir()) == []  # no temporary left


def test_an_unwritable_summary_raises_summary_write_error(tmp_path: Path) -> None:
    (tmp_path / "summary.json").mkdir()
    try:
        _summary().write_json(tmp_path / "summary.json")
    except SummaryWriteError as error:
        assert "summary.json" in str(error)
    else:
        raise AssertionError("no SummaryWriteError")
    assert [p.name for p in tmp_path.iterdir()] == ["summary.json"]


def test_a_run_whose_summary_cannot_be_written_exits_3_with_one_line(
        bin_folder: Path, weights_file: Path, tmp_path: Path) -> None:
    out = tmp_path / "out"
    (out / "summary.json").mkdir(parents=True)
    result = CliRunner().invoke(app, ["run", str(bin_folder), "--out", str(out), "--weights", str(weights_file),
                                      "--workers", "1", "--no-progress", "--set", "upsample.device=cpu",
                                      "--set", "dask.torch_threads=1"])
    assert result.exit_code == EXIT_FRAMES_FAILED, result.output
    assert result.stderr.strip().count("\n") == 0 and "summary.json" in result.stderr, result.stderr
    assert "exit 3 as the run's summary is missing" in result.stderr
    # the run's record in OUT/runs/ says so too (it said exit 0)
    (record,) = [json.loads(path.read_text()) for path in (out / "runs").glob("*.json")]
    assert record["exit_code"] == EXIT_FRAMES_FAILED and "summary.json" in record["summary_missing"]
    assert len(parquet_files(out)) == 2  # the frames are complete on disk
    assert "done 2, skipped 0, failed 0 of 2 frames" in result.stdout  # no table was printed (a new-user trial)


def test_a_summary_that_cannot_be_written_never_leaves_the_last_runs_standing_for_it(
        bin_folder: Path, weights_file: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    # on a full disk the last run's summary.json (exit 0) stayed, the new run's record said exit 0
    # too (its rewrite found no space), and info reported the last run (an operator's trial)
    out = tmp_path / "out"
    arguments = ["run", str(bin_folder), "--out", str(out), "--weights", str(weights_file), "--workers", "1",
                 "--no-progress", "--set", "upsample.device=cpu", "--set", "dask.torch_threads=1"]
    assert CliRunner().invoke(app, [*arguments, "--last", "0"]).exit_code == 0
    import pipeline.summary as summary_module

    def full_disk(path: Path, write) -> None:
        if Path(path).name == "summary.json":
            raise OSError(28, "No space left on device")
        original(path, write)

    original = summary_module.replace_atomically
    monkeypatch.setattr(summary_module, "replace_atomically", full_disk)
    result = CliRunner().invoke(app, arguments)
    assert result.exit_code == EXIT_FRAMES_FAILED, result.output
    assert not (out / "summary.json").exists()
    newest = json.loads(sorted((out / "runs").glob("*.json"))[-1].read_text())
    assert newest["exit_code"] == EXIT_FRAMES_FAILED and "No space left" in newest["summary_missing"]
    assert newest["frames_total"] == 2
    monkeypatch.undo()
    shown = format_info(folder_info(out))
    assert "last run: done 1, skipped 1, failed 0 of 2 frames" in shown, shown
    assert "summary.json could not be written (cannot write the run summary" in shown


def test_info_takes_a_later_runs_summary_over_the_record_of_a_run_without_one(tmp_path: Path) -> None:
    # a record saying its run's summary.json could not be written, then a later run that wrote
    # summary.json but not its record: info reported the older run (a review)
    out = tmp_path / "out"
    _output(out)
    failed = _summary(2)
    failed.summary_missing = "cannot write the run summary (No space left on device)"
    record = failed.write_json(out / "runs" / "20261127T000000Z-aaaaaa.json", skipped_frames=False)
    os.utime(record, ns=(10**18, 10**18))
    _summary(5).write_json(out / "summary.json")
    shown = format_info(folder_info(out))
    assert "of 5 frames" in shown and "could not be written" not in shown, shown
    os.utime(out / "summary.json", ns=(10**18 - 10**9,) * 2)  # the summary older than the record
    shown = format_info(folder_info(out))
    assert "of 2 frames" in shown and "summary.json could not be written" in shown, shown


def test_a_run_whose_record_cannot_be_written_says_so_in_its_summary_and_exits_3(
        bin_folder: Path, weights_file: Path, tmp_path: Path) -> None:
    # summary.json said exit 0 while the process exited 3 (its record in OUT/runs/ failed after it)
    out = tmp_path / "out"
    out.mkdir()
    (out / "runs").write_text("a file where the records' folder goes\n")
    result = CliRunner().invoke(app, ["run", str(bin_folder), "--out", str(out), "--weights", str(weights_file),
                                      "--workers", "1", "--no-progress", "--set", "upsample.device=cpu",
                                      "--set", "dask.torch_threads=1"])
    assert result.exit_code == EXIT_FRAMES_FAILED, result.output
    summary = json.loads((out / "summary.json").read_text())
    assert summary["exit_code"] == EXIT_FRAMES_FAILED and "runs" in summary["record_missing"]
    assert "exit 3 as the run's record is missing (summary.json says so)" in result.stderr
    # named as the record, and why ("File exists" before)
    assert f"cannot write the run's record {out / 'runs'}" in result.stderr
    assert f"({out / 'runs'} is a file, not a folder)" in result.stderr


def test_info_and_readers_ignore_a_killed_writers_leftovers(tmp_path: Path) -> None:
    out = tmp_path / "out"
    parquet = _output(out)
    data = parquet.read_bytes()
    (parquet.parent / ".000001.tmp-0123abcd.parquet").write_bytes(data[: len(data) // 2])
    (parquet.parent / "_000002.parquet").write_bytes(data[:100])
    assert parquet_files(out) == [parquet]
    assert "odometry" in format_info(folder_info(out))
    assert len(pd.read_parquet(out / "points")) == 2000


def test_preview_of_an_output_frame_writes_beside_points_not_inside(tmp_path: Path) -> None:
    out = tmp_path / "out"
    parquet = _output(out)
    result = CliRunner().invoke(app, ["preview", str(parquet)])
    assert result.exit_code == 0, result.output
    png = Path(result.stdout.strip())
    assert png == out / "preview" / "odometry" / "04" / "000000.png" and png.is_file()
    assert [p.name for p in parquet.parent.iterdir()] == ["000000.parquet"]
    assert len(pd.read_parquet(out / "points")) == 2000
    assert pads.dataset(out / "points", partitioning="hive").count_rows() == 2000


def test_preview_of_a_loose_parquet_writes_to_the_current_folder(tmp_path: Path, monkeypatch) -> None:
    parquet = _output(tmp_path / "out")
    loose = tmp_path / "loose" / "frame.parquet"
    loose.parent.mkdir()
    loose.write_bytes(parquet.read_bytes())
    monkeypatch.chdir(tmp_path)
    result = CliRunner().invoke(app, ["preview", str(loose)])
    assert result.exit_code == 0, result.output
    assert Path(result.stdout.strip()).resolve() == tmp_path / "frame.png"


def test_preview_refuses_a_png_inside_a_data_folder(tmp_path: Path) -> None:
    parquet = _output(tmp_path / "out")
    ply_folder = tmp_path / "out" / "ply" / "odometry" / "00"
    for png in (parquet.with_suffix(".png"), tmp_path / "out" / "points" / "a.png", ply_folder / "a.png"):
        result = CliRunner().invoke(app, ["preview", str(parquet), "--png", str(png)])
        assert result.exit_code == 2 and "inside the data folder" in result.stderr, result.output
    assert [p.name for p in parquet.parent.iterdir()] == ["000000.parquet"]
    assert not list(ply_folder.glob("*.png"))


def test_preview_never_writes_over_a_frame_or_the_summary(tmp_path: Path) -> None:
    # --png took any name: a frame's PLY, a KITTI .bin or summary.json became PNG images
    out = tmp_path / "out"
    parquet = _output(out)
    ply = next((out / "ply").rglob("*.ply"))
    for target in (ply, out / "summary.json", tmp_path / "picture.jpg"):
        before = target.read_bytes() if target.is_file() else None
        result = CliRunner().invoke(app, ["preview", str(parquet), "--png", str(target)])
        assert result.exit_code == 2 and "ending in .png" in result.stderr, result.output
        assert (target.read_bytes() if target.is_file() else None) == before


def test_info_names_an_unreadable_frame_or_summary_and_reports_the_rest(tmp_path: Path) -> None:
    out = tmp_path / "out"
    parquet = _output(out)
    (parquet.parent / "000009.parquet").write_bytes(parquet.read_bytes()[:500])  # a truncated copy
    (out / "summary.json").write_text("{")
    result = CliRunner().invoke(app, ["info", str(out)])
    assert result.exit_code == 0, result.output  # both were tracebacks with exit 1
    assert "odometry" in result.output
    assert f"warning: unreadable, left out: {parquet.parent / '000009.parquet'}" in result.output
    assert f"warning: unreadable, left out: {out / 'summary.json'} (JSONDecodeError" in result.output
    (out / "summary.json").write_text('{"frames": []}')  # JSON, but not a summary of this version
    result = CliRunner().invoke(app, ["info", str(out)])
    assert result.exit_code == 0 and "summary.json (KeyError: 'no exit_code, frames_done" in result.output
    (out / "summary.json").unlink()
    parquet.write_bytes(parquet.read_bytes()[:500])  # the frame's PLY still holds it
    result = CliRunner().invoke(app, ["info", str(out)])
    assert result.exit_code == 0 and "(counted from the PLY files" in result.output
    for ply in out.glob("ply/**/*.ply"):
        ply.unlink()  # nothing readable left: said, with the files
    result = CliRunner().invoke(app, ["info", str(out)])
    assert result.exit_code == 2 and "holds no readable kitti-pu frame; unreadable: " in result.output


def test_preview_of_an_unreadable_or_foreign_parquet_or_a_folder_is_one_line_exit_2(tmp_path: Path) -> None:
    import pandas

    parquet = _output(tmp_path / "out")
    truncated = tmp_path / "truncated.parquet"
    truncated.write_bytes(parquet.read_bytes()[:500])
    foreign = tmp_path / "foreign.parquet"
    pandas.DataFrame({"a": [1]}).to_parquet(foreign)
    for path, message in ((truncated, "is not a readable kitti-pu output frame"),
                          (foreign, "is not a readable kitti-pu output frame"),
                          (parquet.parent, "is a folder; give one frame's file (.parquet, .ply, .bin)")):
        result = CliRunner().invoke(app, ["preview", str(path), "--png", str(tmp_path / "p.png")])
        assert result.exit_code == 2 and message in result.output, result.output
        assert "Traceback" not in result.output
    blocker = tmp_path / "afile"
    blocker.write_text("a file where the PNG's folder should be")
    unwritable = CliRunner().invoke(app, ["preview", str(parquet), "--png", str(blocker / "p.png")])
    assert unwritable.exit_code == 2 and f"preview: cannot write {blocker / 'p.png'}" in unwritable.output


def test_info_says_when_a_run_is_writing_to_the_folder(tmp_path: Path) -> None:
    from filelock import FileLock

    from pipeline.output_lock import LOCK_NAME

    # mid-run, info counted the frames finished so far as the folder's, without a word (a trial)
    out = tmp_path / "out"
    _output(out)
    assert folder_info(out)["run_in_progress"] is False
    with FileLock(out / LOCK_NAME):
        info = folder_info(out)
        assert info["run_in_progress"] is True
        assert f"warning: a kitti-pu run is writing to {out} now" in format_info(info)
    assert "writing to" not in format_info(folder_info(out))


def test_info_names_the_output_folder_absolute_as_the_summary_does(tmp_path: Path,
                                                                   monkeypatch: pytest.MonkeyPatch) -> None:
    _output(tmp_path / "out")
    monkeypatch.chdir(tmp_path)
    assert folder_info(Path("out"))["output_dir"] == str(tmp_path / "out")


def test_info_verify_names_a_scan_rewritten_with_its_size_and_time_kept(
        bin_folder: Path, weights_file: Path, tmp_path: Path) -> None:
    # cp -p of a corrected scan of the same size: a rerun keeps the frame (it compares path, size
    # and time), and --verify, which reads every file whole, passed too (an operator's trial)
    out = tmp_path / "out"
    run = CliRunner().invoke(app, ["run", str(bin_folder), "--out", str(out), "--weights", str(weights_file),
                                   "--workers", "1", "--no-progress", "--set", "upsample.device=cpu",
                                   "--set", "dask.torch_threads=1", "--format", "parquet"])
    assert run.exit_code == 0, run.output
    assert CliRunner().invoke(app, ["info", str(out), "--verify"]).exit_code == 0
    scan = bin_folder / "000001.bin"
    before = scan.stat()
    points = np.fromfile(scan, np.float32).reshape(-1, 4)
    points[:, 0] += 1.0
    points.tofile(scan)
    os.utime(scan, ns=(before.st_atime_ns, before.st_mtime_ns))
    result = CliRunner().invoke(app, ["info", str(out), "--verify"])
    assert result.exit_code == EXIT_FRAMES_FAILED, result.output
    assert "1 scan(s) holding other bytes than their frames were made from" in result.stdout
    assert str(scan) in result.stdout and "touch them and run again" in result.stderr


def test_info_verify_finds_damage_inside_a_file_whose_footer_reads(tmp_path: Path) -> None:
    out = tmp_path / "out"
    parquet = _output(out)
    verified = CliRunner().invoke(app, ["info", str(out), "--verify"])
    assert verified.exit_code == 0 and "verified: every frame file reads whole" in verified.stdout
    assert "PLY and KITTI files by their size only, their contents unchecked" in verified.stdout  # (a trial)
    import pyarrow.parquet as pq

    # a disk error inside the data pages of the parent column, the one users join on
    chunk = pq.ParquetFile(parquet).metadata.row_group(0).column(6)
    assert chunk.path_in_schema == "parent"
    data = bytearray(parquet.read_bytes())
    start = chunk.data_page_offset + 16
    data[start:start + 64] = bytes(64)
    parquet.write_bytes(bytes(data))
    assert CliRunner().invoke(app, ["info", str(out)]).exit_code == 0  # the footer still reads
    damaged = CliRunner().invoke(app, ["info", str(out), "--verify"])
    assert damaged.exit_code == EXIT_FRAMES_FAILED
    assert f"damaged: {parquet}" in damaged.stdout and "remove them and run again" in damaged.stderr


def test_info_warns_of_frames_whose_scan_is_gone(tmp_path: Path) -> None:
    # after a scan was deleted its frame stayed, and info totalled it without a word
    from stages.frame import Frame

    out = tmp_path / "out"
    rng = np.random.default_rng(4)
    scans = []
    for index in range(2):
        scan = tmp_path / "scans" / f"{index:06d}.bin"
        scan.parent.mkdir(exist_ok=True)
        scan.write_bytes(b"\0" * 16)
        cloud = StitchedCloud(xyz=rng.uniform(-20, 20, (100, 3)).astype(np.float32),
                              reflectance=np.zeros(100, np.float32), generated=np.zeros(100, bool),
                              ground=np.zeros(100, bool), parent=np.arange(100))
        frame = Frame(points=np.zeros((100, 4), np.float32), dataset="bin", sequence="scans", index=index,
                      source=str(scan))
        write.write_frame(cloud, frame, out, {}, formats=("parquet",))
        scans.append(scan)
    assert "not found from here" not in CliRunner().invoke(app, ["info", str(out)]).output
    scans[1].unlink()
    result = CliRunner().invoke(app, ["info", str(out)])
    assert result.exit_code == 0 and "2 frames" in result.output
    assert f"warning: 1 frame(s) whose scan is not found from here (deleted or moved since, or on another " \
           f"machine), e.g. {scans[1]}" in result.output


def test_info_verify_reads_the_ply_and_kitti_files_too(tmp_path: Path) -> None:
    # a truncated KITTI scan and a truncated PLY: "verified: nothing", exit 0
    from stages.frame import Frame

    out = tmp_path / "out"
    rng = np.random.default_rng(3)
    cloud = StitchedCloud(xyz=rng.uniform(-20, 20, (500, 3)).astype(np.float32),
                          reflectance=rng.uniform(0, 1, 500).astype(np.float32), generated=rng.random(500) < 0.5,
                          ground=np.zeros(500, bool), parent=np.arange(500))
    frame = Frame(points=np.zeros((500, 4), np.float32), dataset="odometry", sequence="04", index=1)
    paths = write.write_frame(cloud, frame, out, {}, formats=("ply", "kitti"))
    assert CliRunner().invoke(app, ["info", str(out), "--verify"]).exit_code == 0
    for name in ("kitti", "ply"):
        whole = paths[name].read_bytes()
        paths[name].write_bytes(whole[:5000])
        damaged = CliRunner().invoke(app, ["info", str(out), "--verify"])
        assert damaged.exit_code == EXIT_FRAMES_FAILED and f"damaged: {paths[name]}" in damaged.stdout, damaged.output
        paths[name].write_bytes(whole)


def test_info_verify_and_the_export_find_flipped_bytes_that_still_decompress(tmp_path: Path) -> None:
    import pyarrow.parquet as pq

    from stages.stored import read_cloud

    out = tmp_path / "out"
    parquet = _output(out)
    chunk = pq.ParquetFile(parquet).metadata.row_group(0).column(0)
    assert chunk.path_in_schema == "x"
    data = bytearray(parquet.read_bytes())
    middle = chunk.data_page_offset + chunk.total_compressed_size // 2
    data[middle:middle + 8] = bytes(byte ^ 0xFF for byte in data[middle:middle + 8])
    parquet.write_bytes(bytes(data))
    # LZ4 decompressed the flipped bytes into other x values: --verify said "every Parquet frame
    # reads whole" and a new format was written from them (a new-user trial)
    damaged = CliRunner().invoke(app, ["info", str(out), "--verify"])
    assert damaged.exit_code == EXIT_FRAMES_FAILED and f"damaged: {parquet}" in damaged.stdout
    assert "CRC" in damaged.stdout or "checksum" in damaged.stdout.lower()
    with pytest.raises(OSError):
        read_cloud("parquet", parquet)


def _verify(out: Path) -> tuple[int, str]:
    """`kitti-pu info OUT --verify`: exit status and output."""
    result = CliRunner().invoke(app, ["info", str(out), "--verify"])
    return result.exit_code, result.output


def test_info_verify_reads_the_frame_name_columns_and_checks_the_footer_readers_filter_by(tmp_path: Path) -> None:
    import pyarrow.dataset as pads
    import pyarrow.parquet as pq

    # --verify read only the cloud's columns: a flip in the frame column's page passed as
    # "verified" while readers got frame 16843009 or refused the folder, and a footer whose frame
    # statistics lost the frame passed while pyarrow.dataset's filter on it returned no rows (a trial)
    out = tmp_path / "out"
    parquet = _output(out, index=123456)
    whole = parquet.read_bytes()
    assert _verify(out)[0] == 0
    frame_chunk = pq.ParquetFile(parquet).metadata.row_group(0).column(7)
    assert frame_chunk.path_in_schema == "frame"
    data = bytearray(whole)
    data[frame_chunk.data_page_offset + frame_chunk.total_compressed_size - 4] ^= 1
    parquet.write_bytes(bytes(data))
    status, output = _verify(out)
    assert status == EXIT_FRAMES_FAILED and f"damaged: {parquet}" in output, output
    # the footer's min and max of the frame column made 123457 (its rows hold 123456)
    footer_start = len(whole) - 8 - int.from_bytes(whole[-8:-4], "little")
    value, other = (123456).to_bytes(4, "little"), (123457).to_bytes(4, "little")
    assert whole[footer_start:].count(value) >= 2
    parquet.write_bytes(whole[:footer_start] + whole[footer_start:].replace(value, other))
    assert pads.dataset(out / "points").to_table(filter=pads.field("frame") == 123456).num_rows == 0
    status, output = _verify(out)
    assert status == EXIT_FRAMES_FAILED and "the footer's statistics of its frame column say 123457 to 123457" in output


def test_info_verify_passes_a_file_of_the_earlier_layout_without_the_name_columns(tmp_path: Path) -> None:
    import pyarrow.parquet as pq

    # files of the points/dataset=.../sequence=... layout hold no dataset and sequence columns:
    # --verify called them damaged ("No match for FieldRef.Name(dataset)": a review)
    out = tmp_path / "out"
    parquet = _output(out, index=3)
    legacy = out / "points" / "dataset=odometry" / "sequence=04" / "000003.parquet"
    legacy.parent.mkdir(parents=True)
    pq.write_table(pq.read_table(parquet).drop_columns(["dataset", "sequence"]), legacy)
    parquet.unlink()
    status, output = _verify(out)
    assert "damaged" not in output and status == 0, output


def _flat_frame(out: Path, fmt: str, n: int) -> Path:
    """Frame 000000 of odometry sequence 04, n points at (1, 1, 1), written to `out` in format
    `fmt`; returns its file."""
    cloud = StitchedCloud(xyz=np.ones((n, 3), np.float32), reflectance=np.zeros(n, np.float32),
                          generated=np.zeros(n, bool), ground=np.zeros(n, bool), parent=np.arange(n))
    frame = Frame(points=np.zeros((n, 4), np.float32), dataset="odometry", sequence="04", index=0)
    return write.write_frame(cloud, frame, out, {}, formats=(fmt,))[fmt]


def test_info_verify_finds_a_ply_of_another_size_than_its_header_and_record_say(tmp_path: Path) -> None:
    # the size check passed any file at least as long as its header said: a vertex count lowered
    # by a flipped digit (readers then lost rows, or refused it) and bytes appended passed (a trial)
    out = tmp_path / "out"
    ply = _flat_frame(out, "ply", 500)
    whole = ply.read_bytes()
    for changed in (whole.replace(b"element vertex 500\n", b"element vertex 490\n"), whole + bytes(24)):
        ply.write_bytes(changed)
        status, output = _verify(out)
        assert status == EXIT_FRAMES_FAILED and f"damaged: {ply} (not the size its header announces)" in output
        assert not write.is_complete({"ply": ply})  # so the next run redoes it
    ply.write_bytes(whole)
    assert _verify(out)[0] == 0


def _flip_member_byte(archive_path: Path, name: str, from_start: int | None = None, from_end: int | None = None) -> None:
    """Flip one byte of a zip member's compressed data, `from_start` bytes after its start or
    `from_end` bytes before its end (the local header gives its own name and extra lengths)."""
    import zipfile

    with zipfile.ZipFile(archive_path) as archive:
        member = archive.getinfo(name)
    data = bytearray(archive_path.read_bytes())
    local = member.header_offset
    start = local + 30 + int.from_bytes(data[local + 26:local + 28], "little") + int.from_bytes(
        data[local + 28:local + 30], "little")
    data[start + from_start if from_start is not None else start + member.compress_size - from_end] ^= 0xFF
    archive_path.write_bytes(bytes(data))


def test_a_kitti_sidecar_whose_parents_are_damaged_is_named_by_verify(tmp_path: Path) -> None:
    from stages import write_kitti

    # a flipped byte in the sidecar's parent member: --verify named the intact scan beside it (a trial)
    out = tmp_path / "out"
    scan = _flat_frame(out, "kitti", 300)
    sidecar = write_kitti.sidecar_path(scan)
    _flip_member_byte(sidecar, "parent.npy", from_end=8)
    write_kitti.sidecar_record(sidecar)  # the record and the flags still read
    status, output = _verify(out)
    assert status == EXIT_FRAMES_FAILED and f"damaged: {sidecar} (the sidecar of {scan.name}" in output, output
    assert f"damaged: {scan} " not in output


def test_a_damaged_kitti_sidecar_is_named_itself_by_info_and_by_verify(tmp_path: Path) -> None:
    from stages import write_kitti
    from stages.frame import Frame

    out = tmp_path / "out"
    rng = np.random.default_rng(5)
    for index in range(2):
        cloud = StitchedCloud(xyz=rng.uniform(-20, 20, (300, 3)).astype(np.float32),
                              reflectance=np.zeros(300, np.float32), generated=np.zeros(300, bool),
                              ground=np.zeros(300, bool), parent=np.arange(300))
        frame = Frame(points=np.zeros((300, 4), np.float32), dataset="odometry", sequence="04", index=index)
        scan = write.write_frame(cloud, frame, out, {}, formats=("kitti",))["kitti"]
    sidecar = write_kitti.sidecar_path(scan)
    sidecar.write_bytes(sidecar.read_bytes()[:200])
    # plain info dropped the frame without a word (2 frames became 1); --verify named the intact scan
    plain = CliRunner().invoke(app, ["info", str(out)])
    assert "1 frame" in plain.output and str(sidecar) in plain.output, plain.output
    verified = CliRunner().invoke(app, ["info", str(out), "--verify"])
    assert verified.exit_code == EXIT_FRAMES_FAILED
    assert f"damaged: {sidecar} (the sidecar of {scan.name}" in verified.stdout, verified.output
    assert f"damaged: {scan} " not in verified.stdout


def test_a_mirrored_scan_named_bin_in_capitals_is_verified_and_previewed_as_the_outputs(tmp_path: Path) -> None:
    from pipeline.preview import default_png_path
    from stages.frame import Frame

    # the mirror keeps "000007.BIN": --verify globbed *.bin and passed it truncated, and preview
    # wrote its PNG to the current folder
    source = tmp_path / "upper" / "000007.BIN"
    source.parent.mkdir()
    source.write_bytes(b"\0" * 16)
    cloud = StitchedCloud(xyz=np.ones((300, 3), np.float32), reflectance=np.zeros(300, np.float32),
                          generated=np.zeros(300, bool), ground=np.zeros(300, bool), parent=np.arange(300))
    frame = Frame(points=np.zeros((300, 4), np.float32), dataset="bin", sequence="upper", index=7, source=str(source))
    out = tmp_path / "out"
    scan = write.write_frame(cloud, frame, out, {}, formats=("kitti",))["kitti"]
    assert scan.name == "000007.bin"  # what readers that glob *.bin find (pykitti's: a trial)
    scan = scan.rename(scan.with_name("000007.BIN"))  # as versions before 2026-11-26 wrote it
    (out / "summary.json").write_text("{}")  # what makes it an output folder, as a run leaves it
    assert default_png_path(scan) == out / "preview" / "bin" / "upper" / "000007.png"
    scan.write_bytes(scan.read_bytes()[:100])
    verified = CliRunner().invoke(app, ["info", str(out), "--verify"])
    assert verified.exit_code == EXIT_FRAMES_FAILED and f"damaged: {scan}" in verified.stdout, verified.output


def test_the_skip_check_of_a_kitti_frame_reads_its_sidecars_array_headers_only(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    # every rerun's check of every finished frame decompressed the whole sidecar (np.load), 2-12 ms
    # a frame, twice: minutes an hourly no-op rerun of a large mirror (a trial at scale)
    from stages import write_kitti

    scan = _flat_frame(tmp_path / "out", "kitti", 300)
    sidecar = write_kitti.sidecar_path(scan)

    def no_arrays(*args: object, **kwargs: object) -> None:
        raise AssertionError("an array's data was read")

    with monkeypatch.context() as patched:
        patched.setattr(np, "load", no_arrays)
        assert write_kitti.is_complete(scan)
    assert write_kitti.sidecar_shapes(sidecar) == {"generated": (300,), "ground": (300,), "parent": (300,)}
    assert write_kitti.sidecar_record(sidecar)[1] == 300
    scan.write_bytes(scan.read_bytes()[:16 * 299])  # a point short of its sidecar: not complete
    assert not write_kitti.is_complete(scan)


def test_a_sidecar_damaged_at_the_start_of_a_member_is_said_not_a_traceback(tmp_path: Path) -> None:
    from stages import write_kitti
    from stages.stored import read_cloud

    # one byte at the start of generated.npy's compressed data: zlib.error ("Error -3 while
    # decompressing") escaped the skip check, the export and --verify as a traceback (a review)
    out = tmp_path / "out"
    scan = _flat_frame(out, "kitti", 300)
    sidecar = write_kitti.sidecar_path(scan)
    _flip_member_byte(sidecar, "generated.npy", from_start=0)
    assert not write_kitti.is_complete(scan)
    with pytest.raises(ValueError):
        write_kitti.sidecar_shapes(sidecar)
    with pytest.raises(ValueError):
        read_cloud("kitti", scan)
    status, output = _verify(out)  # the folder's only frame: no readable frame, said in one line
    assert status == 2 and f"unreadable: {sidecar}" in output and "Traceback" not in output, output
    n = 300
    cloud = StitchedCloud(xyz=np.ones((n, 3), np.float32), reflectance=np.zeros(n, np.float32),
                          generated=np.zeros(n, bool), ground=np.zeros(n, bool), parent=np.arange(n))
    write.write_frame(cloud, Frame(points=np.zeros((n, 4), np.float32), dataset="odometry", sequence="04", index=1),
                      out, {}, formats=("kitti",))
    status, output = _verify(out)
    assert status == EXIT_FRAMES_FAILED and f"damaged: {sidecar}" in output, output


def test_info_verify_names_a_kitti_scan_without_its_sidecar_and_a_sidecar_without_its_scan(tmp_path: Path) -> None:
    # a KITTI copy whose sidecar was lost: "verified: every frame file reads whole", exit 0, though
    # preview refused the scan and a run wrote it again (a new user's trial)
    from stages import write_kitti
    from stages.frame import Frame

    out = tmp_path / "out"
    rng = np.random.default_rng(5)
    cloud = StitchedCloud(xyz=rng.uniform(-20, 20, (200, 3)).astype(np.float32),
                          reflectance=np.zeros(200, np.float32), generated=np.zeros(200, bool),
                          ground=np.zeros(200, bool), parent=np.arange(200))
    scans = [write.write_frame(cloud, Frame(points=np.zeros((200, 4), np.float32), dataset="odometry",
                                            sequence="04", index=index), out, {}, formats=("kitti",))["kitti"]
             for index in range(2)]
    assert CliRunner().invoke(app, ["info", str(out), "--verify"]).exit_code == 0
    sidecar = write_kitti.sidecar_path(scans[0])
    kept = sidecar.read_bytes()
    sidecar.unlink()
    lost = CliRunner().invoke(app, ["info", str(out), "--verify"])
    assert lost.exit_code == EXIT_FRAMES_FAILED
    assert f"damaged: {scans[0]} (a scan of the KITTI copy without its sidecar" in lost.stdout, lost.output
    sidecar.write_bytes(kept)
    scans[1].unlink()
    alone = CliRunner().invoke(app, ["info", str(out), "--verify"])
    assert alone.exit_code == EXIT_FRAMES_FAILED
    assert f"damaged: {write_kitti.sidecar_path(scans[1])} (a sidecar of the KITTI copy without its scan" in alone.stdout
