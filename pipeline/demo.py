"""The embedded default input: a synthetic drive in the KITTI raw layout.

A simulated HDL-64E (`cadpu.lidar`) drives down a procedural street (`cadpu.street`) at 10 m/s,
one scan every 0.1 s, and everything is written the way KITTI raw ships it, so `pykitti.raw` and
the pipeline read it like a real drive:

    BASE/DATE/calib_cam_to_cam.txt, calib_imu_to_velo.txt, calib_velo_to_cam.txt
    BASE/DATE/DATE_drive_XXXX_sync/velodyne_points/data/NNNNNNNNNN.bin (+ timestamps*.txt)
    BASE/DATE/DATE_drive_XXXX_sync/oxts/data/NNNNNNNNNN.txt (+ timestamps.txt)

Calibration values are those of KITTI's 2011_09_26 recordings (published with the dataset).
"""

from __future__ import annotations

import datetime as dt
import math
import os
import shutil
import uuid
from pathlib import Path

import numpy as np

from cadpu.lidar import MOUNT_HEIGHT, simulate_scan
from cadpu.street import ROAD_HALF_WIDTH, make_street

EARTH_RADIUS = 6378137.0  # metres, as pykitti's oxts conversion uses
LATITUDE, LONGITUDE, ALTITUDE = 49.011, 8.423, 112.0  # Karlsruhe, where KITTI was recorded
SPEED = 10.0  # m/s
PERIOD = 0.1  # s between scans (10 Hz)
START = dt.datetime(2011, 9, 26, 13, 2, 25)

CALIB_IMU_TO_VELO = """calib_time: 25-May-2012 16:47:16
R: 9.999976e-01 7.553071e-04 -2.035826e-03 -7.854027e-04 9.998898e-01 -1.482298e-02 2.024406e-03 1.482454e-02 9.998881e-01
T: -8.086759e-01 3.195559e-01 -7.997231e-01
"""
CALIB_VELO_TO_CAM = """calib_time: 15-Mar-2012 11:37:16
R: 7.533745e-03 -9.999714e-01 -6.166020e-04 1.480249e-02 7.280733e-04 -9.998902e-01 9.998621e-01 7.523790e-03 1.480755e-02
T: -4.069766e-03 -7.631618e-02 -2.717806e-01
delta_f: 0.000000e+00 0.000000e+00
delta_c: 0.000000e+00 0.000000e+00
"""
_RECT = "9.999239e-01 9.837760e-03 -7.445048e-03 -9.869795e-03 9.999421e-01 -4.278459e-03 7.402527e-03 4.351614e-03 9.999631e-01"
_BASELINES = (0.0, -3.875744e+02, 4.485728e+01, -3.395242e+02)


def _cam_to_cam() -> str:
    lines = ["calib_time: 09-Jan-2012 13:57:47", "corner_dist: 9.950000e-02"]
    for cam, tx in enumerate(_BASELINES):
        lines.append(f"R_rect_0{cam}: {_RECT}")
        lines.append(f"P_rect_0{cam}: 7.215377e+02 0.000000e+00 6.095593e+02 {tx:.6e} 0.000000e+00 "
                     "7.215377e+02 1.728540e+02 0.000000e+00 0.000000e+00 0.000000e+00 1.000000e+00 0.000000e+00")
    return "\n".join(lines) + "\n"


def _oxts_line(x: float, y: float, z: float, yaw: float) -> str:
    """One OXTS packet (30 values) placing the IMU at mercator (x, y) metres east/north of the
    drive's first position, as pykitti converts it back."""
    scale = math.cos(math.radians(LATITUDE))
    mx0 = scale * math.radians(LONGITUDE) * EARTH_RADIUS
    my0 = scale * EARTH_RADIUS * math.log(math.tan(math.radians(90.0 + LATITUDE) / 2))
    lon = math.degrees((mx0 + x) / (scale * EARTH_RADIUS))
    lat = 2 * math.degrees(math.atan(math.exp((my0 + y) / (scale * EARTH_RADIUS)))) - 90.0
    values = [lat, lon, ALTITUDE + z, 0.0, 0.0, yaw, SPEED, 0.0, SPEED, 0.0, 0.0] + [0.0] * 12 + [0.05, 0.02, 4, 10, 5, 5, 0]
    return " ".join(f"{v:.12g}" if isinstance(v, float) else str(v) for v in values) + "\n"


