"""Tests of the synthetic KITTI raw drive (pipeline.synthetic_drive), read back by the real pykitti."""

from __future__ import annotations

import datetime as dt
import os
from pathlib import Path

import numpy as np
import pytest

from cadpu.synthetic.lidar import MOUNT_HEIGHT
from stages.rings import recover_rings
from pipeline.synthetic_drive import PERIOD, SPEED, oxts_packet, sensor_poses, write_synthetic_drive

pykitti = pytest.importorskip("pykitti")


@pytest.fixture(scope="module")
def drive(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    base = tmp_path_factory.mktemp("kitti_raw")
    return base, write_synthetic_drive(base, n_frames=3, seed=2, date="2011_09_26", drive="0007")


@pytest.fixture(scope="module")
def data(drive: tuple[Path, Path]):
    base, _ = drive
    return pykitti.raw(str(base), "2011_09_26", "0007")


def test_layout_is_kitti_raw(drive: tuple[Path, Path]) -> None:
    base, folder = drive
    assert folder == base / "2011_09_26" / "2011_09_26_drive_0007_sync"
    for name in ("calib_cam_to_cam.txt", "calib_imu_to_velo.txt", "calib_velo_to_cam.txt"):
        assert (base / "2011_09_26" / name).is_file()
    velodyne = folder / "velodyne_points"
    assert sorted(p.name for p in (velodyne / "data").iterdir()) == [f"{i:010d}.bin" for i in range(3)]
    assert sorted(p.name for p in (folder / "oxts" / "data").iterdir()) == [f"{i:010d}.txt" for i in range(3)]
    for name in ("timestamps.txt", "timestamps_start.txt", "timestamps_end.txt"):
        assert len((velodyne / name).read_text().splitlines()) == 3
    leftovers = [p.name for p in (base / "2011_09_26").iterdir() if p.name.startswith(".")]
    assert leftovers == []  # no temporary files or folders left behind


def test_pykitti_reads_the_scans(drive: tuple[Path, Path], data) -> None:
    _, folder = drive
    scans = list(data.velo)
    assert len(data) == 3 and len(scans) == 3
    for i, scan in enumerate(scans):
        size = (folder / "velodyne_points" / "data" / f"{i:010d}.bin").stat().st_size
        assert scan.dtype == np.float32 and scan.shape == (size // 16, 4)
        assert 80_000 < len(scan) < 130_000
        assert np.array_equal(np.unique(recover_rings(scan)), np.arange(64))  # KITTI point order
        assert 0.0 <= scan[:, 3].min() and scan[:, 3].max() <= 1.0


def test_frames_differ_by_the_ego_motion(data) -> None:
    first, second = data.get_velo(0), data.get_velo(1)
    assert not np.array_equal(first[:1000], second[:1000])


def test_timestamps_are_ten_hertz(data) -> None:
    steps = np.diff([t.timestamp() for t in data.timestamps])
    assert np.allclose(steps, PERIOD, atol=1e-6)
    assert data.timestamps[0].date() == dt.date(2011, 9, 26)


def test_oxts_poses_reproduce_the_ego_motion(data) -> None:
    t_imu_velo = np.linalg.inv(data.calib.T_velo_imu)
    velo_poses = [packet.T_w_imu @ t_imu_velo for packet in data.oxts]
    expected, _ = sensor_poses(3, seed=2)
    for i, (pose, truth) in enumerate(zip(velo_poses, expected)):
        relative = np.linalg.inv(velo_poses[0]) @ pose
        relative_truth = np.linalg.inv(expected[0]) @ truth
        assert np.allclose(relative, relative_truth, atol=1e-5)
        assert np.allclose(pose[:3, :3], truth[:3, :3], atol=1e-5)
        assert np.linalg.norm(relative[:3, 3]) == pytest.approx(SPEED * PERIOD * i, abs=0.01)
    assert data.oxts[0].packet.lat == pytest.approx(49.0112128)
    assert np.allclose(data.oxts[0].T_w_imu[:3, 3], 0.0)  # pykitti's origin: the first position


def test_calibration_is_kitti_2011_09_26(data) -> None:
    t_cam0_velo = data.calib.T_cam0_velo
    assert t_cam0_velo.shape == (4, 4)
    assert np.allclose(t_cam0_velo[:3, :3] @ t_cam0_velo[:3, :3].T, np.eye(3), atol=1e-5)
    # the Velodyne's forward axis (x) is the camera's viewing axis (z)
    assert (t_cam0_velo[:3, :3] @ [1.0, 0.0, 0.0])[2] > 0.999
    assert data.calib.b_rgb == pytest.approx(0.54, abs=0.01)  # KITTI's colour stereo baseline
    assert data.calib.T_velo_imu[:3, 3] == pytest.approx([-0.8086759, 0.3195559, -0.7997231])


def test_the_ground_is_mount_height_below_the_sensor(data) -> None:
    scan = data.get_velo(0)
    # returns within 10 m and below 1 m under the sensor: the road, and the sidewalks 15 cm above it
    low = (np.hypot(scan[:, 0], scan[:, 1]) < 10.0) & (scan[:, 2] < -1.0)
    assert low.sum() > 5000 and np.median(scan[low, 2]) == pytest.approx(-MOUNT_HEIGHT, abs=0.03)


def test_rewriting_replaces_the_drive_and_is_deterministic(tmp_path: Path) -> None:
    folder = write_synthetic_drive(tmp_path, n_frames=2, seed=5)
    before = (folder / "velodyne_points" / "data" / "0000000000.bin").read_bytes()
    again = write_synthetic_drive(tmp_path, n_frames=1, seed=5)
    assert again == folder
    assert [p.name for p in (folder / "velodyne_points" / "data").iterdir()] == ["0000000000.bin"]
    assert (folder / "velodyne_points" / "data" / "0000000000.bin").read_bytes() == before


def test_a_drive_made_again_with_more_frames_keeps_its_earlier_scans_as_they_were(tmp_path: Path) -> None:
    folder = write_synthetic_drive(tmp_path, n_frames=1, seed=5)
    scan = folder / "velodyne_points" / "data" / "0000000000.bin"
    os.utime(scan, ns=(1_000_000_000_000_000_000, 1_000_000_000_000_000_000))  # made long ago
    write_synthetic_drive(tmp_path, n_frames=2, seed=5)
    # rewritten byte for byte with a new time, so `kitti-pu demo --frames 2` after a 1-frame demo
    # redid frame 0 as "source changed" (an operator's trial)
    assert scan.stat().st_mtime_ns == 1_000_000_000_000_000_000
    assert (folder / "velodyne_points" / "data" / "0000000001.bin").stat().st_mtime_ns != scan.stat().st_mtime_ns


def test_oxts_packet_has_thirty_values() -> None:
    line = oxts_packet(np.eye(4), np.zeros(3))
    assert line.endswith("\n") and len(line.split()) == 30


@pytest.mark.parametrize(("kwargs", "message"), [({"n_frames": 0}, "n_frames"), ({"drive": "12"}, "drive"),
                                                  ({"date": "2011-09-26"}, "'2011-09-26' does not match format")])
def test_bad_arguments_are_rejected(tmp_path: Path, kwargs: dict, message: str) -> None:
    with pytest.raises(ValueError, match=message):
        write_synthetic_drive(tmp_path, **kwargs)


def test_writing_the_same_drive_again_leaves_it_untouched(tmp_path: Path) -> None:
    folder = write_synthetic_drive(tmp_path, n_frames=2, seed=5)
    scan = folder / "velodyne_points" / "data" / "0000000001.bin"
    os.utime(scan, ns=(1_000_000_000, 1_000_000_000))  # an old modification time
    assert write_synthetic_drive(tmp_path, n_frames=2, seed=5) == folder
    assert scan.stat().st_mtime_ns == 1_000_000_000  # the same files: kept, so a rerun skips its frames
    write_synthetic_drive(tmp_path, n_frames=2, seed=6)
    assert scan.stat().st_mtime_ns != 1_000_000_000
