"""stages.load: discovery and loading of KITTI raw drives, odometry sequences and .bin folders,
read through real pykitti from tiny layouts written here."""

from __future__ import annotations

import pickle
import re
import shutil
from pathlib import Path

import numpy as np
import pytest

from stages.discovery import bin_sequence_name
from stages.errors import InputError
from stages.load import FrameRef, Options, discover, frame_from_points, frame_metadata, read_scan, run

DATE = "2011_09_26"
DRIVE = "0005"
DRIVE_NAME = f"{DATE}_drive_{DRIVE}_sync"
IMU_TO_VELO_T = np.array([-0.8, 0.3, -0.9])  # identity rotation, this translation
RIGHT = "1 0 0 0 1 0 0 0 1"


def _scan(rng: np.random.Generator, n: int = 2000) -> np.ndarray:
    points = rng.uniform(-20, 20, size=(n, 4)).astype(np.float32)
    points[:, 3] = rng.uniform(0, 1, n)
    return points


def _projection(tx: float) -> str:
    return f"700 0 600 {tx} 0 700 180 0 0 0 1 0"


def write_raw_drive(base: Path, n_frames: int = 3, drive: str = DRIVE, seed: int = 0, date: str = DATE) -> Path:
    """A KITTI raw drive as pykitti reads it: calib_*.txt, velodyne .bin scans, oxts packets
    (IMU rising 1 m per frame, no rotation) and timestamps 0.1 s apart."""
    rng = np.random.default_rng(seed)
    date_dir = base / date
    drive_dir = date_dir / f"{date}_drive_{drive}_sync"
    (drive_dir / "velodyne_points" / "data").mkdir(parents=True)
    (drive_dir / "oxts" / "data").mkdir(parents=True)
    t = " ".join(str(v) for v in IMU_TO_VELO_T)
    (date_dir / "calib_imu_to_velo.txt").write_text(f"calib_time: x\nR: {RIGHT}\nT: {t}\n")
    (date_dir / "calib_velo_to_cam.txt").write_text(f"calib_time: x\nR: {RIGHT}\nT: 0 0 -0.3\n")
    cam = ["calib_time: x"]
    for i, tx in enumerate((0.0, -380.0, 45.0, -340.0)):
        cam += [f"R_rect_0{i}: {RIGHT}", f"P_rect_0{i}: {_projection(tx)}"]
    (date_dir / "calib_cam_to_cam.txt").write_text("\n".join(cam) + "\n")
    stamps = []
    for i in range(n_frames):
        _scan(rng).tofile(drive_dir / "velodyne_points" / "data" / f"{i:010d}.bin")
        packet = [49.0, 8.4, 100.0 + i] + [0.0] * 22 + [4, 10, 5, 5, 0]
        (drive_dir / "oxts" / "data" / f"{i:010d}.txt").write_text(" ".join(map(str, packet)) + "\n")
        stamps.append(f"2011-09-26 13:02:25.{i * 100_000_000:09d}\n")
    (drive_dir / "oxts" / "timestamps.txt").write_text("".join(stamps))
    return drive_dir


def write_odometry_sequence(base: Path, sequence: str = "04", n_frames: int = 3, poses: bool = True,
                            seed: int = 1) -> Path:
    """A KITTI odometry sequence: velodyne scans, calib.txt, times.txt and poses/NN.txt (camera
    moving 2 m per frame along z)."""
    rng = np.random.default_rng(seed)
    sequence_dir = base / "sequences" / sequence
    (sequence_dir / "velodyne").mkdir(parents=True)
    for i in range(n_frames):
        _scan(rng).tofile(sequence_dir / "velodyne" / f"{i:06d}.bin")
    calib = [f"P{i}: {_projection(tx)}" for i, tx in enumerate((0.0, -380.0, 45.0, -340.0))]
    calib.append("Tr: 0 -1 0 0 0 0 -1 -0.08 1 0 0 -0.27")
    (sequence_dir / "calib.txt").write_text("\n".join(calib) + "\n")
    (sequence_dir / "times.txt").write_text("".join(f"{0.1 * i:e}\n" for i in range(n_frames)))
    if poses:
        (base / "poses").mkdir(exist_ok=True)
        (base / "poses" / f"{sequence}.txt").write_text(
            "".join(f"1 0 0 0 0 1 0 0 0 0 1 {2.0 * i}\n" for i in range(n_frames)))
    return sequence_dir


@pytest.fixture()
def raw_base(tmp_path: Path) -> Path:
    base = tmp_path / "raw"
    write_raw_drive(base)
    return base


@pytest.fixture()
def odometry_base(tmp_path: Path) -> Path:
    base = tmp_path / "odometry"
    write_odometry_sequence(base)
    return base


# --- discovery ----------------------------------------------------------------------------------


def test_discover_raw_from_base_date_and_drive_folders(raw_base: Path) -> None:
    for path in (raw_base, raw_base / DATE, raw_base / DATE / DRIVE_NAME):
        refs = discover(path, kind="auto")
        assert [r.key for r in refs] == [f"raw/{DRIVE_NAME}/{i:06d}" for i in range(3)]
        assert all(r.dataset == "raw" and r.date == DATE and r.drive == DRIVE for r in refs)
        assert Path(refs[0].base) == raw_base


