"""stages.write under faults (issue 21, items 2, 4, 6 and 11): a writer killed mid-write leaves
nothing any reader of the Hive folder takes and nothing a later run cannot sweep; a disk that
fills up is one error line; a non-finite value is never written; each file records which scan
it came from. Real files, real readers (pandas, pyarrow.dataset, dask.dataframe, Open3D) and
real processes killed at the worst moment."""

from __future__ import annotations

import dataclasses
import os
import socket
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import dask.dataframe as dd
import numpy as np
import pandas as pd
import pyarrow.dataset as pads
import pytest

from pipeline.info import folder_info, format_info
from stages import write
from stages.errors import StageError
from stages.frame import Frame, StitchedCloud
from stages.load import source_fingerprint

REPO = Path(__file__).resolve().parents[2]

#: Writes one frame of 3,000 points to sys.argv[1], its scan at sys.argv[2]; sys.argv[3] picks a fault.
CHILD = textwrap.dedent("""
    import os, resource, signal, sys
    from pathlib import Path
    import numpy as np
    from stages import write
    from stages.errors import StageError
    from stages.frame import Frame, StitchedCloud

    out, scan, fault = Path(sys.argv[1]), sys.argv[2], sys.argv[3]
    rng = np.random.default_rng(0)
    n = 3000
    cloud = StitchedCloud(xyz=rng.uniform(-9, 9, (n, 3)).astype(np.float32),
                          reflectance=rng.uniform(0, 1, n).astype(np.float32), generated=np.ones(n, bool),
                          ground=np.zeros(n, bool), parent=np.arange(n))
    frame = Frame(points=np.zeros((n, 4), np.float32), dataset="odometry", sequence="04", index=1,
                  source=scan)
    if fault == "kill":  # die like kill -9 between writing the temporaries and renaming them
        os.replace = lambda *args: os._exit(9)
    elif fault == "full":  # the disk fills after 4 KiB: every write beyond fails with EFBIG
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
        resource.setrlimit(resource.RLIMIT_FSIZE, (4096, resource.RLIM_INFINITY))
    try:
        write.write_frame(cloud, frame, out, {"config_hash": "c"}, formats=tuple(sys.argv[4:]))
    except StageError as error:
        print("StageError:", error)
""")


def _child(out: Path, scan: Path, fault: str, *formats: str) -> subprocess.CompletedProcess:
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    return subprocess.run([sys.executable, "-c", CHILD, str(out), str(scan), fault, *formats],
                          capture_output=True, text=True, env=env, timeout=120)


def _cloud_and_frame(source: Path, n: int = 500) -> tuple[StitchedCloud, Frame]:
    rng = np.random.default_rng(1)
    scan = rng.uniform(-10, 10, (n, 4)).astype(np.float32)
    scan.tofile(source)
    cloud = StitchedCloud(xyz=scan[:, :3].copy(), reflectance=scan[:, 3].copy(), generated=np.zeros(n, bool),
                          ground=np.zeros(n, bool), parent=np.arange(n))
    return cloud, Frame(points=scan, dataset="odometry", sequence="04", index=0, source=str(source))


@pytest.fixture()
def written(tmp_path: Path) -> tuple[Path, Path]:
    """An output folder holding one complete frame (000000) and the scan it came from."""
    cloud, frame = _cloud_and_frame(tmp_path / "000000.bin")
    write.write_frame(cloud, frame, tmp_path / "out", {"config_hash": "c"})
    return tmp_path / "out", tmp_path / "000000.bin"


def test_a_writer_killed_mid_write_leaves_nothing_a_reader_takes(written: tuple[Path, Path]) -> None:
    out, scan = written
    result = _child(out, scan, "kill", "parquet", "ply")
    assert result.returncode == 9, result.stderr
    leftovers = [p for p in out.rglob("*") if p.is_file() and p.name not in ("000000.parquet", "000000.ply")]
    assert leftovers, "the killed writer left no temporaries: the test did not kill it mid-write"
    assert not [p for p in leftovers if "points" in p.relative_to(out).parts]
    assert len(pd.read_parquet(out / "points")) == 500
    assert pads.dataset(out / "points").count_rows() == 500
    assert len(dd.read_parquet(out / "points").compute()) == 500
    assert "odometry" in format_info(folder_info(out))


