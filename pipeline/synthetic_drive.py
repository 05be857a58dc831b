"""The embedded default input: a synthetic drive in the KITTI raw layout.

A simulated HDL-64E (`cadpu.synthetic.lidar`, the measured sensor, its scans de-skewed for the car's
own 10 m/s) on a car driving up the right-hand lane of a procedural street
(`cadpu.synthetic.street`) at 10 m/s, one scan every 0.1 s (so about 1 m per frame), written the way KITTI
raw ships a drive, so that `pykitti.raw(BASE, DATE, DRIVE)` and the pipeline read it like a real
one:

    BASE/DATE/calib_cam_to_cam.txt, calib_imu_to_velo.txt, calib_velo_to_cam.txt
    BASE/DATE/DATE_drive_XXXX_sync/velodyne_points/data/NNNNNNNNNN.bin
    BASE/DATE/DATE_drive_XXXX_sync/velodyne_points/timestamps.txt, timestamps_start.txt, timestamps_end.txt
    BASE/DATE/DATE_drive_XXXX_sync/oxts/data/NNNNNNNNNN.txt, oxts/timestamps.txt

Calibration: the rigid transforms and the rectified projections of KITTI's 2011_09_26 recordings,
in the files' own format (pykitti reads R/T of the rigid files and P_rect_0X/R_rect_0X of the
camera file). OXTS packets carry the IMU pose (latitude, longitude, altitude, roll, pitch, yaw)
such that pykitti's Mercator conversion gives back T_w_imu = T_w_velo @ T_velo_imu, where T_w_velo
is the simulated sensor pose with the world origin moved to the first IMU position (pykitti's
convention). Scans are simulated from one pose each (no motion distortion within a revolution).
"""

from __future__ import annotations

import datetime as dt
import math
import os
import shutil
import tempfile
from pathlib import Path

import dataclasses
import filecmp

import numpy as np

from cadpu.synthetic.lidar import HDL64E, SceneCaster, mount_pose, simulate_scan
from cadpu.synthetic.street import Scene, make_street

EARTH_RADIUS = 6378137.0  # metres, the constant of pykitti's (and KITTI's devkit) Mercator projection
ORIGIN_LAT, ORIGIN_LON, ORIGIN_ALT = 49.011212804408, 8.4228850417969, 112.83492279053  # Karlsruhe
SPEED = 10.0  # m/s along the street
PERIOD = 0.1  # s between scans (10 Hz)
START_TIME = dt.datetime(2011, 9, 26, 13, 2, 25, 964389)
STREET_MARGIN = 120.0  # metres of street ahead of the last frame (the sensor's range)
#: Street length for drives up to 41 frames: their first frames are the same whatever n_frames is.
MIN_STREET_LENGTH = 160.0

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
CALIB_CAM_TO_CAM = """calib_time: 09-Jan-2012 13:57:47
corner_dist: 9.950000e-02
S_rect_00: 1.242000e+03 3.750000e+02
R_rect_00: 9.999239e-01 9.837760e-03 -7.445048e-03 -9.869795e-03 9.999421e-01 -4.278459e-03 7.402527e-03 4.351614e-03 9.999631e-01
P_rect_00: 7.215377e+02 0.000000e+00 6.095593e+02 0.000000e+00 0.000000e+00 7.215377e+02 1.728540e+02 0.000000e+00 0.000000e+00 0.000000e+00 1.000000e+00 0.000000e+00
S_rect_01: 1.242000e+03 3.750000e+02
R_rect_01: 9.996878e-01 -8.503992e-03 -2.355207e-02 8.604383e-03 9.999551e-01 4.183014e-03 2.351563e-02 -4.384464e-03 9.997138e-01
P_rect_01: 7.215377e+02 0.000000e+00 6.095593e+02 -3.875744e+02 0.000000e+00 7.215377e+02 1.728540e+02 0.000000e+00 0.000000e+00 0.000000e+00 1.000000e+00 0.000000e+00
S_rect_02: 1.242000e+03 3.750000e+02
R_rect_02: 9.998817e-01 1.511453e-02 -2.841595e-03 -1.511724e-02 9.998853e-01 -9.338510e-04 2.827154e-03 9.766976e-04 9.999955e-01
P_rect_02: 7.215377e+02 0.000000e+00 6.095593e+02 4.485728e+01 0.000000e+00 7.215377e+02 1.728540e+02 2.163791e-01 0.000000e+00 0.000000e+00 1.000000e+00 2.745884e-03
S_rect_03: 1.242000e+03 3.750000e+02
R_rect_03: 9.998321e-01 -7.193136e-03 1.685599e-02 7.232804e-03 9.999712e-01 -2.293585e-03 -1.683901e-02 2.415116e-03 9.998553e-01
P_rect_03: 7.215377e+02 0.000000e+00 6.095593e+02 -3.395242e+02 0.000000e+00 7.215377e+02 1.728540e+02 2.199936e+00 0.000000e+00 0.000000e+00 1.000000e+00 2.729905e-03
"""


