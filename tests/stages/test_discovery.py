"""stages.discovery: frame identity is unique, comes from the full source and never from a file's
position, a folder named like a scan is not a scan, and every scan is fingerprinted (issue 21,
items 1, 10 and 11)."""

from __future__ import annotations

import os
import shutil
from pathlib import Path

import numpy as np
import pytest

from stages.errors import InputError
from stages.load import discover, source_fingerprint


def _write_scans(folder: Path, names: list[str], seed: int = 0) -> Path:
    rng = np.random.default_rng(seed)
    folder.mkdir(parents=True, exist_ok=True)
    for name in names:
        rng.uniform(-20, 20, size=(300, 4)).astype(np.float32).tofile(folder / name)
    return folder


def test_a_copy_beside_its_original_is_a_collision_naming_both_files(tmp_path: Path) -> None:
    folder = _write_scans(tmp_path / "scans", ["000000.bin", "000000_copy.bin", "000001.bin"])
    with pytest.raises(InputError, match="also") as info:
        discover(folder)
    message = str(info.value)
    assert "000000.bin" in message and "000000_copy.bin" in message and "000001.bin" not in message
    assert info.value.stage == "load"


def test_hidden_files_are_not_scans_and_the_suffix_may_be_upper_case(tmp_path: Path) -> None:
    # macOS leaves "._NAME" files beside every file it copies to a shared drive; an odometry
    # sequence holding them, and a folder scanned to upper-case names
    sequence = _write_scans(tmp_path / "base" / "sequences" / "00" / "velodyne", ["000000.bin", "000001.bin"])
    (sequence / "._000000.bin").write_bytes(b"\0" * 4096)
    (sequence / ".000001.bin").write_bytes(b"")
    assert [Path(ref.source).name for ref in discover(tmp_path / "base")] == ["000000.bin", "000001.bin"]
    upper = _write_scans(tmp_path / "upper", ["000010.BIN", "000011.Bin"])
    assert [ref.index for ref in discover(upper, kind="bin")] == [10, 11]
    assert [ref.index for ref in discover(upper / "000010.BIN")] == [10]


def test_frame_numbers_come_from_names_not_positions(tmp_path: Path) -> None:
    folder = _write_scans(tmp_path / "named", ["scan_12.bin", "scan_7.bin"])
    before = {ref.key: ref.source for ref in discover(folder, kind="bin")}
    assert sorted(int(key[-6:]) for key in before) == [7, 12]
    _write_scans(folder, ["scan_0999.bin", "scan_0001.bin"], seed=1)  # sorts before the others
    after = {ref.key: ref.source for ref in discover(folder, kind="bin")}
    assert {key: after[key] for key in before} == before


def test_a_name_without_a_number_is_refused(tmp_path: Path) -> None:
    folder = _write_scans(tmp_path / "named", ["000001.bin", "a_scan.bin"])
    with pytest.raises(InputError, match="no frame number") as info:
        discover(folder, kind="bin")
    assert info.value.source.endswith("a_scan.bin")


def test_bin_sequences_are_named_by_their_full_path(tmp_path: Path) -> None:
    first = _write_scans(tmp_path / "kitti" / "sequences" / "00" / "velodyne", ["000000.bin"])
    second = _write_scans(tmp_path / "other" / "velodyne", ["000000.bin"], seed=1)
    one, two = discover(first, kind="bin")[0], discover(second, kind="bin")[0]
    assert one.key != two.key
    assert one.sequence.startswith("velodyne-") and two.sequence.startswith("velodyne-")
    assert discover(first, kind="bin")[0].key == one.key  # stable from run to run
    assert [r.key for r in discover(first, kind="bin", sequences=["velodyne"])] == [one.key]


def test_a_directory_named_like_a_scan_is_not_a_scan(tmp_path: Path) -> None:
    folder = _write_scans(tmp_path / "scans", ["000000.bin"])
    (folder / "000001.bin").mkdir()
    (folder / "x.bin").mkdir()
    assert [Path(r.source).name for r in discover(folder)] == ["000000.bin"]
    only_folders = tmp_path / "odd"
    (only_folders / "x.bin").mkdir(parents=True)
    with pytest.raises(InputError, match="no KITTI raw drives, odometry sequences or .bin scans"):
        discover(only_folders)


