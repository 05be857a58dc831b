"""stages.load on implausible input (issue 21, items 7 and 10): points beyond the sensor's range
are dropped and counted before ring recovery, a file of garbage is refused, and a garbage
timestamp names its file. Scans and drives are real files read through real pykitti."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from pipeline.demo import write_synthetic_drive
from stages.errors import InputError
from stages.load import Options, discover, drop_out_of_range, frame_from_points, run
from stages.ring_snap import scan_rings


@pytest.fixture(scope="module")
def drive(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A one-frame synthetic KITTI raw drive (a full simulated HDL-64E scan, KITTI point order)."""
    return write_synthetic_drive(tmp_path_factory.mktemp("raw"), n_frames=1, seed=3)


def test_far_points_are_dropped_counted_and_do_not_derail_ring_recovery(drive: Path, tmp_path: Path) -> None:
    scan_file = drive / "velodyne_points" / "data" / "0000000000.bin"
    clean = np.fromfile(scan_file, dtype=np.float32).reshape(-1, 4)
    rng = np.random.default_rng(0)
    at = np.sort(rng.choice(len(clean), 125, replace=False))
    far = np.full((125, 4), 1e30, np.float32)
    far[:, 3] = 0.5
    polluted = np.insert(clean, at, far, axis=0)
    base = drive.parent.parent
    polluted.tofile(scan_file)
    try:
        frame = run(discover(base)[0], Options())
    finally:
        clean.tofile(scan_file)
    assert np.array_equal(frame.points, clean)
    assert np.array_equal(frame.rings, scan_rings(clean))
    assert any("125" in note and "200" in note for note in frame.notes), frame.notes


def test_a_clean_scan_gets_no_note(drive: Path) -> None:
    frame = run(discover(drive.parent.parent)[0], Options())
    assert not any("beyond" in note for note in frame.notes)


def test_a_text_file_renamed_bin_is_refused(tmp_path: Path) -> None:
    folder = tmp_path / "scans"
    folder.mkdir()
    text = (Path(__file__).read_text() * 4)[:976].encode()
    (folder / "000000.bin").write_bytes(text)
    with pytest.raises(InputError, match="beyond") as info:
        run(discover(folder)[0], Options())
    assert info.value.source.endswith("000000.bin")


