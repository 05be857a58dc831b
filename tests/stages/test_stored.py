"""stages.stored: each output format read back gives the cloud that was written, as its files hold it."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest

from stages import write
from stages.frame import Frame, StitchedCloud
from stages.stored import read_cloud


def _cloud_and_frame(n: int = 900) -> tuple[StitchedCloud, Frame]:
    rng = np.random.default_rng(3)
    inputs = rng.uniform(-20, 20, size=(n // 3, 4)).astype(np.float32)
    frame = Frame(points=inputs, dataset="odometry", sequence="00", index=4, source="/data/sequences/00/velodyne/000004.bin")
    parent = rng.integers(0, len(inputs), n).astype(np.int64)
    cloud = StitchedCloud(xyz=rng.uniform(-20, 20, size=(n, 3)).astype(np.float32), reflectance=inputs[parent, 3],
                          generated=rng.random(n) < 0.6, ground=rng.random(n) < 0.2, parent=parent)
    return cloud, frame


@pytest.mark.parametrize("name", write.FORMATS)
def test_every_format_reads_back_as_the_cloud_written(tmp_path: Path, name: str) -> None:
    cloud, frame = _cloud_and_frame()
    paths = write.write_frame(cloud, frame, tmp_path, {"config_hash": "c"}, formats=(name,))
    back = read_cloud(name, paths[name])
    for column in ("xyz", "reflectance", "generated", "ground", "parent"):
        assert np.array_equal(getattr(back, column), getattr(cloud, column)), column
    assert back.xyz.dtype == np.float32 and back.parent.dtype == np.int64 and back.generated.dtype == bool


def test_the_parent_read_back_is_the_scan_row_the_files_hold(tmp_path: Path) -> None:
    cloud, frame = _cloud_and_frame()
    rows = np.arange(len(frame.points), dtype=np.int64) * 2 + 1  # load kept every other row
    paths = write.write_frame(cloud, dataclasses.replace(frame, scan_rows=rows), tmp_path, {}, formats=("ply",))
    assert np.array_equal(read_cloud("ply", paths["ply"]).parent, rows[cloud.parent])


def test_a_cut_or_foreign_file_is_refused_naming_it(tmp_path: Path) -> None:
    cloud, frame = _cloud_and_frame()
    paths = write.write_frame(cloud, frame, tmp_path, {}, formats=("ply", "kitti"))
    ply = paths["ply"]
    ply.write_bytes(ply.read_bytes()[:-100])
    with pytest.raises(ValueError, match=f"{ply}: .* of the 900 vertices"):
        read_cloud("ply", ply)
    ascii_ply = tmp_path / "ascii.ply"
    ascii_ply.write_text("ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nend_header\n1\n")
    with pytest.raises(ValueError, match="not a PLY file as kitti-pu writes them"):
        read_cloud("ply", ascii_ply)
    scan = paths["kitti"]
    scan.write_bytes(scan.read_bytes()[:-3])
    with pytest.raises(ValueError, match="not a whole number of KITTI points"):
        read_cloud("kitti", scan)


def test_a_damaged_sidecar_or_a_parquet_file_without_a_column_is_a_value_error_naming_it(tmp_path: Path) -> None:
    # zipfile.BadZipFile, KeyError and ArrowInvalid came out as they were (preview ended in a traceback)
    import pyarrow as pa
    import pyarrow.parquet as pq

    from stages import write_kitti
    from stages.stored import read_cloud

    scan = tmp_path / "kitti" / "points" / "000000.bin"
    scan.parent.mkdir(parents=True)
    np.zeros((3, 4), np.float32).tofile(scan)
    sidecar = write_kitti.sidecar_path(scan)
    sidecar.parent.mkdir(parents=True)
    sidecar.write_bytes(b"PK\x03\x04 cut short")
    with pytest.raises(ValueError, match=f"{scan}: not a whole kitti file"):
        read_cloud("kitti", scan)
    np.savez(sidecar.with_suffix(""), generated=np.zeros(3, bool), ground=np.zeros(3, bool))  # no parent
    with pytest.raises(ValueError, match=f"{scan}: not a whole kitti file .*KeyError"):
        read_cloud("kitti", scan)
    table = tmp_path / "000000.parquet"
    pq.write_table(pa.table({"x": np.zeros(3, np.float32)}), table)
    with pytest.raises(ValueError, match=f"{table}: not a whole parquet file"):
        read_cloud("parquet", table)