def test_discover_every_drive_and_select_by_name(raw_base: Path) -> None:
    write_raw_drive(raw_base, n_frames=2, drive="0009")
    assert {r.sequence for r in discover(raw_base, kind="raw")} == {DRIVE_NAME, f"{DATE}_drive_0009_sync"}
    for name in ("0009", f"{DATE}_drive_0009", f"{DATE}_drive_0009_sync"):
        refs = discover(raw_base, kind="raw", sequences=[name])
        assert [r.index for r in refs] == [0, 1]
        assert {r.drive for r in refs} == {"0009"}
    # one name mistyped among several: refused, naming it, not silently left out
    with pytest.raises(InputError, match=r"sequences \['0010'\] not found; found: "):
        discover(raw_base, kind="raw", sequences=["0009", "0010"])


def test_a_short_drive_name_that_names_drives_of_several_dates_is_refused(raw_base: Path) -> None:
    write_raw_drive(raw_base, n_frames=1, drive="0009")
    write_raw_drive(raw_base, n_frames=1, drive="0009", date="2011_09_28")
    # "-s 9" quietly took drive 0009 of every date (a new-user trial): KITTI numbers drives per date
    with pytest.raises(InputError, match=r"sequence '9' names 2 drives or sequences: 2011_09_26_drive_0009_sync, "
                                         r"2011_09_28_drive_0009_sync; name each one wanted by its full name"):
        discover(raw_base, kind="raw", sequences=["9"])
    assert {r.date for r in discover(raw_base, kind="raw", sequences=["2011_09_28_drive_0009"])} == {"2011_09_28"}


def test_discover_odometry_from_base_sequences_and_sequence_folders(odometry_base: Path) -> None:
    for path in (odometry_base, odometry_base / "sequences", odometry_base / "sequences" / "04"):
        refs = discover(path, kind="odometry")
        assert [r.key for r in refs] == [f"odometry/04/{i:06d}" for i in range(3)]
        assert Path(refs[0].base) == odometry_base
    assert [r.dataset for r in discover(odometry_base)] == ["odometry"] * 3  # auto


def test_discover_frame_selection(odometry_base: Path) -> None:
    refs = discover(odometry_base, frames=range(1, 3))
    assert [r.index for r in refs] == [1, 2]
    with pytest.raises(InputError, match=r"sequences \['05'\] not found; found: 04"):
        discover(odometry_base, sequences=["05"])
    # one name as a string is that name, not its characters ("['5'] not found", before)
    assert discover(odometry_base, sequences="04") == discover(odometry_base, sequences=["04"])
    with pytest.raises(InputError, match=r"sequences \['05'\] not found"):
        discover(odometry_base, sequences="05")
    # integers, as `-s 4` gives them (a TypeError, 'int' object is not iterable, before)
    assert discover(odometry_base, sequences=4) == discover(odometry_base, sequences=[4]) == \
        discover(odometry_base, sequences=["04"])


def test_load_run_names_what_it_takes(odometry_base: Path) -> None:
    ref = discover(odometry_base)[0]
    with pytest.raises(TypeError, match=r"load.run takes a stages.load.FrameRef .*got str .*scan_points"):
        run(ref.source)  # an AttributeError ('str' object has no attribute 'source') before
    assert run(ref, {"max_range": 50.0}).points.shape[1] == 4  # options as a mapping of its keys


def test_discover_names_the_frames_that_exist_when_a_range_selects_none(odometry_base: Path) -> None:
    with pytest.raises(InputError, match=r"no frames in the selected range \(first 5, last 8\) in 04; "
                                         r"frames found: 04: 3 frames, 0 to 2"):
        discover(odometry_base, frames=range(5, 9))


def test_the_frames_found_name_the_gaps_of_a_partial_download(odometry_base: Path) -> None:
    # "3 frames, 0 to 2" with frame 1 absent read as if a range of frame 1 should have found it
    # (a batch user's trial)
    next((odometry_base / "sequences" / "04" / "velodyne").glob("000001.bin")).unlink()
    with pytest.raises(InputError, match=r"in 04; frames found: 04: 2 frames from 0 to 2: 0, 2$"):
        discover(odometry_base, frames=range(1, 2))


def test_a_named_sequence_the_range_leaves_empty_is_refused(odometry_base: Path) -> None:
    write_odometry_sequence(odometry_base, sequence="05", n_frames=6)
    assert {r.sequence for r in discover(odometry_base, frames=range(4, 6))} == {"05"}  # none named: fine
    with pytest.raises(InputError, match=r"\(first 4, last 5\) in 04; frames found: 04: 3 frames, 0 to 2"):
        discover(odometry_base, sequences=["04", "05"], frames=range(4, 6))


def test_discover_matches_digit_sequence_names_without_leading_zeros(odometry_base: Path) -> None:
    for name in ("4", "04", "004"):
        assert [r.sequence for r in discover(odometry_base, sequences=[name])] == ["04"] * 3


def test_one_scan_with_named_sequences_is_refused(odometry_base: Path) -> None:
    scan = next((odometry_base / "sequences" / "04" / "velodyne").glob("*.bin"))
    with pytest.raises(InputError, match="one scan is one frame"):
        discover(scan, sequences=["foo"])


def test_discover_takes_one_bin_file_as_one_frame(odometry_base: Path, tmp_path: Path) -> None:
    scan = odometry_base / "sequences" / "04" / "velodyne" / "000001.bin"
    [ref] = discover(scan)
    assert (ref.dataset, ref.sequence, ref.index, ref.source) == ("bin", bin_sequence_name(scan.parent), 1, str(scan))
    assert run(ref, Options(max_points=10_000)).points.shape[1] == 4
    with pytest.raises(InputError, match="outside the selected range"):
        discover(scan, frames=range(2, 3))
    text = tmp_path / "notes.txt"
    text.write_text("x")
    with pytest.raises(InputError, match="not a KITTI .bin scan"):
        discover(text)


