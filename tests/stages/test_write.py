"""stages.write: Parquet and PLY files read back with the documented schema and metadata, writes
are atomic, and a run's Parquet folder reads as one Hive-partitioned table."""

from __future__ import annotations

import dataclasses
import os
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest

from cadpu.o3d import o3d
from stages import load, stitch, write, write_kitti
from stages.errors import StageError
from stages.frame import Frame
from stages.stitch import StitchedCloud

METADATA = {"ratio": "4", "model_checksum": "abc123", "config_hash": "cfg9", "tool_version": "0.1.0"}


def _cloud_and_frame(n: int = 1500, index: int = 7, dataset: str = "odometry", sequence: str = "04",
                     seed: int = 0) -> tuple[StitchedCloud, Frame]:
    rng = np.random.default_rng(seed)
    inputs = rng.uniform(-10, 10, size=(n // 3, 4)).astype(np.float32)
    frame = Frame(points=inputs, dataset=dataset, sequence=sequence, index=index, timestamp=0.25,
                  source=f"/data/{index:06d}.bin")
    parent = rng.integers(0, len(inputs), n).astype(np.int64)
    cloud = StitchedCloud(
        xyz=rng.uniform(-10, 10, size=(n, 3)).astype(np.float32),
        reflectance=inputs[parent, 3],
        generated=rng.random(n) < 0.6,
        ground=rng.random(n) < 0.2,
        parent=parent,
    )
    return cloud, frame


def _leftovers(folder: Path) -> list[Path]:
    return [p for p in folder.rglob("*") if p.is_file() and (".tmp-" in p.name or p.name.endswith(".part"))]


def test_output_paths_follow_the_documented_layout(tmp_path: Path) -> None:
    paths = write.output_paths(tmp_path, "raw", "2011_09_26_drive_0001_sync", 12, ("parquet", "ply"))
    assert paths["parquet"] == tmp_path / "points/raw/2011_09_26_drive_0001_sync/000012.parquet"
    assert paths["ply"] == tmp_path / "ply/raw/2011_09_26_drive_0001_sync/000012.ply"
    assert list(write.output_paths(tmp_path, "bin", "s", 0, ("ply",))) == ["ply"]
    with pytest.raises(ValueError, match="las"):
        write.output_paths(tmp_path, "bin", "s", 0, ("las",))


def test_parquet_reads_back_with_schema_values_and_metadata(tmp_path: Path) -> None:
    cloud, frame = _cloud_and_frame()
    paths = write.write_frame(cloud, frame, tmp_path, METADATA, formats=("parquet",))
    table = pq.read_table(paths["parquet"], partitioning=None)
    assert table.schema.names == ["x", "y", "z", "reflectance", "generated", "ground", "parent", "frame",
                                  "dataset", "sequence"]
    assert [table.schema.field(n).type for n in table.schema.names] == [
        pa.float32()] * 4 + [pa.bool_(), pa.bool_(), pa.int64(), pa.int32(), pa.string(), pa.string()]
    assert set(table["sequence"].to_pylist()) == {"04"} and set(table["dataset"].to_pylist()) == {"odometry"}
    assert np.array_equal(np.column_stack([table[c].to_numpy() for c in "xyz"]), cloud.xyz)
    assert np.array_equal(table["reflectance"].to_numpy(), cloud.reflectance)
    assert np.array_equal(table["generated"].to_numpy(zero_copy_only=False), cloud.generated)
    assert np.array_equal(table["ground"].to_numpy(zero_copy_only=False), cloud.ground)
    assert np.array_equal(table["parent"].to_numpy(), cloud.parent)
    assert set(table["frame"].to_numpy()) == {7}
    info = {k.decode(): v.decode() for k, v in pq.read_metadata(paths["parquet"]).metadata.items()}
    assert info["dataset"] == "odometry" and info["sequence"] == "04" and info["frame"] == "7"
    assert float(info["timestamp"]) == 0.25
    assert info["points"] == str(len(cloud)) and info["generated_points"] == str(int(cloud.generated.sum()))
    assert {k: info[k] for k in METADATA} == METADATA
    frame_table = write.read_frame(paths["parquet"])
    assert len(frame_table) == len(cloud) and "x" in frame_table.columns


def test_every_format_records_the_frames_pose(tmp_path: Path) -> None:
    # the README promised each frame its own pose; the stage read it and no file kept it
    import dataclasses
    import json

    cloud, frame = _cloud_and_frame()
    pose = np.eye(4)
    pose[:3, 3] = [12.5, -3.25, 0.125]
    pose[:3, :3] = [[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]
    paths = write.write_frame(cloud, dataclasses.replace(frame, pose=pose), tmp_path, METADATA,
                              formats=("parquet", "ply", "kitti"))
    for name, path in paths.items():
        assert np.array_equal(np.array(json.loads(write.stored_record({name: path})["pose"])), pose), name
    unknown = write.write_frame(cloud, frame, tmp_path / "unknown", METADATA, formats=("parquet",))
    assert write.stored_record(unknown)["pose"] == ""


def test_a_ply_of_a_scan_under_a_deep_folder_keeps_every_header_line_short_enough_for_open3d(
        tmp_path: Path) -> None:
    # the record (with the source path, twice) was one comment line; beyond 1,024 characters
    # Open3D's PLY reader aborts the whole process
    import dataclasses
    import subprocess
    import sys

    cloud, frame = _cloud_and_frame()
    deep = "/data/" + "/".join(["a_long_folder_name_of_a_dataset"] * 40) + "/000007.bin"
    frame = dataclasses.replace(frame, source=deep)
    path = write.write_frame(cloud, frame, tmp_path, METADATA, formats=("ply",))["ply"]
    header = path.read_bytes().split(b"end_header\n")[0].decode().splitlines()
    assert max(len(line) for line in header) < 1000
    assert write.stored_record({"ply": path})["source"] == deep
    read = subprocess.run([sys.executable, "-c", "import sys, open3d as o3d; "
                           "print(len(o3d.t.io.read_point_cloud(sys.argv[1]).point.positions))", str(path)],
                          capture_output=True, text=True, timeout=120)
    assert read.returncode == 0 and read.stdout.split()[-1] == str(len(cloud)), read.stderr[-500:]


def test_ply_reads_back_with_attributes(tmp_path: Path) -> None:
    cloud, frame = _cloud_and_frame()
    paths = write.write_frame(cloud, frame, tmp_path, METADATA, formats=("ply",))
    assert paths["ply"].read_bytes().startswith(b"ply\nformat binary_little_endian")
    pcd = o3d.t.io.read_point_cloud(str(paths["ply"]))
    assert np.array_equal(pcd.point["positions"].numpy(), cloud.xyz)
    assert np.array_equal(pcd.point["reflectance"].numpy().ravel(), cloud.reflectance)
    assert np.array_equal(pcd.point["generated"].numpy().ravel().astype(bool), cloud.generated)
    assert np.array_equal(pcd.point["ground"].numpy().ravel().astype(bool), cloud.ground)
    assert np.array_equal(pcd.point["parent"].numpy().ravel().astype(np.int64), cloud.parent)


def test_is_complete_detects_missing_truncated_and_corrupt_files(tmp_path: Path) -> None:
    cloud, frame = _cloud_and_frame()
    paths = write.write_frame(cloud, frame, tmp_path, METADATA)
    assert write.is_complete(paths)
    ply = paths["ply"].read_bytes()
    paths["ply"].write_bytes(ply[: len(ply) - 100])
    assert not write.is_complete(paths)
    paths["ply"].write_bytes(ply)
    parquet = paths["parquet"].read_bytes()
    paths["parquet"].write_bytes(parquet[: len(parquet) // 2])
    assert not write.is_complete(paths)
    paths["parquet"].unlink()
    assert not write.is_complete(paths)
    assert not write.is_complete({"ply": tmp_path / "nowhere.ply"})


def test_writes_leave_no_temporary_files_and_overwrite_in_place(tmp_path: Path) -> None:
    first, frame = _cloud_and_frame(seed=1)
    write.write_frame(first, frame, tmp_path, METADATA)
    second, _ = _cloud_and_frame(n=900, seed=2)
    paths = write.write_frame(second, frame, tmp_path, METADATA)
    assert _leftovers(tmp_path) == []
    assert sorted(p.name for p in tmp_path.rglob("*") if p.is_file()) == ["000007.parquet", "000007.ply"]
    assert pq.read_metadata(paths["parquet"]).num_rows == 900


def test_failed_parquet_write_leaves_nothing(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    cloud, frame = _cloud_and_frame()

    class HalfWriter:
        def __init__(self, where: Path, schema: pa.Schema, **kwargs: object) -> None:
            Path(where).write_bytes(b"PAR1 partial")

        def __enter__(self) -> "HalfWriter":
            return self

        def __exit__(self, *exc: object) -> None:
            pass

        def write_table(self, table: pa.Table) -> None:
            raise OSError(28, "No space left on device")

    monkeypatch.setattr(write.pq, "ParquetWriter", HalfWriter)
    with pytest.raises(StageError, match="No space left") as info:
        write.write_frame(cloud, frame, tmp_path, METADATA, formats=("parquet",))
    assert info.value.stage == "write" and info.value.source.endswith("000007.parquet")
    assert [p for p in tmp_path.rglob("*") if p.is_file()] == []


def test_failed_ply_rename_leaves_no_temporary_file(tmp_path: Path) -> None:
    cloud, frame = _cloud_and_frame()
    target = write.output_paths(tmp_path, frame.dataset, frame.sequence, frame.index, ("ply",))["ply"]
    (target / "blocker").mkdir(parents=True)  # a non-empty folder where the file should go
    with pytest.raises(StageError) as info:
        write.write_frame(cloud, frame, tmp_path, METADATA, formats=("ply",))
    assert info.value.source == str(target)
    assert [p for p in tmp_path.rglob("*") if p.is_file()] == []


def test_run_folder_reads_as_one_partitioned_table_with_dask(tmp_path: Path) -> None:
    import dask.dataframe as dd

    expected = 0
    for dataset, sequence, index, n in (("odometry", "04", 0, 300), ("odometry", "04", 1, 600),
                                        ("odometry", "05", 0, 900), ("raw", "2011_09_26_drive_0001_sync", 3, 1200)):
        cloud, frame = _cloud_and_frame(n=n, index=index, dataset=dataset, sequence=sequence, seed=n)
        write.write_frame(cloud, frame, tmp_path, METADATA, formats=("parquet",))
        expected += n
    assert len(dd.read_parquet(tmp_path / "points")) == expected
    table = dd.read_parquet(tmp_path / "points").compute()
    assert len(table) == expected
    assert set(table["sequence"]) == {"04", "05", "2011_09_26_drive_0001_sync"}
    counts = table.groupby(["dataset", "sequence", "frame"], observed=True).size()
    assert counts[("odometry", "04", 1)] == 600 and counts[("odometry", "05", 0)] == 900
    assert counts[("raw", "2011_09_26_drive_0001_sync", 3)] == 1200
    assert {"x", "y", "z", "reflectance", "generated", "ground", "parent"} <= set(table.columns)


def test_a_failed_format_removes_the_frames_other_files(tmp_path) -> None:
    """If the PLY cannot be written, the frame's Parquet file must not stay behind."""
    import numpy as np
    import pytest

    from stages.errors import StageError
    from stages.frame import Frame
    from stages.stitch import stitch
    from stages.write import output_paths, write_frame

    points = np.random.default_rng(0).normal(size=(500, 4)).astype(np.float32)
    frame = Frame(points=points, dataset="bin", sequence="s", index=1)
    paths = output_paths(tmp_path, "bin", "s", 1)
    paths["ply"].parent.mkdir(parents=True)
    paths["ply"].mkdir()  # a folder where the PLY file should go: the rename onto it fails
    with pytest.raises(StageError, match="write"):
        write_frame(stitch(frame), frame, tmp_path, metadata={})
    assert not paths["parquet"].exists()


def test_ply_rows_are_the_bytes_of_the_structured_array(tmp_path: Path) -> None:
    """The packed rows equal numpy's structured array of PLY_PROPERTIES, field by field."""
    cloud, frame = _cloud_and_frame(n=1001, index=12)
    paths = write.write_frame(cloud, frame, tmp_path, METADATA, formats=("ply",))
    rows = np.empty(len(cloud), dtype=[(name, dtype) for name, _, dtype in write.PLY_PROPERTIES])
    for name, values in (("x", cloud.xyz[:, 0]), ("y", cloud.xyz[:, 1]), ("z", cloud.xyz[:, 2]),
                         ("reflectance", cloud.reflectance), ("generated", cloud.generated),
                         ("ground", cloud.ground), ("parent", cloud.parent), ("frame", 12)):
        rows[name] = values
    body = paths["ply"].read_bytes().split(b"end_header\n", 1)[1]
    assert body == rows.tobytes()
    with pytest.raises(ValueError, match="ply_rows"):
        write.ply_rows(cloud, 0, np.empty(10, np.uint8))


def test_parquet_schema_reads_back_exactly_without_a_stored_arrow_schema(tmp_path: Path) -> None:
    cloud, frame = _cloud_and_frame()
    paths = write.write_frame(cloud, frame, tmp_path, METADATA, formats=("parquet",))
    assert pq.read_schema(paths["parquet"]).remove_metadata().equals(write.SCHEMA)
    assert b"ARROW:schema" not in pq.read_metadata(paths["parquet"]).metadata


def test_parquet_columns_are_required_with_statistics_only_where_readers_select_frames(tmp_path: Path) -> None:
    """No column holds nulls, so none carries definition levels (they cost a fifth of the write);
    min/max statistics only on the columns a folder's frames are selected by."""
    cloud, frame = _cloud_and_frame()
    paths = write.write_frame(cloud, frame, tmp_path, METADATA, formats=("parquet",))
    parquet = pq.ParquetFile(paths["parquet"])
    assert [parquet.schema.column(i).max_definition_level for i in range(len(write.SCHEMA))] == [0] * len(write.SCHEMA)
    row_group = parquet.metadata.row_group(0)
    with_statistics = {row_group.column(i).path_in_schema for i in range(row_group.num_columns)
                       if row_group.column(i).is_stats_set}
    assert with_statistics == {"frame", "dataset", "sequence"}
    frame_statistics = row_group.column(write.SCHEMA.names.index("frame")).statistics
    assert (frame_statistics.min, frame_statistics.max) == (7, 7)


def test_a_folder_with_files_of_the_earlier_nullable_schema_reads_as_one_table(tmp_path: Path) -> None:
    """Frames written before the columns became required sit beside new ones after a resumed run:
    pandas, pyarrow.dataset, Dask and DuckDB read the folder as one table."""
    import dask.dataframe as dd
    import duckdb
    import pandas as pd
    import pyarrow.dataset as ds

    cloud, frame = _cloud_and_frame(index=0)
    write.write_frame(cloud, frame, tmp_path, METADATA, formats=("parquet",))
    old, old_frame = _cloud_and_frame(index=1, seed=1)
    table = write.to_table(old, old_frame, METADATA)
    nullable = pa.schema([field.with_nullable(True) for field in table.schema], metadata=table.schema.metadata)
    old_path = write.output_paths(tmp_path, "odometry", "04", 1)["parquet"]
    pq.write_table(table.cast(nullable), old_path, store_schema=False)
    assert pq.ParquetFile(old_path).schema.column(0).max_definition_level == 1
    points = tmp_path / "points"
    expected = 2 * len(cloud)
    assert len(pd.read_parquet(points)) == expected
    assert ds.dataset(points).to_table().num_rows == expected
    assert len(dd.read_parquet(points).compute()) == expected
    assert duckdb.sql(f"SELECT count(*) FROM read_parquet('{points}/**/*.parquet')").fetchall() == [(expected,)]


def test_a_frame_whose_name_leaves_the_layout_is_refused_with_nothing_written(tmp_path: Path) -> None:
    cloud, frame = _cloud_and_frame()
    for name in (dict(sequence="../../escape"), dict(sequence=""), dict(index=-1)):
        with pytest.raises(StageError, match=r"\[write\].*(not one folder name|index must be)"):
            write.write_frame(cloud, frame.with_(**name), tmp_path / "out", {})
    assert not [path for path in tmp_path.rglob("*") if path.is_file()]


def test_every_format_gives_parents_as_rows_of_the_scan_when_load_dropped_points(tmp_path: Path) -> None:
    rng = np.random.default_rng(0)
    scan = np.column_stack([rng.uniform(5, 20, (400, 3)), rng.uniform(0, 1, 400)]).astype(np.float32)
    scan[:50] = 0.0  # zeros written for missing returns: dropped at load
    scan[100:110, :3] = 500.0  # beyond the range limit: dropped too
    frame = load.frame_from_points(scan, source=str(tmp_path / "000000.bin"))
    assert len(frame.points) == 340
    frame = frame.with_(ground=np.zeros(340, dtype=bool))
    frame = frame.with_(cloud=stitch.stitch(frame))
    paths = write.run(frame, write.Options(dir=tmp_path / "out", formats=["parquet", "ply", "kitti"])).outputs
    table = pq.read_table(paths["parquet"])
    parent = table["parent"].to_numpy()
    xyz = np.column_stack([table[c].to_numpy() for c in "xyz"])
    assert np.array_equal(xyz, scan[parent, :3])  # each input point is its scan row
    ply = o3d.t.io.read_point_cloud(paths["ply"])
    assert np.array_equal(ply.point["parent"].numpy().ravel(), parent)
    with np.load(write.write_kitti.sidecar_path(Path(paths["kitti"]))) as sidecar:
        assert np.array_equal(sidecar["parent"], parent)
    # in memory the cloud keeps indexing the frame's points
    assert np.array_equal(frame.cloud.parent, np.arange(340))


def test_the_kitti_mirror_takes_up_metadata_that_grew_or_changed_with_the_next_frame(tmp_path: Path) -> None:
    sequence = tmp_path / "kitti" / "sequences" / "00"
    (sequence / "velodyne").mkdir(parents=True)
    (sequence / "times.txt").write_text("0.0\n0.1\n")
    (sequence / "calib.txt").write_text("P0: 1 0 0 0 0 1 0 0 0 0 1 0\n")
    out = tmp_path / "out"

    def write_frame(index: int) -> None:
        cloud, frame = _cloud_and_frame(index=index, sequence="00")
        scan = sequence / "velodyne" / f"{index:06d}.bin"
        frame.points.tofile(scan)
        write.write_frame(cloud, dataclasses.replace(frame, source=str(scan)), out, METADATA, ("kitti",))

    mirrored = out / "kitti" / "sequences" / "00"
    write_frame(0)
    assert (mirrored / "times.txt").read_text() == "0.0\n0.1\n"
    # the dataset grows: a scan and its time line arrive, and the calibration is corrected
    (sequence / "times.txt").write_text("0.0\n0.1\n0.2\n")
    (sequence / "calib.txt").write_text("P0: 2 0 0 0 0 1 0 0 0 0 1 0\n")  # the same size: told by its time
    later = (sequence / "calib.txt").stat().st_mtime_ns + 2_000_000_000  # clear of coarse file-system clocks
    os.utime(sequence / "calib.txt", ns=(later, later))
    write_frame(2)
    assert (mirrored / "times.txt").read_text() == "0.0\n0.1\n0.2\n"
    assert (mirrored / "calib.txt").read_text().startswith("P0: 2 ")


def test_output_paths_take_formats_as_a_comma_separated_string_as_the_options_do(tmp_path: Path) -> None:
    # "parquet" was seven unknown formats, 'a', 'e', 'p', ... (a new-user trial)
    assert list(write.output_paths(tmp_path, "bin", "s", 0, "parquet")) == ["parquet"]
    assert list(write.output_paths(tmp_path, "bin", "s", 0, "parquet, ply")) == ["parquet", "ply"]


def test_metadata_change_names_what_a_correction_changed_and_tolerates_rounding() -> None:
    pose = np.eye(4)
    pose[:3, 3] = [12.5, -3.0, 0.75]
    stored = write.metadata_record(0.1, pose)
    assert write.metadata_change(stored, write.metadata_record(0.1, pose)) is None
    # the same numbers computed again elsewhere, off in their last bits, still match: a raw pose's
    # translation is in Mercator metres near 4e6, where 3 steps of a float64 are 1.4e-9
    assert write.metadata_change(stored, write.metadata_record(0.1 + 1e-15, pose + 1e-13)) is None
    far = pose.copy()
    far[:3, 3] = [4.1e6, 5.4e6, 110.0]
    assert write.metadata_change(write.metadata_record(0.1, far), write.metadata_record(0.1, far + 1.4e-9)) is None
    assert write.metadata_change(stored, write.metadata_record(0.2, pose)) == "timestamp changed"
    moved = pose.copy()
    moved[0, 3] += 0.01
    assert write.metadata_change(stored, write.metadata_record(0.1, moved)) == "pose changed"
    # a pose that became known (poses/NN.txt added), or unknown (removed)
    assert write.metadata_change(write.metadata_record(0.1, None), stored) == "pose changed"
    assert write.metadata_change(stored, write.metadata_record(0.1, None)) == "pose changed"
    # a record of an earlier version without the fields is no evidence of a change
    assert write.metadata_change({"config_hash": "x"}, stored) is None
    # a field edited into something that is not a number is not the same
    assert write.metadata_change({**stored, "pose": "garbage"}, stored) == "pose changed"


def test_the_record_holds_the_frame_metadata_as_metadata_record_gives_it() -> None:
    cloud, frame = _cloud_and_frame()
    pose = np.arange(16, dtype=np.float64).reshape(4, 4)
    record = write.frame_record(cloud, dataclasses.replace(frame, pose=pose), METADATA)
    assert {key: record[key] for key in ("timestamp", "pose")} == write.metadata_record(0.25, pose)
    assert write.metadata_change(record, write.metadata_record(frame.timestamp, pose)) is None


def test_the_record_names_the_scan_as_it_was_read_not_as_it_is_when_written(tmp_path: Path) -> None:
    # a sync job replaced the scan while its frame ran: the record named the new file's size and
    # time beside the old file's points, so every rerun skipped the frame for good
    scan = tmp_path / "seq" / "000000.bin"
    scan.parent.mkdir()
    rng = np.random.default_rng(1)
    np.column_stack([rng.normal(size=(500, 3)) * [10, 10, 1], rng.uniform(size=500)]).astype(np.float32).tofile(scan)
    frame = load.run(load.discover(scan.parent, kind="bin")[0])
    read_as = frame.source_fingerprint
    assert read_as == load.source_fingerprint(scan)
    replacement = tmp_path / "replacement.bin"
    np.column_stack([rng.normal(size=(700, 3)) * [10, 10, 1], rng.uniform(size=700)]).astype(np.float32).tofile(replacement)
    os.replace(replacement, scan)
    cloud, _ = _cloud_and_frame()
    record = write.frame_record(cloud, frame, METADATA)
    assert record[write.SOURCE_KEY] == read_as != load.source_fingerprint(scan)
    assert write.fingerprint_differs(record[write.SOURCE_KEY], load.source_fingerprint(scan))


def test_a_fifo_named_like_a_scan_is_refused_not_waited_on(tmp_path: Path) -> None:
    # opening it blocked the worker for ever; stat had called it an empty scan
    fifo = tmp_path / "000001.bin"
    os.mkfifo(fifo)
    with pytest.raises(StageError, match="not a regular file, so not a scan"):
        load.read_scan(fifo)


def test_the_kitti_mirror_of_a_raw_drive_copies_its_packets_whole_once_then_each_frames_own(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    # each frame checked every packet of the drive: a cost per frame that grew with the drive
    from pipeline.synthetic_drive import write_synthetic_drive
    from stages import write_kitti

    drive = write_synthetic_drive(tmp_path / "raw", n_frames=3, seed=0)
    packets = drive / "oxts" / "data"
    for index in range(3, 40):  # a longer drive: packets of frames still to come
        (packets / f"{index:010d}.txt").write_text((packets / f"{2:010d}.txt").read_text())
    checked: list[Path] = []
    same_copy = write_kitti._same_copy
    monkeypatch.setattr(write_kitti, "_same_copy", lambda source, target: checked.append(source) or same_copy(source, target))
    monkeypatch.setattr(write_kitti, "_SYNCED_PACKETS", set())
    out = tmp_path / "out"
    for index in (1, 2):
        cloud, frame = _cloud_and_frame(index=index, dataset="raw", sequence=drive.name)
        scan = drive / "velodyne_points" / "data" / f"{index:010d}.bin"
        write.write_frame(cloud, dataclasses.replace(frame, source=str(scan)), out, METADATA, ("kitti",))
        copied = sorted((out / "kitti").rglob("oxts/data/*.txt"))
        assert len(copied) == 40  # the whole drive's packets, from the first frame on
        checked_packets = [p for p in checked if p.parent == packets]
        assert len(checked_packets) == (40 if index == 1 else 2)  # then frame 0's and the frame's own
        checked.clear()
    # a second output of the drive in the same process got frame 0's packet and its frames' own
    # only (a library user running twice): pykitti pairs packets by position
    cloud, frame = _cloud_and_frame(index=1, dataset="raw", sequence=drive.name)
    scan = drive / "velodyne_points" / "data" / f"{1:010d}.bin"
    write.write_frame(cloud, dataclasses.replace(frame, source=str(scan)), tmp_path / "second", METADATA, ("kitti",))
    assert len(sorted((tmp_path / "second" / "kitti").rglob("oxts/data/*.txt"))) == 40


def test_frames_from_one_file_of_another_kind_each_get_their_own_kitti_scan(tmp_path: Path) -> None:
    # the mirror named a scan after its source: three frames made from drive_0001.h5 wrote one file,
    # kitti/points/drive_0001.h5, which no KITTI reader takes for a scan
    written = []
    for index in range(3):
        cloud, frame = _cloud_and_frame(index=index, dataset="bin", sequence="points")
        frame = dataclasses.replace(frame, source="/data/drive_0001.h5")
        written.append(Path(write.write_frame(cloud, frame, tmp_path, METADATA, ("kitti",))["kitti"]))
    assert [path.name for path in written] == ["000000.bin", "000001.bin", "000002.bin"]
    assert all(path.is_file() for path in written)
    # a discovered scan keeps its own name
    assert write_kitti.scan_path(tmp_path, "bin", "s", 7, "/data/scan_0007.bin").name == "scan_0007.bin"


def test_a_frame_with_an_empty_cloud_is_complete_in_every_format(tmp_path: Path) -> None:
    # its KITTI scan of 0 bytes was never complete, so every rerun redid the frame (a review)
    cloud, frame = _cloud_and_frame()
    empty = cloud.select(np.zeros(len(cloud), bool))
    outputs = write.write_frame(empty, frame, tmp_path, METADATA, ("parquet", "ply", "kitti"))
    assert write.is_complete({name: Path(path) for name, path in outputs.items()})
    assert Path(outputs["kitti"]).stat().st_size == 0


def test_a_ply_file_whose_header_is_garbage_is_not_complete(tmp_path: Path) -> None:
    # "element vertex x12" raised a ValueError out of is_complete, and a rerun's planning with it
    cloud, frame = _cloud_and_frame()
    outputs = write.write_frame(cloud, frame, tmp_path, METADATA, ("ply",))
    ply = Path(outputs["ply"])
    ply.write_bytes(ply.read_bytes().replace(b"element vertex ", b"element vertex x", 1))
    assert not write.is_complete({"ply": ply})


def test_lines_appended_to_a_times_file_differ_from_nothing_only_at_a_line_boundary(tmp_path: Path) -> None:
    # a copy ending mid-line ("1.0") was taken for the start of "1.05\n2.1\n" (a review)
    from stages.write_kitti import _differs

    origin, target = tmp_path / "in" / "times.txt", tmp_path / "mirror" / "times.txt"
    origin.parent.mkdir()
    target.parent.mkdir()
    origin.write_text("0.0\n1.05\n2.1\n")
    for copy, differs in (("0.0\n1.05\n", False), ("0.0\n1.0", True), ("0.0\n1.1\n", True)):
        target.write_text(copy)
        assert _differs(origin, target) is differs, copy


def test_labels_replaced_while_they_are_copied_are_copied_again_next_time(tmp_path: Path, monkeypatch) -> None:
    # the copy took the input's time after reading it: labels replaced in between left the mirror
    # with the old ones under the new time, current for ever (a review)
    from stages import write_kitti

    scan_source = tmp_path / "in" / "sequences" / "00" / "velodyne" / "000000.bin"
    scan_source.parent.mkdir(parents=True)
    np.zeros((3, 4), np.float32).tofile(scan_source)
    origin = scan_source.parent.parent / "labels" / "000000.label"
    origin.parent.mkdir()
    np.arange(3, dtype=np.uint32).tofile(origin)
    target = tmp_path / "out" / "sequences" / "00" / "labels" / "000000.label"
    read = write_kitti.labels_of_points

    def replaced_after_reading(*args):
        mirrored = read(*args)
        np.full(3, 7, np.uint32).tofile(origin)
        os.utime(origin, ns=(origin.stat().st_mtime_ns + 10**9,) * 2)
        return mirrored

    monkeypatch.setattr(write_kitti, "labels_of_points", replaced_after_reading)

    def atomic(path: Path, write_file) -> None:
        path.parent.mkdir(parents=True, exist_ok=True)
        write_file(path)

    write_kitti._write_labels(origin, target, np.arange(3), scan_source, atomic)
    assert not write_kitti._labels_current(origin, target)


@pytest.mark.parametrize("broken", ["short reflectance", "short ground", "xyz of four columns", "nan", "parent beyond int32"])
def test_the_stand_alone_writers_refuse_a_cloud_write_frame_refuses(tmp_path: Path, broken: str) -> None:
    # write_ply packed the rows unchecked: columns shorter than xyz wrote the memory past their
    # ends into the file, a (Q, 4) xyz scrambled the positions, parents beyond int32 wrapped to
    # negative (a library user's trial); write_frame's checks were its own
    cloud, frame = _cloud_and_frame(n=300)
    n = len(cloud)
    cloud = {
        "short reflectance": dataclasses.replace(cloud, reflectance=cloud.reflectance[:-10]),
        "short ground": dataclasses.replace(cloud, ground=cloud.ground[:3]),
        "xyz of four columns": dataclasses.replace(cloud, xyz=np.c_[cloud.xyz, np.ones(n)].astype(np.float32)),
        "nan": dataclasses.replace(cloud, xyz=np.where(np.arange(n)[:, None] == 5, np.nan, cloud.xyz)),
        "parent beyond int32": dataclasses.replace(cloud, parent=cloud.parent + 2**31),
    }[broken]
    message = {"nan": "non-finite values", "parent beyond int32": "beyond what a file's int32 parent holds"}.get(
        broken, "the cloud's arrays must be xyz")
    with pytest.raises(StageError, match=message) as raised:
        write.write_ply(cloud, tmp_path / "cloud.ply")
    assert str(tmp_path / "cloud.ply") in str(raised.value)
    if broken != "parent beyond int32":  # a frame with points bounds the parents lower still
        with pytest.raises(StageError, match=message):
            write.write_parquet(cloud, frame, tmp_path / "cloud.parquet", METADATA)
    assert not list(tmp_path.iterdir())


@pytest.mark.parametrize("arguments, message", [
    # read back as -2147483648 (2**31) and 0 (2**40): the frame column is the PLY's int32
    ({"frame_index": 2**31}, "frame_index must be a whole number from 0 to 2147483647"),
    ({"frame_index": -1}, "frame_index must be a whole number"),
    # Open3D's reader aborted the whole process on the long line ("buffer overflow detected"), and
    # read the file with the line break as one without vertex attributes (a library user's trial)
    ({"comments": ("x" * 2000,)}, "each PLY comment must be one line of text of at most 1000"),
    ({"comments": ("note\nend_header",)}, "each PLY comment must be one line"),
])
def test_write_ply_refuses_arguments_its_readers_cannot_take(tmp_path: Path, arguments: dict, message: str) -> None:
    cloud, _ = _cloud_and_frame(n=50)
    with pytest.raises(StageError, match=message):
        write.write_ply(cloud, tmp_path / "cloud.ply", **arguments)
    assert not list(tmp_path.iterdir())


def test_write_ply_takes_a_string_path_and_names_a_folder_given_as_the_file(tmp_path: Path) -> None:
    cloud, _ = _cloud_and_frame(n=50)
    write.write_ply(cloud, str(tmp_path / "cloud.ply"), frame_index=2**31 - 1, comments=("x" * 1000,))
    read = o3d.t.io.read_point_cloud(str(tmp_path / "cloud.ply"))
    assert read.point["frame"].numpy()[0, 0] == 2**31 - 1 and len(read.point["positions"]) == len(cloud)
    # an IsADirectoryError that named a temporary file (".NNN@host~...part")
    with pytest.raises(StageError, match="is a folder; give the PLY file's path") as raised:
        write.write_ply(cloud, tmp_path)
    assert str(tmp_path) in str(raised.value)


def test_write_parquet_takes_a_string_path_and_names_a_folder_given_as_the_file(tmp_path: Path) -> None:
    # a str path failed with "AttributeError: 'str' object has no attribute 'parent'" (a library
    # user's trial), where write_ply took one
    cloud, frame = _cloud_and_frame(n=50)
    write.write_parquet(cloud, frame, str(tmp_path / "cloud.parquet"), METADATA)
    assert pq.read_table(tmp_path / "cloud.parquet").num_rows == len(cloud)
    with pytest.raises(StageError, match="is a folder; give the Parquet file's path") as raised:
        write.write_parquet(cloud, frame, tmp_path, METADATA)
    assert str(tmp_path) in str(raised.value)
    # without a run's provenance, as a cloud made by library calls has none: "missing 1 required
    # positional argument: 'metadata'" (a library user's trial)
    write.write_parquet(cloud, frame, tmp_path / "alone.parquet")
    assert pq.read_table(tmp_path / "alone.parquet").num_rows == len(cloud)


def test_the_kitti_format_refuses_a_dataset_it_has_no_layout_for(tmp_path: Path) -> None:
    # frames of datasets "bin" and "foo" with one sequence name both went to kitti/points/000000.bin,
    # the second replacing the first's copy without a word (a library user's trial)
    cloud, frame = _cloud_and_frame(n=50, dataset="foo", sequence="points", index=0)
    with pytest.raises(StageError, match=r"the kitti format mirrors KITTI's layouts \(raw, odometry, bin\); frame "
                                         r"dataset 'foo' has none"):
        write.write_frame(cloud, frame, tmp_path, METADATA, formats=("parquet", "kitti"))
    assert not list(tmp_path.iterdir())
    assert write.write_frame(cloud, frame, tmp_path, METADATA, formats=("parquet",))["parquet"].is_file()


def test_the_kitti_mirrors_metadata_takes_the_mode_of_new_files_and_the_inputs_time(tmp_path: Path) -> None:
    # shutil.copy2 kept a read-only input's r--r--r-- in the mirror (an operator's trial)
    sequence = tmp_path / "kitti" / "sequences" / "00"
    (sequence / "velodyne").mkdir(parents=True)
    for name, text in (("times.txt", "0.0\n"), ("calib.txt", "P0: 1 0 0 0 0 1 0 0 0 0 1 0\n")):
        (sequence / name).write_text(text)
        (sequence / name).chmod(0o444)
    cloud, frame = _cloud_and_frame(index=0, sequence="00")
    scan = sequence / "velodyne" / "000000.bin"
    frame.points.tofile(scan)
    out = tmp_path / "out"
    write.write_frame(cloud, dataclasses.replace(frame, source=str(scan)), out, METADATA, ("kitti",))
    umask = os.umask(0)
    os.umask(umask)
    for name in ("times.txt", "calib.txt"):
        copy = out / "kitti" / "sequences" / "00" / name
        assert copy.stat().st_mode & 0o777 == 0o666 & ~umask
        assert copy.stat().st_mtime_ns == (sequence / name).stat().st_mtime_ns
