"""Run summaries: counts, exit codes, JSON written atomically, the printed table."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from pipeline.summary import EXIT_FRAMES_FAILED, EXIT_OK, FrameReport, RunSummary


def _summary(statuses: list[str]) -> RunSummary:
    frames = [
        FrameReport(
            key=f"bin/seq/{i:06d}", dataset="bin", sequence="seq", index=i, status=status,
            points_in=100, points_out=400 if status == "done" else 0,
            timings={"load": 0.01, "tile": 0.02 * (i + 1)} if status == "done" else {},
            error="[load] x.bin: truncated" if status == "failed" else None,
            outputs={"parquet": f"out/points/bin/seq/{i:06d}.parquet"} if status in ("done", "skipped") else {},
        )
        for i, status in enumerate(statuses)
    ]
    return RunSummary(frames=frames, wall_seconds=1.5, config_hash="abc", model_checksum="f" * 64,
                      ratio=4, workers=2, scheduler="LocalCluster", output_dir="out")


def test_exit_code_is_distinct_when_a_frame_failed() -> None:
    assert _summary(["done", "skipped"]).exit_code == EXIT_OK
    assert _summary(["done", "failed"]).exit_code == EXIT_FRAMES_FAILED
    # a frame the cluster lost (the scheduler died) is not done: the run did not do all it was asked
    assert _summary(["done", "interrupted"]).exit_code == EXIT_FRAMES_FAILED


def test_an_interrupted_run_records_the_exit_status_of_its_signal(tmp_path: Path) -> None:
    for signal_name, status in (("SIGINT", 130), ("SIGTERM", 143)):
        summary = _summary(["done", "failed", "interrupted"])
        summary.interrupted_by = signal_name
        assert summary.exit_code == status  # the signal wins over a failed frame, as the process's status does
        data = json.loads(summary.write_json(tmp_path / "summary.json").read_text())
        assert (data["exit_code"], data["interrupted"], data["interrupted_by"]) == (status, True, signal_name)


def test_the_folder_totals_count_every_frame_with_files_whatever_its_status() -> None:
    summary = _summary(["done", "failed"])
    kept = summary.frames[1]  # a failed frame whose earlier complete outputs stay in the folder
    kept.points_in, kept.points_out, kept.outputs = 100, 390, {"parquet": "out/points/bin/seq/000001.parquet"}
    totals = summary.to_dict()
    assert (totals["points_out"], totals["points_out_on_disk"]) == (400, 790)


def test_json_counts_and_points(tmp_path: Path) -> None:
    path = _summary(["done", "done", "skipped", "failed"]).write_json(tmp_path / "s" / "summary.json")
    data = json.loads(path.read_text())
    assert (data["frames_done"], data["frames_skipped"], data["frames_failed"]) == (2, 1, 1)
    assert data["points_in"] == 200 and data["points_out"] == 800
    assert data["stage_median_ms"]["tile"] == pytest.approx(30.0)  # two frames, 20 and 40 ms: their mean (40, before)
    assert [p.name for p in path.parent.iterdir()] == ["summary.json"]  # no temporary left


def test_table_lists_failures_first_with_their_error() -> None:
    text = _summary(["done", "failed"]).table()
    lines = text.splitlines()
    assert "failed" in lines[2] and "error: [load] x.bin: truncated" in lines[3]
    assert "done 1, skipped 0, failed 1 of 2 frames" in text


def test_table_totals_name_the_skipped_frames_files_and_a_run_without_a_cluster() -> None:
    summary = _summary(["skipped", "skipped"])
    for frame in summary.frames:  # a skipped frame carries what its stored files hold
        frame.points_out = 400
    summary.workers = 0
    text = summary.table()
    # "in the folder" read as the whole folder's, where info totals more (a batch user's trial)
    assert "points in 0, out 0 (the selected frames' files, with those not done now: in 200, out 800)" in text
    assert "(no cluster started: nothing to process)" in text and "0 worker(s)" not in text
    # nothing to list: the totals line alone, not a header and two rules around no row (a trial)
    assert text.splitlines() == [text.splitlines()[-1]] and text.startswith("done 0, skipped 2")
    assert "with the skipped" not in _summary(["done"]).table() and "on 2 worker(s)" in _summary(["done"]).table()
    # a user's cluster that was not reached: "no cluster started" read as if the run starts one (an
    # operator's trial)
    summary.scheduler = "tcp://10.0.0.5:8786 (not contacted: nothing to do)"
    assert "(cluster not contacted: nothing to do)" in summary.table() and "no cluster started" not in summary.table()


def test_a_run_stopped_before_its_cluster_started_says_so() -> None:
    summary = _summary(["interrupted", "interrupted"])
    summary.workers, summary.interrupted_by = 0, "SIGTERM"
    text = summary.table()
    assert "(stopped before the cluster started)" in text and "nothing to process" not in text


def test_a_run_whose_cluster_failed_does_not_say_there_was_nothing_to_process() -> None:
    summary = _summary(["failed", "failed"])  # e.g. its workers died registering their setup
    summary.workers = 0
    text = summary.table()
    assert "(no worker ran a frame: the cluster failed)" in text and "nothing to process" not in text


def test_the_table_prints_each_frames_notes() -> None:
    summary = _summary(["done", "done"])
    summary.frames[1].notes.append("100 points beyond 200 m dropped at load (0.08% of the scan)")
    assert "    note: 100 points beyond 200 m dropped at load" in summary.table()


def test_the_interrupt_line_counts_the_frames_finished_before() -> None:
    from pipeline.runner import RunInterrupted

    summary = _summary(["done", "skipped", "skipped", "interrupted"])
    summary.interrupted_by = "SIGTERM"
    # "1 of 4 frames done" alone read as if nothing else were on disk
    assert str(RunInterrupted(summary)) == "interrupted by SIGTERM: 1 of 4 frames done, 2 finished before"
    summary.frames = summary.frames[:1] + summary.frames[3:]
    assert str(RunInterrupted(summary)) == "interrupted by SIGTERM: 1 of 2 frames done"


def test_the_runs_record_leaves_out_the_skipped_frames_but_counts_them(tmp_path: Path) -> None:
    summary = _summary(["done", "skipped", "skipped", "failed"])
    record = json.loads(summary.write_json(tmp_path / "run.json", skipped_frames=False).read_text())
    # every finished frame again, per run, before: 37 MB an hour for a full KITTI set rerun hourly
    assert [f["status"] for f in record["frames"]] == ["done", "failed"]
    assert record["frames_skipped"] == 2 and record["frames_total"] == 4
    full = json.loads(summary.write_json(tmp_path / "summary.json").read_text())
    assert len(full["frames"]) == 4
    # but one with a note of what the run did beside it (a stale file removed after a kill) stays,
    # which summary.json, overwritten by the next run, held alone (a review)
    summary.frames[2].notes.append("removed its ply file of another scan, configuration, model, timestamp or pose")
    record = json.loads(summary.write_json(tmp_path / "run.json", skipped_frames=False).read_text())
    assert [f["status"] for f in record["frames"]] == ["done", "skipped", "failed"]


def test_the_table_lists_the_frames_of_this_run_and_counts_the_skipped_ones_in_the_totals() -> None:
    summary = _summary(["skipped", "skipped", "skipped", "done", "failed"])
    lines = summary.table(max_rows=3).splitlines()
    rows = [line.split()[:2] for line in lines[2:] if line.startswith("bin/")]
    # the README says skipped frames are counted in the totals only: they were listed (a new-user trial)
    assert rows == [["bin/seq/000004", "failed"], ["bin/seq/000003", "done"]]
    assert "skipped 3" in lines[-1] and "more frames" not in summary.table(max_rows=3)


def test_the_totals_count_frames_a_cluster_without_workers_left_and_say_so() -> None:
    summary = _summary(["interrupted", "interrupted"])
    summary.workers, summary.scheduler = 0, "tcp://127.0.0.1:8786"
    last = summary.table().splitlines()[-1]  # "done 0, skipped 0, failed 0 of 2 frames ... nothing to process"
    assert "interrupted 2 of 2 frames" in last and "(no worker ran a frame: the cluster had none)" in last


def test_keys_longer_than_the_column_keep_the_table_aligned() -> None:
    summary = _summary(["done"])
    summary.frames[0].key = "raw/2011_09_26_drive_0001_sync/000000"
    header, _, row = summary.table().splitlines()[:3]
    assert header.index("status") == row.index("done")