def test_a_run_sweeps_dead_writers_temporaries_but_not_a_live_ones(written: tuple[Path, Path]) -> None:
    out, scan = written
    assert _child(out, scan, "kill", "parquet", "ply").returncode == 9
    dead = sorted(p for p in out.rglob("*") if p.is_file() and p.name not in ("000000.parquet", "000000.ply"))
    live = write.temporary_path(out, "000002.parquet")  # this process's: a writer still running
    live.write_bytes(b"being written")
    other_host = live.with_name(live.name.replace(f"@{socket.gethostname()}~", "@elsewhere~"))
    other_host.write_bytes(b"a remote writer, still young")
    old = time.time() - 2 * write.TEMPORARY_MAX_AGE_S
    legacy = out / "points" / "odometry" / "04" / ".000003.tmp-0123abcd.parquet"
    legacy.write_bytes(b"left by an earlier version")
    swept = write.sweep_stale_temporaries(out)
    assert sorted(swept) == sorted([*dead, legacy])
    assert live.is_file() and other_host.is_file()
    os.utime(other_host, (old, old))
    assert write.sweep_stale_temporaries(out) == [other_host]
    assert write.is_complete(write.output_paths(out, "odometry", "04", 0))


def test_a_full_disk_is_one_line_and_leaves_nothing(written: tuple[Path, Path]) -> None:
    out, scan = written
    for formats in (("ply",), ("parquet", "ply")):
        result = _child(out, scan, "full", *formats)
        lines = (result.stdout + result.stderr).strip().splitlines()
        assert len(lines) == 1 and lines[0].startswith("StageError: [write]"), lines[:5]
        assert "000001" in lines[0]
        assert not list(out.rglob("000001.*"))


def test_a_non_finite_value_is_never_written(tmp_path: Path) -> None:
    cloud, frame = _cloud_and_frame(tmp_path / "000000.bin")
    for column, value in (("xyz", np.nan), ("reflectance", np.inf), ("xyz", -np.inf), ("reflectance", np.nan)):
        values = getattr(cloud, column).copy()
        values.flat[7] = value
        bad = StitchedCloud(**{**cloud.__dict__, column: values})
        with pytest.raises(StageError, match="non-finite") as info:
            write.write_frame(bad, frame, tmp_path / "out", {})
        assert isinstance(info.value, write.NonFiniteOutputError)
        assert info.value.stage == "write" and "odometry/04/000000" in str(info.value)
        assert not list((tmp_path / "out").rglob("*.*"))


def test_float64_values_beyond_float32s_range_are_refused_not_written_as_infinite(tmp_path: Path) -> None:
    cloud, frame = _cloud_and_frame(tmp_path / "000000.bin")
    for column in ("xyz", "reflectance"):
        values = getattr(cloud, column).astype(np.float64)
        values.flat[5] = 1e39  # finite in float64; the check passed it and every format held inf
        bad = StitchedCloud(**{**cloud.__dict__, column: values})
        with pytest.raises(write.NonFiniteOutputError, match=r"1 of \d+ output points have non-finite values in "
                                                             r"float32 \(first at row \d+"):
            write.write_frame(bad, frame, tmp_path / "out", {}, formats=("parquet", "ply", "kitti"))
        assert not list((tmp_path / "out").rglob("*.*"))


def test_a_cloud_of_wrong_shapes_or_negative_parents_is_never_written(tmp_path: Path) -> None:
    cloud, frame = _cloud_and_frame(tmp_path / "000000.bin")
    four_columns = StitchedCloud(**{**cloud.__dict__, "xyz": np.c_[cloud.xyz, cloud.reflectance]})
    with pytest.raises(StageError, match=r"\[write\] .*xyz \(Q, 3\).*got xyz \(\d+, 4\)"):
        write.write_frame(four_columns, frame, tmp_path / "out", {})
    parents = cloud.parent.copy()
    parents[3] = -1
    with pytest.raises(StageError, match="negative index"):
        write.write_frame(StitchedCloud(**{**cloud.__dict__, "parent": parents}), frame, tmp_path / "out", {})
    parents[3] = len(frame.points)  # written as it was (an IndexError when load had dropped points)
    with pytest.raises(StageError, match=rf"parent column holds {len(frame.points)}, beyond the frame's "
                                         rf"{len(frame.points)} points"):
        write.write_frame(StitchedCloud(**{**cloud.__dict__, "parent": parents}), frame, tmp_path / "out", {})
    assert not list((tmp_path / "out").rglob("*.*"))