def test_discover_bin_folder_uses_the_numbers_in_names(tmp_path: Path) -> None:
    rng = np.random.default_rng(2)
    folder = tmp_path / "scans"
    folder.mkdir()
    for name in ("000010.bin", "000012.bin"):
        _scan(rng).tofile(folder / name)
    refs = discover(folder)
    sequence = bin_sequence_name(folder)
    assert [(r.dataset, r.sequence, r.index) for r in refs] == [("bin", sequence, 10), ("bin", sequence, 12)]
    other = tmp_path / "named"
    other.mkdir()
    for name in ("scan_b_0002.bin", "scan_a_0005.bin"):
        _scan(rng).tofile(other / name)
    refs = discover(other, kind="bin")
    assert [(Path(r.source).name, r.index) for r in refs] == [("scan_b_0002.bin", 2), ("scan_a_0005.bin", 5)]  # frame order


def test_discover_rejects_paths_with_nothing_recognisable(tmp_path: Path) -> None:
    (tmp_path / "empty").mkdir()
    with pytest.raises(InputError, match="does not exist") as info:
        discover(tmp_path / "missing")
    assert info.value.stage == "load" and info.value.source.endswith("missing")
    with pytest.raises(InputError, match="no KITTI raw drives"):
        discover(tmp_path / "empty", kind="raw")
    with pytest.raises(InputError, match="no KITTI raw drives, odometry sequences or .bin scans"):
        discover(tmp_path / "empty")
    with pytest.raises(InputError, match="unknown input kind"):
        discover(tmp_path, kind="lidar")


def test_frame_ref_pickles_and_keys(raw_base: Path) -> None:
    ref = discover(raw_base)[1]
    clone = pickle.loads(pickle.dumps(ref))
    assert clone == ref and clone.key == f"raw/{DRIVE_NAME}/000001"


# --- loading ------------------------------------------------------------------------------------


def test_load_raw_frame_with_timestamp_calibration_and_pose(raw_base: Path) -> None:
    refs = discover(raw_base)
    frame = run(refs[2], Options(max_points=10_000))
    expected = np.fromfile(refs[2].source, dtype=np.float32).reshape(-1, 4)
    assert frame.points.dtype == np.float32 and np.array_equal(frame.points, expected)
    assert (frame.dataset, frame.sequence, frame.index, frame.source) == ("raw", DRIVE_NAME, 2, refs[2].source)
    assert frame.timestamp == pytest.approx(0.2)
    assert np.allclose(frame.calib["T_velo_imu"][:3, 3], IMU_TO_VELO_T)
    assert frame.calib["T_cam0_velo"].shape == (4, 4) and frame.calib["P_rect_20"].shape == (3, 4)
    # IMU 2 m above its first position, no rotation: T_w_velo = T_w_imu @ inv(T_velo_imu).
    assert np.allclose(frame.pose[:3, :3], np.eye(3))
    assert np.allclose(frame.pose[:3, 3], np.array([0, 0, 2.0]) - IMU_TO_VELO_T, atol=1e-6)


def test_an_extract_drive_takes_its_own_timestamps_not_the_sync_drives(raw_base: Path) -> None:
    # pykitti reads a "_sync" drive unless told: an "_extract" drive beside one was given the sync
    # drive's times, and alone every frame failed naming a folder not there (a trial)
    sync = raw_base / DATE / DRIVE_NAME
    extract = Path(shutil.copytree(sync, sync.with_name(DRIVE_NAME.replace("_sync", "_extract"))))
    stamps = extract / "oxts" / "timestamps.txt"
    lines = stamps.read_text().splitlines(keepends=True)
    lines[2] = lines[2].replace(lines[2][11:19], "00:00:09")  # frame 2, seconds later than the sync drive's
    stamps.write_text("".join(lines))
    frame = run(next(ref for ref in discover(raw_base) if ref.sequence == extract.name and ref.index == 2),
                Options(max_points=10_000))
    sync_frame = run(next(ref for ref in discover(raw_base) if ref.sequence == DRIVE_NAME and ref.index == 2),
                     Options(max_points=10_000))
    assert frame.timestamp != pytest.approx(sync_frame.timestamp)
    shutil.rmtree(sync)
    alone = run(discover(raw_base)[2], Options(max_points=10_000))
    assert alone.sequence == extract.name and alone.timestamp == pytest.approx(frame.timestamp)


def test_load_odometry_frame_with_pose_from_poses_file(odometry_base: Path) -> None:
    frame = run(discover(odometry_base)[1], Options(max_points=10_000))
    assert (frame.dataset, frame.sequence, frame.index) == ("odometry", "04", 1)
    assert frame.timestamp == pytest.approx(0.1)
    tr = frame.calib["T_cam0_velo"]
    assert np.allclose(tr[:3, 3], [0, -0.08, -0.27])
    expected_pose = np.eye(4)
    expected_pose[2, 3] = 2.0
    assert np.allclose(frame.pose, expected_pose @ tr)  # T_w_velo = T_w_cam0 @ Tr