@pytest.mark.parametrize("layout", ["xyz", "float64"])
def test_a_scan_of_another_layout_is_refused_saying_what_a_kitti_bin_holds(drive: Path, tmp_path: Path,
                                                                           layout: str) -> None:
    scan = np.fromfile(drive / "velodyne_points" / "data" / "0000000000.bin", dtype=np.float32).reshape(-1, 4)
    scan = scan[:len(scan) // 4 * 4]  # 12-byte points then fill whole 16-byte ones
    other = tmp_path / layout / "000000.bin"
    other.parent.mkdir()
    # x, y, z only (12 bytes a point) read as 16 puts coordinates in the reflectance: it was "done",
    # with garbage written; float64 was refused as points beyond 200 m, with no word of the layout
    (scan[:, :3] if layout == "xyz" else scan.astype(np.float64)).tofile(other)
    with pytest.raises(InputError, match=f"{other}: .*negative reflectance: a KITTI \\.bin holds float32 x, y, z, "
                                         "reflectance per point"):
        run(discover(other)[0], Options())


def test_the_share_of_far_points_is_bounded() -> None:
    points = np.zeros((100, 4), np.float32)
    points[:, 0] = 10.0
    points[:10, 0] = 250.0
    kept, far, near, rows = drop_out_of_range(points, "scan.bin", max_range=200.0, max_share=0.1)
    assert (far, near) == (10, 0) and len(kept) == 90 and np.array_equal(rows, np.arange(10, 100))
    points[10, 0] = 250.0
    with pytest.raises(InputError, match="11 of 100"):
        drop_out_of_range(points, "scan.bin", max_range=200.0, max_share=0.1)


def test_a_garbage_raw_timestamp_names_the_timestamps_file(drive: Path, tmp_path: Path) -> None:
    base = tmp_path / "raw"
    write_synthetic_drive(base, n_frames=2, seed=3)
    stamps = next(base.glob("*/*/oxts/timestamps.txt"))
    lines = stamps.read_text().splitlines(keepends=True)
    stamps.write_text(lines[0] + "not a time at all\n")
    with pytest.raises(InputError, match="line 2") as info:
        run(discover(base)[1], Options())
    assert info.value.source == str(stamps)
    assert run(discover(base)[0], Options()).timestamp == 0.0  # its own line is good (it failed too, before)


def test_a_garbled_oxts_packet_leaves_the_pose_unknown_with_a_note_naming_it(tmp_path: Path) -> None:
    base = tmp_path / "raw"
    write_synthetic_drive(base, n_frames=3, seed=3)
    packets = sorted(base.glob("*/*/oxts/data/*.txt"))
    packets[1].write_text("garbage not numbers\n")
    # the pose is not in any output: a bad packet failed the frame, and frame 0's every frame (a new-user trial)
    frames = [run(ref, Options()) for ref in discover(base)]
    assert frames[1].pose is None and frames[0].pose is not None and frames[2].pose is not None
    assert f"pose unknown: {packets[1]} is not an OXTS packet (3 numbers, not 30)" in frames[1].notes
    packets[0].write_text(" ".join(["1.0"] * 34) + "\n")  # frame 0's: the world origin of every pose
    assert all(run(ref, Options()).pose is None for ref in discover(base))
    assert f"{packets[0]} is not an OXTS packet (34 numbers, not 30)" in run(discover(base)[2], Options()).notes[0]


def test_a_malformed_calibration_names_the_calibration(drive: Path, tmp_path: Path) -> None:
    sequence = _odometry_sequence(drive, tmp_path)
    calib = [f"P{i}: 700 0 600 0 0 700 180 0 0 0 1 0" for i in range(4)]
    (sequence / "calib.txt").write_text("\n".join([*calib, "Tr: 1 2 3"]) + "\n")  # named the scan, before
    with pytest.raises(InputError, match=r"calibration entry 'Tr' holds 3 numbers, not 12") as info:
        run(discover(tmp_path / "odometry")[0], Options())
    assert info.value.source == str(sequence / "calib.txt")


@pytest.mark.parametrize("name, line, message", [
    ("calib_velo_to_cam.txt", "T: 1 2", "calibration entry 'T' holds 2 numbers, not 3"),
    ("calib_imu_to_velo.txt", "R: 1 2 3", "calibration entry 'R' holds 3 numbers, not 9"),
    ("calib_cam_to_cam.txt", "P_rect_02: 1 2", "calibration entry 'P_rect_02' holds 2 numbers, not 12"),
])
def test_a_malformed_raw_calibration_file_is_named_not_the_folders_pattern(tmp_path: Path, name: str, line: str,
                                                                           message: str) -> None:
    base = tmp_path / "raw"
    write_synthetic_drive(base, n_frames=1, seed=3)
    calib = next(base.glob(f"*/{name}"))
    key = line.partition(":")[0]
    kept = [text for text in calib.read_text().splitlines() if not text.startswith(f"{key}:")]
    calib.write_text("\n".join([*kept, line]) + "\n")
    # the message named "DATE/calib_*.txt", though 'T' is in two of the three files (a new-user trial)
    with pytest.raises(InputError, match=message) as info:
        run(discover(base)[0], Options())
    assert info.value.source == str(calib)


def test_a_garbage_odometry_time_names_times_txt(drive: Path, tmp_path: Path) -> None:
    sequence = _odometry_sequence(drive, tmp_path)
    (sequence / "times.txt").write_text("0.0x\n")
    with pytest.raises(InputError, match="line 1") as info:
        run(discover(tmp_path / "odometry")[0], Options())
    assert info.value.source == str(sequence / "times.txt")


@pytest.mark.parametrize("time", ["nan", "inf", "1e300", "-1e400"])
def test_a_non_finite_or_huge_odometry_time_names_times_txt(drive: Path, tmp_path: Path, time: str) -> None:
    # nan named the calibration ("cannot convert float NaN to integer"), inf and 1e300 ended in an
    # OverflowError traceback (exit 1), also on a rerun over finished frames (a hostile-input trial)
    sequence = _odometry_sequence(drive, tmp_path)
    (sequence / "times.txt").write_text(f"{time}\n")
    with pytest.raises(InputError, match="not a timestamp at line 1") as info:
        run(discover(tmp_path / "odometry")[0], Options())
    assert info.value.source == str(sequence / "times.txt")


@pytest.mark.parametrize("where", ["calib", "poses"])
def test_a_pose_with_a_non_finite_value_is_unknown_with_a_note(drive: Path, tmp_path: Path, where: str) -> None:
    # a NaN in calib.txt's Tr gave a pose of NaN, written into every file's record (a hostile-input trial)
    sequence = _odometry_sequence(drive, tmp_path)
    (tmp_path / "odometry" / "poses").mkdir()
    (tmp_path / "odometry" / "poses" / "07.txt").write_text("1 0 0 0 0 1 0 0 0 0 1 0\n")
    if where == "calib":
        calib = sequence / "calib.txt"
        calib.write_text(calib.read_text().replace("Tr: 0 -1", "Tr: nan -1"))
    else:  # finite numbers whose product with Tr overflows
        (tmp_path / "odometry" / "poses" / "07.txt").write_text("0 -1.7e308 -1.7e308 1.7e308 0 1 0 0 0 0 1 0\n")
    frame = run(discover(tmp_path / "odometry")[0], Options())
    assert frame.pose is None
    assert any(note.startswith("pose unknown: ") and "non-finite" in note for note in frame.notes), frame.notes


def test_a_calibration_with_a_byte_order_mark_is_said_so(drive: Path, tmp_path: Path) -> None:
    # "calibration entry 'P0' is missing", though P0 was on line 1 (a hostile-input trial)
    sequence = _odometry_sequence(drive, tmp_path)
    calib = sequence / "calib.txt"
    calib.write_bytes("\ufeff".encode() + calib.read_bytes())
    with pytest.raises(InputError, match="starts with a byte-order mark") as info:
        run(discover(tmp_path / "odometry")[0], Options())
    assert info.value.source == str(calib)


def _odometry_sequence(drive: Path, tmp_path: Path) -> Path:
    """Odometry sequence 07 under tmp_path/odometry: one scan, a valid calib.txt and times.txt."""
    sequence = tmp_path / "odometry" / "sequences" / "07"
    (sequence / "velodyne").mkdir(parents=True)
    np.fromfile(drive / "velodyne_points" / "data" / "0000000000.bin", dtype=np.float32).tofile(
        sequence / "velodyne" / "000000.bin")
    calib = [f"P{i}: 700 0 600 0 0 700 180 0 0 0 1 0" for i in range(4)]
    (sequence / "calib.txt").write_text("\n".join([*calib, "Tr: 0 -1 0 0 0 0 -1 -0.08 1 0 0 -0.27"]) + "\n")
    (sequence / "times.txt").write_text("0.0\n")
    return sequence


def test_zero_returns_are_dropped_with_a_note_and_leave_the_rings_alone(drive: Path) -> None:
    scan = np.fromfile(drive / "velodyne_points" / "data" / "0000000000.bin", dtype=np.float32).reshape(-1, 4)
    rings = scan_rings(scan)
    zeroed = scan.copy()
    zeroed[::50, :3] = 0.0  # some converters write (0, 0, 0) for a missing return
    assert scan_rings(zeroed) is None or scan_rings(zeroed).max() > rings.max()  # kept, they break ring recovery
    frame = frame_from_points(zeroed)
    assert len(frame.points) == len(scan) - len(scan[::50])
    assert frame.rings is not None and frame.rings.max() == rings.max()
    assert any(f"{len(scan[::50])} points within 0.5 m of the sensor" in note for note in frame.notes), frame.notes
    kept, far, near, _ = drop_out_of_range(zeroed, "scan.bin")
    assert (far, near) == (0, len(scan[::50]))
    organised = scan.copy()
    organised[::6, :3] = 0.0  # an organised cloud: a zero for every missing return, here 17%
    assert len(frame_from_points(organised).points) == len(scan) - len(scan[::6])  # not refused as "not a scan"
    # input.min_range 0 keeps them: as one point, the place they all repeat
    assert len(frame_from_points(zeroed, min_range=0.0).points) == len(scan) - len(scan[::50]) + 1
    with pytest.raises(InputError, match="no points between 0.5 and 200 m of the sensor"):  # zeros only
        frame_from_points(np.zeros((1000, 4), np.float32))