def test_a_cloud_of_wrong_column_types_is_never_written(tmp_path: Path) -> None:
    cloud, frame = _cloud_and_frame(tmp_path / "000000.bin")
    flags = cloud.generated.astype(np.int64) * 7  # written as 0/7 into a column of 0 or 1 (a trial)
    with pytest.raises(StageError, match=r"\[write\] .*generated and ground of bool.*got generated int64"):
        write.write_frame(StitchedCloud(**{**cloud.__dict__, "generated": flags}), frame, tmp_path / "out", {})
    as_list = StitchedCloud(**{**cloud.__dict__, "xyz": cloud.xyz.tolist()})  # an AttributeError before
    with pytest.raises(StageError, match=r"\[write\] .*numpy arrays.*got xyz list"):
        write.write_ply(as_list, tmp_path / "out" / "a.ply")
    assert not list((tmp_path / "out").rglob("*.*"))


def test_each_file_records_its_scan_and_a_changed_scan_is_stale(written: tuple[Path, Path]) -> None:
    out, scan = written
    for formats in (("parquet", "ply"), ("ply",)):
        paths = write.output_paths(out, "odometry", "04", 0, formats)
        assert write.stored_source(paths) == source_fingerprint(scan)
        assert not write.source_changed(paths, source_fingerprint(scan))
        assert write.source_changed(paths, source_fingerprint(Path(__file__)))
    cloud, frame = _cloud_and_frame(scan, n=400)  # rewritten: a different size
    assert write.source_changed(write.output_paths(out, "odometry", "04", 0), source_fingerprint(scan))
    unknown = write.write_frame(cloud, frame.with_(source=""), out / "other", {})
    assert write.stored_source(unknown) is None and write.source_changed(unknown, source_fingerprint(scan))


def test_files_are_written_with_the_modes_of_ordinary_files(written: tuple[Path, Path]) -> None:
    out, _ = written
    umask = os.umask(0)
    os.umask(umask)
    for path in write.output_paths(out, "odometry", "04", 0).values():
        assert path.stat().st_mode & 0o777 == 0o666 & ~umask


def test_every_format_records_the_frame_even_from_a_deep_source_path(tmp_path: Path) -> None:
    deep = tmp_path.joinpath(*["d" * 200] * 12)  # a scan path of about 2,500 characters
    deep.mkdir(parents=True)
    cloud, frame = _cloud_and_frame(deep / "000000.bin")
    out = tmp_path / "out"
    metadata = {"config_hash": "c1", "model_checksum": "m1", "run_id": "r1"}
    paths = write.write_frame(cloud, frame, out, metadata, formats=("parquet", "ply", "kitti"))
    for name, path in paths.items():  # a header past 4 KiB (the record holds the path twice) reads whole
        record = write.stored_record({name: path})
        assert {key: record[key] for key in metadata} == metadata and record["points"] == str(len(cloud))
        assert record["source"] == frame.source
        assert write.is_complete({name: path})


@pytest.mark.parametrize("fmt", ["ply", "kitti"])
def test_info_totals_a_folder_written_without_parquet(tmp_path: Path, fmt: str) -> None:
    cloud, frame = _cloud_and_frame(tmp_path / "000000.bin")
    out = tmp_path / "out"
    write.write_frame(cloud, frame, out, {"config_hash": "c1", "model_checksum": "m1"}, formats=(fmt,))
    info = folder_info(out)
    assert (info["read_from"], info["frames"], info["points"]) == (fmt, 1, len(cloud))
    assert info["sequences"][0]["configs"] == {"c1": 1} and info["sequences"][0]["sequence"] == "04"