def write_synthetic_drive(raw_base: Path, n_frames: int = 3, seed: int = 0, date: str = "2011_09_26",
                          drive: str = "0001") -> Path:
    """Write a synthetic KITTI raw drive (layout in the module docstring) under `raw_base`.

    Args:
        raw_base: the KITTI raw base folder (BASE); created when missing.
        n_frames: scans in the drive (>= 1); frame i is taken at street position x = i metres.
        seed: seed of the street layout and of the sensor noise.
        date: recording date folder, "YYYY_MM_DD".
        drive: four-digit drive number.

    Returns:
        The drive folder BASE/DATE/DATE_drive_XXXX_sync. Each calibration file and the drive folder
        are written under a temporary name and renamed into place, so an interrupted call leaves
        no partial drive; an existing drive folder of the same name is replaced, unless it holds
        exactly the files this call made (then it is left as it is, modification times included,
        so a run over it again skips its finished frames).
    """
    if n_frames < 1:
        raise ValueError(f"write_synthetic_drive: n_frames must be at least 1, got {n_frames}")
    if not (len(drive) == 4 and drive.isdigit()):
        raise ValueError(f"write_synthetic_drive: drive must be four digits like '0001', got {drive!r}")
    dt.datetime.strptime(date, "%Y_%m_%d")  # raises ValueError on a malformed date
    date_dir = Path(raw_base) / date
    date_dir.mkdir(parents=True, exist_ok=True)
    for name, text in (("calib_imu_to_velo.txt", CALIB_IMU_TO_VELO), ("calib_velo_to_cam.txt", CALIB_VELO_TO_CAM),
                       ("calib_cam_to_cam.txt", CALIB_CAM_TO_CAM)):
        _write_text_atomic(date_dir / name, text)
    drive_dir = date_dir / f"{date}_drive_{drive}_sync"
    staging = Path(tempfile.mkdtemp(prefix=f".{drive_dir.name}.", dir=date_dir))
    try:
        _write_drive(staging, n_frames, seed)
        if not _same_files(staging, drive_dir):
            if drive_dir.exists():
                _keep_times_of_unchanged(staging, drive_dir)
                shutil.rmtree(drive_dir)
            os.replace(staging, drive_dir)
    finally:
        shutil.rmtree(staging, ignore_errors=True)
    return drive_dir


def _keep_times_of_unchanged(made: Path, existing: Path) -> None:
    """Give each file of folder `made` that holds the bytes of its namesake in `existing` that
    file's modification time: a drive made again with more frames keeps its earlier scans as they
    were, so a run skips their finished frames (they were all redone as "source changed")."""
    for path in made.rglob("*"):
        before = existing / path.relative_to(made)
        if path.is_file() and before.is_file() and filecmp.cmp(path, before, shallow=False):
            shutil.copystat(before, path)


def _same_files(made: Path, existing: Path) -> bool:
    """True when folder `existing` holds the same relative file paths as `made`, with the same bytes."""
    if not existing.is_dir():
        return False
    files = sorted(p.relative_to(made) for p in made.rglob("*") if p.is_file())
    if files != sorted(p.relative_to(existing) for p in existing.rglob("*") if p.is_file()):
        return False
    return all(filecmp.cmp(made / name, existing / name, shallow=False) for name in files)


def sensor_poses(n_frames: int, seed: int = 0) -> tuple[list[np.ndarray], Scene]:
    """The street of `seed` and the (4, 4) sensor-to-street poses of the drive's frames: frame i at
    x = SPEED * PERIOD * i metres in the right-hand lane, 1.73 m above the road. The street is
    `MIN_STREET_LENGTH` long, or longer to keep `STREET_MARGIN` ahead of the last frame.

    Returns:
        (poses, scene): a list of n_frames (4, 4) float64 poses and the `cadpu.synthetic.street.Scene`.
    """
    travel = SPEED * PERIOD * (n_frames - 1)
    scene = make_street(seed, length_m=max(MIN_STREET_LENGTH, travel + STREET_MARGIN))
    poses = [mount_pose(scene, SPEED * PERIOD * i) for i in range(n_frames)]
    return poses, scene