def test_frame_metadata_is_what_load_gives_and_follows_a_corrected_file(odometry_base: Path) -> None:
    ref = discover(odometry_base)[1]
    frame = run(ref, Options(max_points=10_000))
    timestamp, pose = frame_metadata(ref)
    assert timestamp == frame.timestamp and np.array_equal(pose, frame.pose)
    # the files are read once per version: an edit (a new size or time) is read again
    times = odometry_base / "sequences" / "04" / "times.txt"
    times.write_text("0.000000e+00\n1.250000e-01\n2.000000e-01\n")
    assert frame_metadata(ref)[0] == pytest.approx(0.125)
    poses = odometry_base / "poses" / "04.txt"
    lines = poses.read_text().splitlines()
    lines[1] = " ".join(["1", "0", "0", "5", "0", "1", "0", "0", "0", "0", "1", "2"])
    poses.write_text("\n".join(lines) + "\n")
    assert frame_metadata(ref)[1][0, 3] == pytest.approx(5.0 + frame.calib["T_cam0_velo"][0, 3])


def test_a_calibration_is_parsed_once_per_version_of_its_files(raw_base: Path, odometry_base: Path,
                                                                monkeypatch: pytest.MonkeyPatch) -> None:
    # every finished frame's check parsed its date's or sequence's calibration again: most of a
    # rerun's cost per skipped frame (a trial at scale)
    import pykitti.utils

    parsed: list[str] = []
    real = pykitti.utils.read_calib_file
    monkeypatch.setattr(pykitti.utils, "read_calib_file", lambda path: parsed.append(path) or real(path))
    for base in (raw_base, odometry_base):
        refs = discover(base)
        first = frame_metadata(refs[1])
        before = len(parsed)
        for ref in refs:
            frame_metadata(ref)
        assert len(parsed) == before, base  # the version already parsed serves every frame
        calib = next(base.rglob("calib_imu_to_velo.txt" if base == raw_base else "calib.txt"))  # what the pose reads
        text = calib.read_text()
        calib.write_text(re.sub(r"^T: \S+", "T: 1.5", text, count=1, flags=re.M) if base == raw_base else
                         re.sub(r"^(Tr: \S+ \S+ \S+) \S+", r"\1 2.0", text, count=1, flags=re.M))
        moved = frame_metadata(refs[1])
        assert len(parsed) > before and not np.allclose(moved[1], first[1]), base  # a corrected file is read


def test_a_frame_metadata_lists_no_folder_of_the_drive(raw_base: Path, odometry_base: Path,
                                                       monkeypatch: pytest.MonkeyPatch) -> None:
    # pykitti's readers globbed every scan, image and packet folder for each frame: a cost that grew
    # with the drive, paid per frame by every load and every rerun's check of the finished frames
    import glob

    refs = [discover(raw_base)[1], discover(odometry_base)[1]]
    listed: list[str] = []
    monkeypatch.setattr(glob, "glob", lambda pattern, *args, **kwargs: listed.append(pattern) or [])
    for ref in refs:
        timestamp, pose = frame_metadata(ref)
        assert timestamp is not None and pose is not None
        run(ref, Options(max_points=10_000))
    assert listed == []


def test_load_odometry_without_poses_file_has_no_pose(tmp_path: Path) -> None:
    write_odometry_sequence(tmp_path, poses=False)
    frame = run(discover(tmp_path)[0], Options(max_points=10_000))
    assert frame.pose is None and frame.timestamp == 0.0


def test_load_odometry_takes_the_pose_from_semantickittis_poses_file_when_kittis_is_absent(tmp_path: Path) -> None:
    # SemanticKITTI ships sequences/NN/poses.txt, KITTI's odometry set poses/NN.txt: with only the
    # first, every pose was unknown without a note
    write_odometry_sequence(tmp_path)
    kittis = tmp_path / "poses" / "04.txt"
    semantic = tmp_path / "sequences" / "04" / "poses.txt"
    semantic.write_text(kittis.read_text())
    expected = run(discover(tmp_path)[1], Options(max_points=10_000)).pose
    kittis.unlink()
    frame = run(discover(tmp_path)[1], Options(max_points=10_000))
    assert frame.pose is not None and np.array_equal(frame.pose, expected)
    assert frame_metadata(discover(tmp_path)[1])[1] is not None
    # KITTI's own file comes first where both are
    kittis.write_text("\n".join(" ".join(["1", "0", "0", "0", "0", "1", "0", "0", "0", "0", "1", str(i)])
                                for i in range(3)) + "\n")
    assert run(discover(tmp_path)[1], Options(max_points=10_000)).pose[2, 3] != pytest.approx(expected[2, 3])
    # and a bad line of SemanticKITTI's is named as KITTI's is
    kittis.unlink()
    semantic.write_text("1 0 0\n" * 3)
    bad = run(discover(tmp_path)[1], Options(max_points=10_000))
    assert bad.pose is None and any(f"pose unknown: {semantic} line 2" in note for note in bad.notes)


def test_load_bin_frame_has_no_metadata(tmp_path: Path) -> None:
    points = _scan(np.random.default_rng(3), 500)
    points.tofile(tmp_path / "000007.bin")
    frame = run(discover(tmp_path)[0], Options(max_points=10_000))
    assert np.array_equal(frame.points, points) and frame.index == 7
    assert frame.timestamp is None and frame.pose is None and frame.calib == {}


