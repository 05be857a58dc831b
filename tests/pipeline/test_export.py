"""A format added to a finished output folder: each finished frame is written in it from its stored
files, without the network, and the new files hold the same points (read back by Open3D and numpy)."""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq

from cadpu.o3d import o3d
from pipeline.config import PipelineConfig
from pipeline.runner import RUN_ID_KEY, run_pipeline
from stages import write


def _parquet_rows(path: Path) -> np.ndarray:
    table = pq.read_table(path)
    return np.column_stack([table[c].to_numpy() for c in ("x", "y", "z", "reflectance")])


def test_an_added_format_is_written_from_the_stored_frames_without_the_network(
        bin_folder: Path, tmp_path: Path, make_config: Callable[..., PipelineConfig]) -> None:
    out = tmp_path / "out"
    first = run_pipeline(make_config(bin_folder, out, output__formats="parquet"), progress=False)
    assert first.count("done") == 2
    parquet_before = {f.key: Path(f.outputs["parquet"]).read_bytes() for f in first.frames}

    added = run_pipeline(make_config(bin_folder, out, output__formats="parquet,ply,kitti"), progress=False)
    assert [f.status for f in added.frames] == ["done", "done"]
    assert added.scheduler == "none (no frame needed the network)"
    for before, frame in zip(first.frames, added.frames):
        assert "written in ply, kitti from its parquet file (the network was not run)" in frame.notes
        counts = ("points_in", "points_out", "generated", "ground", "ground_filled", "dropped")
        assert [getattr(frame, c) for c in counts] == [getattr(before, c) for c in counts]  # ground 0, before
        parquet = Path(frame.outputs["parquet"])
        assert parquet.read_bytes() == parquet_before[frame.key]  # untouched
        rows = _parquet_rows(parquet)
        cloud = o3d.t.io.read_point_cloud(frame.outputs["ply"])
        assert np.array_equal(cloud.point.positions.numpy(), rows[:, :3])
        assert np.array_equal(cloud.point.reflectance.numpy().ravel(), rows[:, 3])
        assert np.array_equal(np.fromfile(frame.outputs["kitti"], np.float32).reshape(-1, 4), rows)
        stored = write.stored_record({"parquet": parquet})
        exported = write.stored_record({"ply": Path(frame.outputs["ply"])})
        assert exported[RUN_ID_KEY] != stored[RUN_ID_KEY]
        assert {k: v for k, v in exported.items() if k != RUN_ID_KEY} == {
            k: v for k, v in stored.items() if k != RUN_ID_KEY}
    summary = json.loads((out / "summary.json").read_text())
    assert [f["status"] for f in summary["frames"]] == ["done", "done"]

    again = run_pipeline(make_config(bin_folder, out, output__formats="parquet,ply,kitti"), progress=False)
    assert [f.status for f in again.frames] == ["skipped", "skipped"]
    assert [f.ground for f in again.frames] == [f.ground for f in first.frames] and first.frames[0].ground > 0


def test_a_frame_of_another_configuration_is_redone_not_exported(
        bin_folder: Path, tmp_path: Path, make_config: Callable[..., PipelineConfig]) -> None:
    out = tmp_path / "out"
    run_pipeline(make_config(bin_folder, out, output__formats="parquet"), progress=False)
    changed = run_pipeline(make_config(bin_folder, out, output__formats="parquet,ply", tile__seed=5), progress=False)
    assert [(f.status, f.reason) for f in changed.frames] == [("replaced", "config changed")] * 2
    assert not any("network was not run" in note for f in changed.frames for note in f.notes)
    assert changed.scheduler.startswith("LocalCluster")


def _damage_inside(path: Path) -> None:
    """Zero a stretch in the middle of a file: its footer or header still reads, its body does not."""
    data = bytearray(path.read_bytes())
    middle = len(data) // 2
    data[middle - 2000:middle + 2000] = bytes(4000)
    path.write_bytes(bytes(data))


def test_a_stored_file_damaged_inside_falls_back_to_another_format_then_to_the_network(
        bin_folder: Path, tmp_path: Path, make_config: Callable[..., PipelineConfig]) -> None:
    out = tmp_path / "out"
    first = run_pipeline(make_config(bin_folder, out, output__formats="parquet,ply"), progress=False)
    parquet = [Path(f.outputs["parquet"]) for f in first.frames]
    ply_rows = [o3d.t.io.read_point_cloud(f.outputs["ply"]).point.positions.numpy() for f in first.frames]
    _damage_inside(parquet[0])
    # it failed "[export] ... cannot read it back" on every run, before
    added = run_pipeline(make_config(bin_folder, out, output__formats="parquet,ply,kitti"), progress=False)
    assert [f.status for f in added.frames] == ["done", "done"]
    assert "written in kitti, parquet from its ply file (the network was not run)" in added.frames[0].notes
    assert np.array_equal(_parquet_rows(parquet[0])[:, :3], ply_rows[0])  # the damaged one written again
    assert "written in kitti from its parquet file (the network was not run)" in added.frames[1].notes
    assert np.array_equal(np.fromfile(added.frames[0].outputs["kitti"], np.float32).reshape(-1, 4)[:, :3], ply_rows[0])

    only = tmp_path / "only"
    alone = run_pipeline(make_config(bin_folder, only, output__formats="parquet"), progress=False)
    _damage_inside(Path(alone.frames[0].outputs["parquet"]))
    redone = run_pipeline(make_config(bin_folder, only, output__formats="parquet,ply"), progress=False)
    # said: "done" without a word lost the only sign of the disk's damage (a scheduled-run trial)
    assert [(f.status, f.reason) for f in redone.frames] == [("replaced", "stored files damaged"), ("done", None)]
    assert not any("network was not run" in note for note in redone.frames[0].notes)  # the network redid it
    assert len(pq.read_table(redone.frames[0].outputs["parquet"])) == redone.frames[0].points_out


def test_the_summary_line_of_a_run_that_only_wrote_added_formats_says_why_no_cluster_started(
        bin_folder: Path, tmp_path: Path, make_config: Callable[..., PipelineConfig]) -> None:
    out = tmp_path / "out"
    run_pipeline(make_config(bin_folder, out, output__formats="parquet"), progress=False)
    added = run_pipeline(make_config(bin_folder, out, output__formats="parquet,ply"), progress=False)
    last = added.table().splitlines()[-1]
    assert "(no cluster started: no frame needed the network)" in last, last  # "the cluster failed", before


def test_a_partial_frame_of_another_configuration_is_reported_replaced(
        bin_folder: Path, tmp_path: Path, make_config: Callable[..., PipelineConfig]) -> None:
    out = tmp_path / "out"
    run_pipeline(make_config(bin_folder, out, output__formats="parquet", tile__seed=5), progress=False)
    # another configuration and one more format: the Parquet files were overwritten as "done", no warning
    changed = run_pipeline(make_config(bin_folder, out, output__formats="parquet,ply"), progress=False)
    assert [(f.status, f.reason) for f in changed.frames] == [("replaced", "config changed")] * 2