def _write_drive(folder: Path, n_frames: int, seed: int) -> None:
    """Simulate the scans and write velodyne_points/ and oxts/ of one drive into `folder`."""
    velo_dir = folder / "velodyne_points" / "data"
    oxts_dir = folder / "oxts" / "data"
    velo_dir.mkdir(parents=True)
    oxts_dir.mkdir(parents=True)
    poses, scene = sensor_poses(n_frames, seed)
    caster = SceneCaster(scene)
    t_velo_imu = _rigid_transform(CALIB_IMU_TO_VELO)
    imu_poses = [pose @ t_velo_imu for pose in poses]  # T_w_imu = T_w_velo @ T_velo_imu
    origin = imu_poses[0][:3, 3].copy()
    sensor = dataclasses.replace(HDL64E, ego_speed=SPEED, sweep_period=PERIOD)  # the car's own motion
    for i, (pose, imu_pose) in enumerate(zip(poses, imu_poses)):
        scan = simulate_scan(caster, pose, seed=seed * 100_003 + i, model=sensor)
        scan.points.tofile(velo_dir / f"{i:010d}.bin")
        (oxts_dir / f"{i:010d}.txt").write_text(oxts_packet(imu_pose, origin))
    stamps = [START_TIME + dt.timedelta(seconds=PERIOD * i) for i in range(n_frames)]
    half = dt.timedelta(seconds=PERIOD / 2)
    (folder / "oxts" / "timestamps.txt").write_text(_timestamps(stamps))
    (folder / "velodyne_points" / "timestamps.txt").write_text(_timestamps(stamps))
    (folder / "velodyne_points" / "timestamps_start.txt").write_text(_timestamps([t - half for t in stamps]))
    (folder / "velodyne_points" / "timestamps_end.txt").write_text(_timestamps([t + half for t in stamps]))


def oxts_packet(t_world_imu: np.ndarray, origin: np.ndarray) -> str:
    """One OXTS line (30 space-separated values, KITTI's dataformat.txt order) for an IMU pose.

    Args:
        t_world_imu: (4, 4) IMU-to-world pose; world x east, y north, z up, metres.
        origin: (3,) world position that maps to (ORIGIN_LAT, ORIGIN_LON, ORIGIN_ALT): the first
            frame's IMU position, since pykitti takes the first packet as its origin.

    Returns:
        The line, newline-terminated: lat, lon, alt, roll, pitch, yaw, velocities (vn, ve, vf, vl,
        vu), accelerations and angular rates (zero: constant speed), accuracies and status flags.
    """
    east, north, up = t_world_imu[:3, 3] - origin
    mercator_scale = math.cos(math.radians(ORIGIN_LAT))  # pykitti's scale comes from the first packet's latitude
    mercator_x0 = mercator_scale * math.radians(ORIGIN_LON) * EARTH_RADIUS
    mercator_y0 = mercator_scale * EARTH_RADIUS * math.log(math.tan(math.radians(90.0 + ORIGIN_LAT) / 2))
    lon = math.degrees((mercator_x0 + east) / (mercator_scale * EARTH_RADIUS))
    lat = 2.0 * math.degrees(math.atan(math.exp((mercator_y0 + north) / (mercator_scale * EARTH_RADIUS)))) - 90.0
    roll, pitch, yaw = _euler_zyx(t_world_imu[:3, :3])
    forward = t_world_imu[:3, 0] * SPEED  # the IMU's x axis points forward
    values: list[float | int] = [lat, lon, ORIGIN_ALT + up, roll, pitch, yaw,
                                 forward[1], forward[0], SPEED, 0.0, 0.0]
    values += [0.0] * 12  # ax ay az af al au, wx wy wz wf wl wu
    values += [0.05, 0.02, 4, 10, 5, 5, 0]  # pos/vel accuracy, navstat, numsats, posmode, velmode, orimode
    return " ".join(repr(float(v)) if isinstance(v, float) else str(v) for v in values) + "\n"


def _euler_zyx(rotation: np.ndarray) -> tuple[float, float, float]:
    """(roll, pitch, yaw) radians with rotation = Rz(yaw) @ Ry(pitch) @ Rx(roll), as OXTS and pykitti
    compose them."""
    pitch = -math.asin(float(np.clip(rotation[2, 0], -1.0, 1.0)))
    roll = math.atan2(float(rotation[2, 1]), float(rotation[2, 2]))
    yaw = math.atan2(float(rotation[1, 0]), float(rotation[0, 0]))
    return roll, pitch, yaw


def _timestamps(times: list[dt.datetime]) -> str:
    """KITTI timestamp lines ("YYYY-MM-DD HH:MM:SS.nnnnnnnnn", nanoseconds, each newline-terminated)."""
    return "".join(t.strftime("%Y-%m-%d %H:%M:%S.%f") + "000\n" for t in times)


def _rigid_transform(text: str) -> np.ndarray:
    """(4, 4) transform from the text of a KITTI rigid calibration file (R: 9 values, T: 3 values)."""
    values = {}
    for line in text.splitlines():
        key, _, rest = line.partition(":")
        if key in ("R", "T"):
            values[key] = np.array(rest.split(), dtype=np.float64)
    transform = np.eye(4)
    transform[:3, :3] = values["R"].reshape(3, 3)
    transform[:3, 3] = values["T"]
    return transform


def _write_text_atomic(path: Path, text: str) -> None:
    """Write `text` to a temporary file beside `path` and rename it into place."""
    descriptor, temporary = tempfile.mkstemp(prefix=f".{path.name}.", dir=path.parent)
    try:
        with os.fdopen(descriptor, "w") as handle:
            handle.write(text)
        os.replace(temporary, path)
    finally:
        if os.path.exists(temporary):
            os.unlink(temporary)