def test_info_totals_frames_whatever_formats_hold_them(tmp_path: Path) -> None:
    out = tmp_path / "out"
    for index, formats in ((0, ("parquet", "ply")), (1, ("kitti",)), (2, ("ply",))):
        cloud, frame = _cloud_and_frame(tmp_path / f"{index:06d}.bin", n=500 + index)
        write.write_frame(cloud, dataclasses.replace(frame, index=index), out, {"config_hash": "c1"}, formats=formats)
    # once the folder held a Parquet file, frames in the KITTI mirror or PLY alone went uncounted (a new-user trial)
    info = folder_info(out)
    assert (info["frames"], info["points"]) == (3, 500 + 501 + 502) and info["read_from"] == "parquet+ply+kitti"
    assert ("counted from the Parquet, PLY and KITTI sidecar files: some frames have no readable Parquet file"
            in format_info(info))


def test_a_mirrored_frame_being_replaced_is_incomplete_until_its_new_scan_is_in_place(tmp_path: Path) -> None:
    from stages import write_kitti
    from stages.temporaries import replace_atomically

    # the new sidecar went in before the new scan: a process killed between the two left the old
    # scan beside the new record, complete to the next run whenever the point counts matched (a review)
    cloud, frame = _cloud_and_frame(tmp_path / "000000.bin")
    scan = write.write_frame(cloud, frame, tmp_path / "out", {"config_hash": "c1"}, formats=("kitti",))["kitti"]
    moved = dataclasses.replace(cloud, xyz=cloud.xyz + 1)  # as many points, other positions

    class Killed(BaseException):
        pass

    def killed_at_the_scan(path: Path, write_file) -> None:
        if path == scan:
            raise Killed
        replace_atomically(path, write_file, tmp_path / "out" / write.TEMPORARY_DIR)

    with pytest.raises(Killed):
        write_kitti.write_kitti(moved, frame, scan, killed_at_the_scan, {"config_hash": "c2"})
    assert write_kitti.stored_record(scan)["config_hash"] == "c2"  # the new sidecar is in place
    assert not write_kitti.is_complete(scan)


def test_a_scan_with_a_long_name_is_mirrored_its_temporary_name_within_the_limit(tmp_path: Path) -> None:
    from stages import temporaries

    # the temporary carried the whole final name: a 240-byte scan name made it too long, and the
    # frame failed its write ("File name too long") after the network had run
    name = "s" * 230 + "_000009.bin"
    source = tmp_path / "scans" / name
    source.parent.mkdir()
    source.write_bytes(b"\0" * 16)
    cloud = StitchedCloud(xyz=np.ones((5, 3), np.float32), reflectance=np.zeros(5, np.float32),
                          generated=np.zeros(5, bool), ground=np.zeros(5, bool), parent=np.arange(5))
    frame = Frame(points=np.zeros((5, 4), np.float32), dataset="bin", sequence="scans", index=9, source=str(source))
    paths = write.write_frame(cloud, frame, tmp_path / "out", {}, formats=("kitti",))
    assert paths["kitti"].name == name and len(np.fromfile(paths["kitti"], np.float32)) == 20
    temporary = temporaries.temporary_name(name)
    assert len(temporary.encode()) <= temporaries.NAME_MAX_BYTES and temporary.endswith(".bin.part")
    assert temporaries.is_stale(tmp_path / temporary.replace(f".{os.getpid()}@", ".999999999@", 1))
    assert temporaries.temporary_name("000009.bin").endswith("~000009.bin.part")  # short names kept whole


def test_a_file_is_on_disk_before_its_name_and_its_rename_after(tmp_path: Path,
                                                                 monkeypatch: pytest.MonkeyPatch) -> None:
    from stages import temporaries

    # renamed without fsync, a power loss could leave an empty or partial file under its final name
    events: list[str] = []
    real_fsync, real_replace = os.fsync, os.replace
    monkeypatch.setattr(os, "fsync", lambda fd: events.append(f"fsync {Path(os.readlink(f'/proc/self/fd/{fd}')).name}")
                        or real_fsync(fd))
    monkeypatch.setattr(os, "replace", lambda a, b: events.append("replace") or real_replace(a, b))
    final = tmp_path / "data" / "000000.parquet"
    temporaries.replace_atomically(final, lambda temporary: Path(temporary).write_bytes(b"x" * 100))
    assert final.read_bytes() == b"x" * 100
    assert len(events) == 3 and events[0].startswith("fsync .") and events[0].endswith("000000.parquet.part")
    assert events[1:] == ["replace", "fsync data"]