def test_every_scan_is_fingerprinted_by_path_size_and_time(tmp_path: Path) -> None:
    folder = _write_scans(tmp_path / "scans", ["000000.bin"])
    ref = discover(folder)[0]
    assert ref.fingerprint and ref.fingerprint == source_fingerprint(ref.source)
    copy = Path(shutil.copy2(ref.source, tmp_path / "000000.bin"))
    assert source_fingerprint(copy) != ref.fingerprint  # same bytes and time, another file
    stat = os.stat(ref.source)
    os.utime(ref.source, ns=(stat.st_atime_ns, stat.st_mtime_ns + 1_000_000))
    assert source_fingerprint(ref.source) != ref.fingerprint
    assert source_fingerprint(tmp_path / "gone.bin") == ""


def test_a_folder_reached_through_a_symbolic_link_is_the_same_sequence_and_sources(tmp_path: Path) -> None:
    folder = _write_scans(tmp_path / "scans", ["000000.bin", "000001.bin"])
    link = tmp_path / "scans_link"
    link.symlink_to(folder, target_is_directory=True)
    direct, linked = discover(folder), discover(link)
    assert [(r.sequence, r.source, r.fingerprint) for r in linked] == [(r.sequence, r.source, r.fingerprint)
                                                                      for r in direct]
    assert direct[0].sequence.startswith("scans-")
    # one scan given through the link: the same frame
    single = discover(link / "000001.bin")
    assert (single[0].sequence, single[0].source, single[0].index) == (direct[1].sequence, direct[1].source, 1)


def test_the_scans_of_a_folder_come_in_frame_order_whatever_their_names(tmp_path: Path) -> None:
    folder = tmp_path / "scans"
    folder.mkdir()
    for name in ("scan_000001.bin", "SCAN_000003.BIN", "scan_000000.bin"):
        np.zeros((4, 4), np.float32).tofile(folder / name)
    # sorted by name, SCAN_000003.BIN came first and the run went 3, 0, 1
    assert [ref.index for ref in discover(folder)] == [0, 1, 3]


def test_frames_numbered_past_a_billion_are_selected_by_an_open_range(tmp_path: Path) -> None:
    from stages.load import Options

    folder = tmp_path / "epoch"
    folder.mkdir()
    for stamp in (1_700_000_000, 1_700_000_001, 1_700_000_002):  # scans named by Unix time
        np.zeros((4, 4), np.float32).tofile(folder / f"{stamp}.bin")
    # the open end was 10**9: "no frames in the selected range" with --step 2
    frames = Options(path=folder, step=2).frame_range()
    assert [ref.index for ref in discover(folder, frames=frames)] == [1_700_000_000, 1_700_000_002]


def test_a_scan_path_that_is_not_utf8_is_refused_at_discovery(tmp_path: Path) -> None:
    folder = tmp_path / "lat"
    folder.mkdir()
    name = os.fsdecode(b"scan\xe9_000000.bin")
    try:
        np.zeros((4, 4), np.float32).tofile(folder / name)
    except (OSError, UnicodeEncodeError):
        pytest.skip("the file system refuses such names")
    # it failed at the write stage, after the network, with a UnicodeEncodeError
    with pytest.raises(InputError, match="the path is not UTF-8 text"):
        discover(folder)


def test_scans_in_a_folder_and_in_its_sub_folders_are_all_found(tmp_path: Path) -> None:
    # the sub-folder's scans were left out without a word once the folder held scans of its own
    top = _write_scans(tmp_path / "top", ["000000.bin"])
    _write_scans(top / "sub", ["000007.bin"], seed=1)
    _write_scans(top / "sub" / "deeper", ["000009.bin"], seed=2)  # deeper folders are not read
    refs = discover(top)
    assert [(Path(ref.source).parent.name, ref.index) for ref in refs] == [("top", 0), ("sub", 7)]
    assert len({ref.sequence for ref in refs}) == 2
    assert [ref.index for ref in discover(top, kind="bin")] == [0, 7]


def test_scans_left_out_as_the_runs_own_output_are_named_as_such(tmp_path: Path) -> None:
    # "no ... .bin scans found" where the scans were there: the run's own KITTI mirror, left out
    mirror = tmp_path / "out" / "kitti" / "sequences" / "00" / "velodyne"
    mirror.mkdir(parents=True)
    np.zeros((20, 4), np.float32).tofile(mirror / "000000.bin")
    with pytest.raises(InputError, match="found outside the run's own output folders .*write the output elsewhere"):
        discover(tmp_path / "out" / "kitti", exclude=[tmp_path / "out" / "kitti"])


@pytest.mark.parametrize("name, named", [("_scans", "scans"), (".scans", "scans"), ("sequence=x", "sequence-x"),
                                         ("run=1", "run-1"), ("__", "scans")])
