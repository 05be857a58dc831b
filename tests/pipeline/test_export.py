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
        assert (frame.points_in, frame.points_out, frame.generated) == (before.points_in, before.points_out,
                                                                         before.generated)
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


def test_a_frame_of_another_configuration_is_redone_not_exported(
        bin_folder: Path, tmp_path: Path, make_config: Callable[..., PipelineConfig]) -> None:
    out = tmp_path / "out"
    run_pipeline(make_config(bin_folder, out, output__formats="parquet"), progress=False)
    changed = run_pipeline(make_config(bin_folder, out, output__formats="parquet,ply", tile__seed=5), progress=False)
    assert [f.status for f in changed.frames] == ["done", "done"]
    assert not any("network was not run" in note for f in changed.frames for note in f.notes)
    assert changed.scheduler.startswith("LocalCluster")