def _stamp(t: dt.datetime) -> str:
    return t.strftime("%Y-%m-%d %H:%M:%S.%f") + "000\n"


def write_synthetic_drive(raw_base: Path, n_frames: int = 3, seed: int = 0, date: str = "2011_09_26",
                          drive: str = "0001") -> Path:
    """Write a synthetic drive under `raw_base` (kept as is when it already exists complete).

    Args:
        raw_base: the KITTI raw base folder to create (BASE in the module docstring).
        n_frames: scans in the drive. seed: street layout and sensor noise.

    Returns:
        The drive folder. Written in a temporary folder and renamed into place: an interrupted
        call leaves no partial drive.
    """
    raw_base = Path(raw_base)
    date_dir = raw_base / date
    drive_dir = date_dir / f"{date}_drive_{drive}_sync"
    if drive_dir.is_dir() and len(list((drive_dir / "velodyne_points" / "data").glob("*.bin"))) == n_frames:
        return drive_dir
    date_dir.mkdir(parents=True, exist_ok=True)
    for name, text in (("calib_imu_to_velo.txt", CALIB_IMU_TO_VELO), ("calib_velo_to_cam.txt", CALIB_VELO_TO_CAM),
                       ("calib_cam_to_cam.txt", _cam_to_cam())):
        (date_dir / name).write_text(text)

    staging = date_dir / f".staging-{uuid.uuid4().hex[:8]}"
    try:
        velo = staging / "velodyne_points" / "data"
        oxts = staging / "oxts" / "data"
        velo.mkdir(parents=True)
        oxts.mkdir(parents=True)
        scene = make_street(seed, length_m=40.0 + SPEED * PERIOD * n_frames + 60.0)
        t_imu_velo = np.linalg.inv(_rigid(CALIB_IMU_TO_VELO))
        lane_y = -ROAD_HALF_WIDTH / 2  # driving in the right lane
        stamps = []
        for i in range(n_frames):
            x = SPEED * PERIOD * i
            sensor_pose = np.eye(4)
            sensor_pose[:3, 3] = [x, lane_y, MOUNT_HEIGHT + 0.02 * x]
            scan = simulate_scan(scene, sensor_pose, seed=seed * 1000 + i)
            scan.points.tofile(velo / f"{i:010d}.bin")
            imu_pose = sensor_pose @ np.linalg.inv(t_imu_velo)  # T_w_imu = T_w_velo @ T_velo_imu
            (oxts / f"{i:010d}.txt").write_text(_oxts_line(*imu_pose[:3, 3], yaw=0.0))
            stamps.append(START + dt.timedelta(seconds=PERIOD * i))
        for folder in ("velodyne_points", "oxts"):
            (staging / folder / "timestamps.txt").write_text("".join(_stamp(t) for t in stamps))
        (staging / "velodyne_points" / "timestamps_start.txt").write_text(
            "".join(_stamp(t - dt.timedelta(seconds=PERIOD / 2)) for t in stamps))
        (staging / "velodyne_points" / "timestamps_end.txt").write_text(
            "".join(_stamp(t + dt.timedelta(seconds=PERIOD / 2)) for t in stamps))
        if drive_dir.exists():
            shutil.rmtree(drive_dir)
        os.replace(staging, drive_dir)
    finally:
        shutil.rmtree(staging, ignore_errors=True)
    return drive_dir


def _rigid(text: str) -> np.ndarray:
    """4x4 transform from a KITTI rigid calibration text (R: 9 values, T: 3 values)."""
    values = {line.split(":")[0]: np.array(line.split(":")[1].split(), dtype=np.float64)
              for line in text.splitlines() if ":" in line and line.split(":")[0] in ("R", "T")}
    transform = np.eye(4)
    transform[:3, :3] = values["R"].reshape(3, 3)
    transform[:3, 3] = values["T"]
    return transform