def test_bin_folder_names_readers_would_skip_or_split_are_named_readably(tmp_path: Path, name: str,
                                                                          named: str) -> None:
    # the outputs of "_scans" were skipped by pyarrow and pandas, and "sequence=x" broke every reader
    from stages.discovery import layout_name_problem

    folder = tmp_path / name
    folder.mkdir()
    np.zeros((10, 4), np.float32).tofile(folder / "000000.bin")
    (ref,) = discover(folder, kind="bin")
    assert layout_name_problem(ref.sequence) is None and ref.sequence[:-9] == named


@pytest.mark.parametrize("name", ["_x", "a=b"])
def test_an_odometry_sequence_readers_would_skip_or_split_is_refused_before_anything_runs(
        tmp_path: Path, name: str) -> None:
    velodyne = tmp_path / "sequences" / name / "velodyne"
    velodyne.mkdir(parents=True)
    np.zeros((10, 4), np.float32).tofile(velodyne / "000000.bin")
    with pytest.raises(InputError, match=f"{name}: the sequence folder's name .* rename it"):
        discover(tmp_path, kind="odometry")


def test_frame_names_readers_would_skip_or_split_are_refused() -> None:
    from stages.frame import check_frame_name

    for sequence in ("_x", ".x", "a=b"):
        with pytest.raises(ValueError, match="readers of the Parquet dataset"):
            check_frame_name("bin", sequence, 0)
    check_frame_name("bin", "scans-1a2b3c4d", 0)


def test_a_bin_folder_beside_a_sequence_is_found_too_but_not_a_sequences_own_scans(tmp_path: Path) -> None:
    # the KITTI mirror of a run over a drive, a sequence and a .bin folder holds all three; run on
    # it, the .bin folder's frames were left out without a word (a trial)
    base = tmp_path / "mirror"
    _write_scans(base / "sequences" / "00" / "velodyne", ["000000.bin", "000001.bin"])
    _write_scans(base / "scans-1a2b3c4d", ["000000.bin"], seed=1)
    found = discover(base)
    assert sorted((ref.dataset, ref.index) for ref in found) == [("bin", 0), ("odometry", 0), ("odometry", 1)]
    # a sequence folder given itself: its velodyne/ is the sequence, not a .bin folder beside it
    assert [ref.dataset for ref in discover(base / "sequences" / "00")] == ["odometry", "odometry"]
    assert [ref.dataset for ref in discover(base, kind="odometry")] == ["odometry", "odometry"]


def test_an_odometry_sequence_outside_a_sequences_folder_is_read_as_bin_and_said_so(tmp_path: Path) -> None:
    from stages.load import odometry_folders_read_as_bin

    copied = tmp_path / "copied" / "00"
    _write_scans(copied / "velodyne", ["000000.bin", "000001.bin"])
    (copied / "times.txt").write_text("0.0\n0.1\n")
    (copied / "calib.txt").write_text("")
    refs = discover(copied)
    assert {ref.dataset for ref in refs} == {"bin"}
    (line,) = odometry_folders_read_as_bin(refs)
    assert str(copied) in line and "calib.txt and times.txt" in line and "BASE/sequences/00" in line
    # in place, it is the odometry sequence it looks like; a plain folder of scans says nothing
    base = tmp_path / "base"
    (base / "sequences").mkdir(parents=True)
    (base / "sequences" / "00").symlink_to(copied)
    in_place = discover(base)
    assert {ref.dataset for ref in in_place} == {"odometry"} and odometry_folders_read_as_bin(in_place) == []
    # in place but read as .bin scans by --kind bin: said so, not that it is misplaced (a trial)
    placed = tmp_path / "placed" / "sequences" / "07"
    _write_scans(placed / "velodyne", ["000000.bin"])
    (placed / "times.txt").write_text("0.0\n")
    expected = (f"{placed / 'velodyne'} holds the scans of KITTI odometry sequence 07, read as a plain folder of "
                ".bin scans, without timestamps, calibration, poses or labels, and written as another sequence "
                f"than odometry 07; give {placed} (without --kind bin) to read it as the sequence")
    (line,) = odometry_folders_read_as_bin(discover(placed, kind="bin"))
    assert line == expected
    # its velodyne/ folder given itself, without --kind bin: "leave out --kind bin" puzzled a new user
    (line,) = odometry_folders_read_as_bin(discover(placed / "velodyne"))
    assert line == expected
    plain = _write_scans(tmp_path / "plain" / "velodyne", ["000000.bin"])
    assert odometry_folders_read_as_bin(discover(plain)) == []