def test_a_scan_kitti_pu_densified_shows_no_rings_and_says_why(street_scan, tmp_path: Path) -> None:
    # the mirror's scans hold the generated points after the returns; the demo drive's read as 256
    # rings, and a second pass snapped away 95% of its new points against the README (a trial)
    folder = tmp_path / "scans"
    folder.mkdir()
    street_scan.points.astype(np.float32).tofile(folder / "000000.bin")
    plain = run(discover(folder)[0])
    assert plain.rings is not None and not plain.notes
    (folder / "kitti_pu").mkdir()
    np.savez(folder / "kitti_pu" / "000000.npz", generated=np.zeros(len(street_scan.points), bool))
    densified = run(discover(folder)[0])
    assert densified.rings is None
    assert densified.notes == (f"load: a scan kitti-pu densified ({folder / 'kitti_pu' / '000000.npz'} beside it): "
                               "its generated points are not in KITTI's ring order, so no laser rings are read "
                               "from it",)


@pytest.mark.parametrize(
    ("content", "message"),
    [
        (b"", "empty scan"),
        (b"\0" * 35, "not a multiple of 16"),
        (np.array([[1, 2, 3, 0.5], [np.nan, 0, 0, 0]], np.float32).tobytes(), "NaN or infinite"),
        (np.array([[1, 2, np.inf, 0.5]], np.float32).tobytes(), "NaN or infinite"),
        (np.zeros((11, 4), np.float32).tobytes(), "exceeds the limit of 10"),
    ],
)
def test_bad_scans_are_reported_with_the_file(tmp_path: Path, content: bytes, message: str) -> None:
    path = tmp_path / "000000.bin"
    path.write_bytes(content)
    with pytest.raises(InputError, match=message) as info:
        read_scan(path, max_points=10)
    assert info.value.source == str(path) and info.value.stage == "load"
    ref = FrameRef(dataset="bin", sequence="x", index=0, source=str(path))
    with pytest.raises(InputError, match=message):
        run(ref, Options(max_points=10))


def test_files_of_other_point_cloud_formats_are_named(tmp_path: Path) -> None:
    # an .npy of a scan was read as one: its 128 header bytes became 8 points (2e8 and 7e31 among
    # them), which the load's range limit then dropped without a word (a library user's trial)
    points = np.tile(np.array([[5.0, 1.0, -1.0, 0.3]], np.float32), (8, 1))
    np.save(tmp_path / "scan.npy", points)
    assert (tmp_path / "scan.npy").stat().st_size % 16 == 0
    with pytest.raises(InputError, match=r"is a NumPy \.npy file \(np\.load it and give the array to "
                                         r"frame_from_points\), not a KITTI scan") as info:
        read_scan(tmp_path / "scan.npy")
    assert info.value.source == str(tmp_path / "scan.npy")
    (tmp_path / "scan.ply").write_bytes(b"ply\nformat binary_little_endian 1.0\n" + points.tobytes())
    with pytest.raises(InputError, match="is a PLY file, not a KITTI scan"):
        read_scan(tmp_path / "scan.ply")
    (tmp_path / "000000.bin").write_bytes(points.tobytes())  # a scan is read as before
    np.testing.assert_array_equal(read_scan(tmp_path / "000000.bin"), points)


def test_missing_scan_file_is_reported(tmp_path: Path) -> None:
    with pytest.raises(InputError, match="cannot read scan") as info:
        read_scan(tmp_path / "gone.bin")
    assert info.value.source.endswith("gone.bin")


@pytest.mark.parametrize("name", ["calib_imu_to_velo.txt", "calib_velo_to_cam.txt", "calib_cam_to_cam.txt"])
def test_missing_raw_calibration_names_the_file(raw_base: Path, name: str) -> None:
    (raw_base / DATE / name).unlink()
    with pytest.raises(InputError, match="missing or unreadable raw metadata") as info:
        run(discover(raw_base)[0], Options(max_points=10_000))
    assert info.value.source.endswith(name)


def test_missing_raw_timestamps_names_the_file(raw_base: Path) -> None:
    (raw_base / DATE / DRIVE_NAME / "oxts" / "timestamps.txt").unlink()
    with pytest.raises(InputError) as info:
        run(discover(raw_base)[0], Options(max_points=10_000))
    assert info.value.source.endswith("oxts/timestamps.txt")


def test_short_raw_timestamps_file_is_reported(raw_base: Path) -> None:
    stamps = raw_base / DATE / DRIVE_NAME / "oxts" / "timestamps.txt"
    stamps.write_text(stamps.read_text().splitlines(keepends=True)[0])
    with pytest.raises(InputError, match="fewer entries than frames: nothing for frame 2") as info:
        run(discover(raw_base)[2], Options(max_points=10_000))
    assert info.value.source.endswith("timestamps.txt")


def test_raw_calibration_without_an_entry_is_reported(raw_base: Path) -> None:
    cam = raw_base / DATE / "calib_cam_to_cam.txt"
    cam.write_text("".join(line for line in cam.read_text().splitlines(keepends=True)
                           if not line.startswith("P_rect_02")))
    with pytest.raises(InputError, match="P_rect_02"):
        run(discover(raw_base)[0], Options(max_points=10_000))


def test_a_partial_odometry_sequence_takes_each_frames_own_time_and_pose(tmp_path: Path) -> None:
    sequence_dir = write_odometry_sequence(tmp_path, n_frames=4)
    for index in (0, 1):  # a partial download: scans 2 and 3 only, metadata of the whole sequence
        (sequence_dir / "velodyne" / f"{index:06d}.bin").unlink()
    frames = [run(ref, Options(max_points=10_000)) for ref in discover(tmp_path)]
    assert [f.index for f in frames] == [2, 3]
    assert [f.timestamp for f in frames] == pytest.approx([0.2, 0.3])  # were 0.0 and 0.1: lines by place
    tr = frames[0].calib["T_cam0_velo"]
    assert [float((f.pose @ np.linalg.inv(tr))[2, 3]) for f in frames] == pytest.approx([4.0, 6.0])


def test_a_partial_raw_drive_takes_each_frames_own_time_and_oxts_packet(raw_base: Path) -> None:
    drive_dir = raw_base / DATE / DRIVE_NAME
    (drive_dir / "velodyne_points" / "data" / "0000000000.bin").unlink()
    (drive_dir / "oxts" / "data" / "0000000001.txt").unlink()  # a packet missing in the middle
    frames = {ref.index: run(ref, Options(max_points=10_000)) for ref in discover(raw_base)}
    assert frames[1].timestamp == pytest.approx(0.1) and frames[2].timestamp == pytest.approx(0.2)
    assert frames[1].pose is None  # its packet is missing: frame 2's packet was taken for it
    assert np.allclose(frames[2].pose[:3, 3], np.array([0, 0, 2.0]) - IMU_TO_VELO_T, atol=1e-6)


def test_raw_scan_without_oxts_packet_has_no_pose_and_a_note_naming_it(raw_base: Path) -> None:
    packet = raw_base / DATE / DRIVE_NAME / "oxts" / "data" / "0000000002.txt"
    packet.unlink()
    frame = run(discover(raw_base)[2], Options(max_points=10_000))
    assert frame.pose is None and frame.timestamp == pytest.approx(0.2)
    assert list(frame.notes) == [f"pose unknown: no OXTS packet {packet}"]  # it was done without a word


@pytest.mark.parametrize("name", ["calib.txt", "times.txt"])
def test_missing_odometry_calibration_or_times_names_the_file(odometry_base: Path, name: str) -> None:
    (odometry_base / "sequences" / "04" / name).unlink()
    with pytest.raises(InputError, match="missing or unreadable odometry metadata") as info:
        run(discover(odometry_base)[0], Options(max_points=10_000))
    assert info.value.source.endswith(name)


def test_loads_the_embedded_synthetic_demo_drive(tmp_path: Path) -> None:
    from pipeline.synthetic_drive import PERIOD, SPEED, write_synthetic_drive

    write_synthetic_drive(tmp_path, n_frames=2, seed=0)
    refs = discover(tmp_path)
    assert [r.key for r in refs] == [f"raw/2011_09_26_drive_0001_sync/{i:06d}" for i in range(2)]
    first, second = (run(ref, Options(max_points=500_000)) for ref in refs)
    assert second.timestamp == pytest.approx(PERIOD) and first.timestamp == 0.0
    assert len(second.points) > 10_000
    # The sensor moves SPEED * PERIOD metres along x between scans.
    assert np.allclose(second.pose[:3, 3] - first.pose[:3, 3], [SPEED * PERIOD, 0, 0.02 * SPEED * PERIOD], atol=1e-3)


def _scan_points(count: int = 2_000, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    points = rng.uniform(-30, 30, size=(count, 4)).astype(np.float32)
    points[:, 3] = rng.uniform(0, 1, count)
    return points


def test_points_in_memory_are_checked_as_a_scan_file_is() -> None:
    points = _scan_points()
    far = points.copy()
    far[:100, :3] *= 300  # 5% of the points thousands of metres out: dropped, with a note
    frame = frame_from_points(far)
    assert len(frame.points) == len(points) - 100 and np.sqrt((frame.points[:, :3] ** 2).sum(1)).max() <= 200
    assert any("100 points beyond 200 m dropped" in note for note in frame.notes)
    mostly_far = points.copy()
    mostly_far[:, :3] *= 300
    with pytest.raises(InputError, match=r"\[load\] points in memory: .* beyond 200 m"):
        frame_from_points(mostly_far)
    # a crop to 20 m was refused as "not a LiDAR scan" with no word of how to crop (a library user's trial)
    with pytest.raises(InputError, match=r"beyond 20 m, more than the 10% input.max_out_of_range_share allows: .* "
                                         r"To crop scans to a shorter input.max_range, raise "
                                         r"input.max_out_of_range_share too"):
        frame_from_points(points, max_range=20.0)
    assert len(frame_from_points(points, max_range=20.0, max_out_of_range_share=1.0).points) < len(points)
    nan = points.copy()
    nan[7, 1] = np.nan
    with pytest.raises(InputError, match=r"points in memory: 1 point with NaN or infinite values \(first at point 7\)"):
        frame_from_points(nan)
    with pytest.raises(InputError, match="no points"):
        frame_from_points(np.zeros((0, 4), np.float32))
    with pytest.raises(InputError, match=r"mine.bin: expected an \(N, 4\) array"):
        frame_from_points(points[:, :3], source="mine.bin")


@pytest.mark.parametrize("per_metre, unit", [(10, "decimetres"), (100, "centimetres"), (1000, "millimetres"),
                                             (1e6, None)])
def test_a_scan_out_of_range_in_other_units_is_said_to_be(per_metre: float, unit: str | None) -> None:
    # a scan in millimetres was refused as garbage or a map's frame, never a word of units (a
    # library user's trial); points a million times too far are no unit's
    points = _scan_points()
    points[:, :3] *= 2.5 * per_metre  # out to 75 m in metres
    with pytest.raises(InputError) as refused:
        frame_from_points(points)
    hint = f"divided by {per_metre:g} (in {unit}) they would lie within 200 m; kitti-pu takes metres"
    assert (hint in str(refused.value)) == (unit is not None), str(refused.value)
    assert unit is not None or "unit smaller than metres" not in str(refused.value)


def test_integer_points_are_taken_with_a_note() -> None:
    # a scan cast to int32 lost 97% of its points as repeats, and the notes never named the cause
    # (a library user's trial)
    points = np.round(_scan_points()[:, :3]).astype(np.int32)
    frame = frame_from_points(np.column_stack([points, np.zeros(len(points), np.int32)]))
    assert any(note.startswith("the points came as integers (int32): whole metres at best") for note in frame.notes)
    assert not any("integers" in note for note in frame_from_points(_scan_points()).notes)


@pytest.mark.parametrize("provenance, message", [
    # written into the files' records as "NaN" / "nan" (a library user's trial)
    ({"timestamp": float("nan")}, "timestamp must be a finite number of seconds"),
    ({"timestamp": "abc"}, "timestamp must be a finite number"),  # it failed only at the write stage
    ({"pose": np.full((4, 4), np.nan)}, r"pose must be a finite \(4, 4\) matrix"),
    ({"pose": np.eye(3)}, r"pose must be a finite \(4, 4\) matrix .* got float64 \(3, 3\)"),
    # a bare TypeError of the Frame's constructor, without the stage (a library user's trial)
    ({"colour": "red"}, r"\[load\] points in memory: unknown frame field\(s\) colour; frame_from_points takes "
                        "timestamp, source"),
])
def test_points_in_memory_refuse_a_timestamp_or_pose_the_files_cannot_record(provenance: dict, message: str) -> None:
    with pytest.raises(InputError, match=message):
        frame_from_points(_scan_points(), **provenance)
    frame = frame_from_points(_scan_points(), timestamp=12.5, pose=np.eye(4))
    assert frame.timestamp == 12.5 and np.array_equal(frame.pose, np.eye(4))


def test_repeated_points_are_dropped_at_load_with_a_note_their_rows_kept() -> None:
    # each copy was upsampled as a point of its own: copies filled their own neighbourhoods and
    # 30,000 stacked generated points of a scan given twice came out without a word (a library
    # user's trial); upsample_object collapsed them already
    points = _scan_points()
    points[:, :3] *= 0.2  # all within range
    twice = np.repeat(points, 2, axis=0)
    twice[1::2, 3] = 0.5  # a copy with another reflectance is still the same place
    frame = frame_from_points(twice)
    assert np.array_equal(frame.points, points) and np.array_equal(frame.scan_rows, np.arange(0, len(twice), 2))
    assert any(note.startswith(f"{len(points)} points repeating an earlier point's x, y, z dropped at load (50.00% "
                               "of the scan)") for note in frame.notes)
    far = twice.copy()
    far[:10, :3] *= 1000  # rows dropped for range and for repeats: the kept rows are those of the scan
    frame = frame_from_points(far)
    assert np.array_equal(frame.points[:, :3], twice[frame.scan_rows, :3])
    assert len(frame.points) == len(points) - 5 and np.array_equal(frame.scan_rows[:3], [10, 12, 14])
    assert not any("repeating" in note for note in frame_from_points(points).notes)


@pytest.mark.parametrize("kind", [bool, str, object])
def test_points_that_are_not_numbers_are_refused_naming_the_type(kind: type) -> None:
    points = _scan_points().astype(kind)  # booleans read as points at (1, 1, 1); strings failed in numpy
    with pytest.raises(InputError, match=r"\[load\] points in memory: expected numbers .* got an array of"):
        frame_from_points(points)


@pytest.mark.parametrize("name, reason", [(dict(sequence="../../escape"), "sequence '../../escape' is not one folder"),
                                          (dict(sequence=""), "sequence '' is not one folder"),
                                          (dict(dataset="a/b"), "dataset 'a/b' is not one folder"),
                                          (dict(index=-1), "index must be an integer from 0 to 2147483647, got -1"),
                                          # the int32 frame column: the PLY wrapped it, the Parquet write failed
                                          (dict(index=2**31 + 7), "index must be an integer from 0 to 2147483647")])
def test_a_frame_name_off_the_output_layout_is_refused(name: dict, reason: str) -> None:
    with pytest.raises(InputError, match=rf"\[load\] points in memory: frame {reason}"):
        frame_from_points(_scan_points(), **name)


def test_a_folder_given_as_a_scan_is_named_as_a_folder(tmp_path: Path) -> None:
    with pytest.raises(InputError, match="is a folder, not a scan"):
        read_scan(tmp_path)


def test_odometry_frames_loaded_on_threads_leave_stdout_alone(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    import sys
    from concurrent.futures import ThreadPoolExecutor

    write_odometry_sequence(tmp_path, n_frames=8, poses=False)  # pykitti prints for each frame without poses
    refs = discover(tmp_path)
    stdout = sys.stdout
    with ThreadPoolExecutor(4) as pool:  # a worker runs frames on threads
        frames = list(pool.map(lambda ref: run(ref, Options(max_points=10_000)), refs * 4))
    assert sys.stdout is stdout and len(frames) == 32
    assert "poses" not in capsys.readouterr().out


def test_frame_from_points_checks_as_a_file_is_checked_and_keeps_its_own_copy() -> None:
    rng = np.random.default_rng(0)
    scan = np.c_[rng.normal(size=(1000, 3)) * 10, rng.uniform(0, 1, 1000)].astype(np.float32)
    xyz_read_as_four = scan[:, :3].reshape(-1, 4)  # x, y, z only, taken four values a point
    # read_scan refused this layout, frame_from_points took it (a new-user trial)
    with pytest.raises(InputError, match="have a negative reflectance"):
        frame_from_points(xyz_read_as_four)
    frame = frame_from_points(scan)
    scan[0, 0] = 999.0  # the frame (frozen) changed with the caller's array before
    assert frame.points[0, 0] != 999.0
    huge = scan.astype(np.float64)
    huge[3, 1] = 1e40
    with pytest.raises(InputError, match=r"1 point with values beyond float32's range \(first at point 3\)"):
        frame_from_points(huge)  # "NaN or infinite values" after an overflow warning before


def test_a_malformed_pose_line_leaves_the_pose_unknown_with_a_note_naming_file_and_line(tmp_path: Path) -> None:
    write_odometry_sequence(tmp_path, sequence="04", n_frames=3)
    poses = tmp_path / "poses" / "04.txt"
    lines = poses.read_text().splitlines()
    poses.write_text("\n".join([lines[0], "1 0 0 0 0 1 0 0 0 0 1", *lines[2:]]) + "\n")  # 11 numbers on line 2
    refs = discover(tmp_path)
    # "calib.txt: cannot read the calibration (ValueError: cannot reshape array of size 11 ...)", before
    second = run(refs[1], Options())
    assert second.pose is None and any(f"pose unknown: {poses} line 2 is not 12 numbers" in note
                                       for note in second.notes)
    assert run(refs[2], Options()).pose is not None


def test_a_bad_first_pose_line_or_a_byte_order_mark_touches_no_other_frame(tmp_path: Path) -> None:
    # frame 0's line was read for every frame: a bad one (or a BOM before it) left every pose unknown
    write_odometry_sequence(tmp_path, sequence="04", n_frames=3)
    poses = tmp_path / "poses" / "04.txt"
    good = poses.read_text().splitlines()
    refs = discover(tmp_path)
    expected = [frame_metadata(ref)[1] for ref in refs]
    poses.write_text("\n".join(["nan 0 0 0 0 1 0 0 0 0 1 0", *good[1:]]) + "\n")
    assert frame_metadata(refs[0])[1] is None
    assert all(np.array_equal(frame_metadata(ref)[1], pose) for ref, pose in zip(refs[1:], expected[1:]))
    poses.write_bytes(b"\xef\xbb\xbf" + ("\n".join(good) + "\n").encode())
    times = tmp_path / "sequences" / "04" / "times.txt"
    times.write_bytes(b"\xef\xbb\xbf" + times.read_bytes())
    assert all(np.array_equal(frame_metadata(ref)[1], pose) for ref, pose in zip(refs, expected))
    assert frame_metadata(refs[0])[0] == 0.0


def test_a_raw_timestamp_reads_the_same_whatever_ends_its_line(raw_base: Path) -> None:
    # pykitti's line[:-4] took a digit more from a last line without its newline, and failed on CRLF
    stamps = raw_base / DATE / DRIVE_NAME / "oxts" / "timestamps.txt"
    refs = discover(raw_base)
    expected = [frame_metadata(ref)[0] for ref in refs]
    text = stamps.read_text()
    for variant in (text.rstrip("\n"), text.replace("\n", "\r\n")):
        stamps.write_bytes(variant.encode())
        assert [frame_metadata(ref)[0] for ref in refs] == expected


def test_a_rewritten_times_file_is_read_again_though_its_size_and_time_are_the_same(odometry_base: Path) -> None:
    # a copy that keeps the time (cp -p, rsync -t) returned the cached lines of the old file
    import os

    ref = discover(odometry_base)[1]
    times = odometry_base / "sequences" / "04" / "times.txt"
    before = times.stat()
    assert frame_metadata(ref)[0] == pytest.approx(0.1)
    replacement = times.with_name("times.new")
    replacement.write_text(times.read_text().replace("1.000000e-01", "2.000000e-01"))
    os.utime(replacement, ns=(before.st_atime_ns, before.st_mtime_ns))
    replacement.replace(times)
    assert times.stat().st_size == before.st_size and times.stat().st_mtime_ns == before.st_mtime_ns
    assert frame_metadata(ref)[0] == pytest.approx(0.2)


def test_a_drive_without_frame_0s_packet_lists_its_packets_once(raw_base: Path) -> None:
    # the first packet present was found by listing the whole folder for every frame: a rerun's
    # check of a long drive's finished frames took minutes
    from stages import load

    (raw_base / DATE / DRIVE_NAME / "oxts" / "data" / "0000000000.txt").unlink()
    refs = discover(raw_base)
    load._first_packet.cache_clear()
    poses = [frame_metadata(ref)[1] for ref in refs]
    assert load._first_packet.cache_info().misses == 1
    assert poses[1] is not None and np.allclose(poses[1][:3, :3], poses[2][:3, :3])


def test_scan_points_takes_a_mapping_of_the_input_section_as_run_does(tmp_path: Path) -> None:
    from stages.load import scan_points

    scan = np.array([[1, 0, 0, 0.5], [30, 0, 0, 0.5], [60, 0, 0, 0.5]] * 20, dtype=np.float32)
    scan[:, 1] = np.arange(len(scan)) * 0.01  # 60 places, none repeated (repeats are dropped)
    path = tmp_path / "000000.bin"
    scan.tofile(path)
    # an AttributeError ('dict' object has no attribute 'max_points') before
    near = scan_points(path, {"max_range": 40.0, "max_out_of_range_share": 0.5})
    assert len(near) == 40 and np.abs(near[:, 0]).max() == 30
