"""pipeline.preflight through run_pipeline: bad weights, output folders, keys, inputs and ratios are
each a ConfigError naming the problem, before anything is written (a real LocalCluster is never
started for them)."""

from __future__ import annotations

import os
import shutil
import sys
from collections.abc import Callable
from pathlib import Path

import pytest

from pipeline.config import ConfigError, PipelineConfig, load_config
from pipeline.runner import run_pipeline

ConfigFactory = Callable[..., PipelineConfig]


def _files_under(folder: Path) -> list[Path]:
    return [path for path in folder.rglob("*") if path.is_file()] if folder.exists() else []


@pytest.mark.parametrize("damage", ["missing", "garbage", "wrong_checksum"])
def test_missing_or_corrupt_weights_are_a_config_error(
        damage: str, weights_file: Path, bin_folder: Path, make_config: ConfigFactory, tmp_path: Path) -> None:
    bad = tmp_path / "weights" / "model.pt"
    bad.parent.mkdir()
    if damage == "garbage":
        bad.write_bytes(b"not a torch file at all" * 10)
    elif damage == "wrong_checksum":
        shutil.copy(weights_file, bad)
        Path(f"{bad}.sha256").write_text("0" * 64 + "  model.pt\n")
    config = make_config(bin_folder, tmp_path / "out", **{"upsample.weights": str(bad)})
    with pytest.raises(ConfigError, match="upsample.weights") as info:
        run_pipeline(config, progress=False)
    assert str(bad) in str(info.value)
    assert _files_under(tmp_path / "out") == []


def test_unwritable_output_folder_is_a_config_error(
        bin_folder: Path, make_config: ConfigFactory, tmp_path: Path) -> None:
    locked = tmp_path / "locked"
    locked.mkdir()
    locked.chmod(0o500)
    try:
        if os.access(locked, os.W_OK):
            pytest.skip("running as a user who can write into a 0o500 folder (root)")
        config = make_config(bin_folder, locked / "out")
        with pytest.raises(ConfigError, match="output.dir") as info:
            run_pipeline(config, progress=False)
        assert str(locked / "out") in str(info.value)
    finally:
        locked.chmod(0o700)
    assert list(locked.iterdir()) == []


def test_output_folder_below_a_file_is_a_config_error(
        bin_folder: Path, make_config: ConfigFactory, tmp_path: Path) -> None:
    """The unwritable case that holds for root too: a path component is a regular file."""
    blocker = tmp_path / "not-a-folder"
    blocker.write_text("a file where the output folder should go")
    config = make_config(bin_folder, blocker / "out")
    with pytest.raises(ConfigError, match="output.dir") as info:
        run_pipeline(config, progress=False)
    assert str(blocker / "out") in str(info.value) and "not writable" in str(info.value)
    assert blocker.read_text() == "a file where the output folder should go"


def test_unknown_config_key_is_named(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match=r"upsample\.ratioo: unknown key"):
        load_config([], {"upsample.ratioo": 4})
    override = tmp_path / "bad.yaml"
    override.write_text("tile:\n  overlapp: 2.0\n")
    with pytest.raises(ConfigError, match=r"tile\.overlapp: unknown key") as info:
        load_config([override])
    assert str(override) in str(info.value)


def test_missing_input_folder_is_a_config_error(make_config: ConfigFactory, tmp_path: Path) -> None:
    config = make_config(tmp_path / "nowhere", tmp_path / "out")
    with pytest.raises(ConfigError, match="does not exist") as info:
        run_pipeline(config, progress=False)
    assert str(tmp_path / "nowhere") in str(info.value)
    assert not (tmp_path / "out").exists()


def test_a_ratio_the_weights_cannot_make_is_a_config_error(tmp_path, bin_folder, make_config) -> None:
    from pipeline.config import ConfigError
    from pipeline.runner import run_pipeline

    config = make_config(bin_folder, tmp_path / "out", **{"upsample.ratio": 8})
    with pytest.raises(ConfigError, match=r"upsample\.ratio: .*power"):
        run_pipeline(config, progress=False)


def test_an_output_folder_in_the_earlier_layout_is_refused_through_the_library_call(
        tmp_path: Path, bin_folder: Path, make_config: ConfigFactory) -> None:
    legacy = tmp_path / "out" / "points" / "dataset=bin" / "sequence=scans"
    legacy.mkdir(parents=True)
    (legacy / "000000.parquet").write_bytes(b"an earlier version's frame")
    config = make_config(bin_folder, tmp_path / "out")
    with pytest.raises(ConfigError, match=r"earlier points/dataset=\.\.\./sequence=\.\.\. layout") as info:
        run_pipeline(config, progress=False)
    assert str(tmp_path / "out" / "points" / "dataset=bin") in str(info.value)
    assert _files_under(tmp_path / "out") == [legacy / "000000.parquet"]


def test_a_temporaries_folder_that_is_a_file_is_refused_before_anything_runs(
        tmp_path: Path, bin_folder: Path, make_config: ConfigFactory) -> None:
    # every frame ran through the network, then failed at its write ("File exists"), exit 3
    from pipeline.config import ConfigError
    from pipeline.runner import run_pipeline

    blocker = tmp_path / "out" / ".tmp"
    blocker.parent.mkdir()
    blocker.write_text("not a folder")
    with pytest.raises(ConfigError, match=r"\.tmp, where files are written before they are renamed into place, "
                                          "is not a folder"):
        run_pipeline(make_config(bin_folder, tmp_path / "out"), progress=False)
    assert _files_under(tmp_path / "out") == [blocker]


@pytest.mark.parametrize("name, kind, message", [
    ("points", "file", "points, a data folder, is not a folder"),  # every frame failed at its write, exit 3
    (".kitti-pu.lock", "folder", ".kitti-pu.lock, the lock a run holds, is a folder"),  # a traceback, exit 1
])
def test_a_place_of_the_output_of_the_wrong_kind_is_refused_before_anything_runs(
        tmp_path: Path, bin_folder: Path, make_config: ConfigFactory, name: str, kind: str, message: str) -> None:
    from pipeline.config import ConfigError
    from pipeline.preflight import preflight

    # found after the network had run, or as a traceback (a hostile-input trial)
    blocker = tmp_path / "out" / name
    blocker.parent.mkdir()
    blocker.mkdir() if kind == "folder" else blocker.write_text("in the way")
    with pytest.raises(ConfigError, match=message):
        preflight(make_config(bin_folder, tmp_path / "out"))


def test_a_folder_whose_output_name_would_be_too_long_is_refused_before_anything_runs(
        tmp_path: Path, bin_folder: Path, make_config: ConfigFactory) -> None:
    from pipeline.config import ConfigError
    from pipeline.preflight import preflight

    # a 250-byte folder name took a hash suffix past 255 bytes: --dry-run passed and the run crashed
    # with "File name too long", exit 1 (a hostile-input trial)
    long = tmp_path / ("a" * 250)
    long.mkdir()
    for scan in sorted(bin_folder.glob("*.bin"))[:1]:
        (long / scan.name).write_bytes(scan.read_bytes())
    with pytest.raises(ConfigError, match=r"would lie under a name of \d+ bytes .* more than the 255 a file system"):
        preflight(make_config(long, tmp_path / "out"))


def test_the_ransac_ground_method_without_open3d_is_a_config_error_naming_the_extra(
        tmp_path: Path, bin_folder: Path, make_config: ConfigFactory, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setitem(sys.modules, "open3d", None)  # how Python marks a module that cannot be imported
    config = make_config(bin_folder, tmp_path / "out", **{"ground.method": "ransac"})
    with pytest.raises(ConfigError, match=r'ground\.method: .ransac. .*pip install "kitti-pu\[open3d\]"'):
        run_pipeline(config, progress=False)
    assert not (tmp_path / "out").exists()


def test_weights_are_named_one_way_whatever_the_folder_the_run_starts_in(tmp_path: Path,
                                                                         monkeypatch: pytest.MonkeyPatch) -> None:
    """A relative weights path is made absolute, as the input and output are, so workers started
    in another folder find it; a shipped file by its path is named as shipped. The output hash
    then does not change with how the same file was named (finished frames stay finished)."""
    from cadpu.weights import WEIGHTS_DIR
    from pipeline.preflight import resolve_paths

    (tmp_path / "w").mkdir()
    shutil.copy(WEIGHTS_DIR / "cadpu_r4_lidar.pt", tmp_path / "w" / "mine.pt")
    monkeypatch.chdir(tmp_path)

    def resolved(weights: str) -> PipelineConfig:
        return resolve_paths(load_config([], {"upsample.weights": weights}))

    mine = resolved("w/mine.pt")
    assert mine.upsample.weights == str(tmp_path / "w" / "mine.pt")
    assert mine.output_hash() == resolved(str(tmp_path / "w" / "mine.pt")).output_hash()
    default = resolve_paths(load_config([], {}))
    assert default.upsample.weights == "cadpu_r4_lidar_alpha1"
    assert default.output_hash() == load_config([], {}).output_hash()  # finished default runs stay finished
    for same in (str(WEIGHTS_DIR / "cadpu_r4_lidar_alpha1.pt"), "cadpu_r4_lidar_alpha1.pt"):
        assert resolved(same).upsample.weights == "cadpu_r4_lidar_alpha1"
        assert resolved(same).output_hash() == default.output_hash()


def test_a_relative_output_path_is_made_absolute_with_leading_dots_folded(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    from pipeline.preflight import resolve_paths

    # "../out" reached the summary and its messages as /a/b/../out (a cluster user's trial)
    (tmp_path / "a" / "b").mkdir(parents=True)
    (tmp_path / "a" / "link").symlink_to(tmp_path / "a" / "b")
    monkeypatch.chdir(tmp_path / "a" / "b")
    config = resolve_paths(load_config([], {"input.path": "../scans", "output.dir": "../../out"}))
    assert config.output.dir == tmp_path / "out"
    # the input as before: finished frames record their scans' paths made from it, compared as text
    assert config.input.path == tmp_path / "a" / "b" / ".." / "scans"
    # a ".." after a folder that may be a link is the file system's to follow: kept
    monkeypatch.chdir(tmp_path / "a")
    assert resolve_paths(load_config([], {"output.dir": "link/../out"})).output.dir == tmp_path / "a" / "link" / ".." / "out"


def test_frames_an_earlier_version_hashed_with_the_weights_as_given_stay_finished(
        bin_folder: Path, make_config: ConfigFactory, weights_file: Path, tmp_path: Path,
        monkeypatch: pytest.MonkeyPatch) -> None:
    """Before weights were made absolute, the hash held them as the user gave them (a relative
    path), and until this version it held their name: an upgrade must not redo those finished frames."""
    import pyarrow.parquet as pq

    from pipeline.preflight import resolve_paths

    shutil.copy(weights_file, tmp_path / "mine.pt")
    shutil.copy(weights_file.with_name(weights_file.name + ".sha256"), tmp_path / "mine.pt.sha256")
    monkeypatch.chdir(tmp_path)
    config = make_config(bin_folder, tmp_path / "out", upsample__weights="mine.pt", input__last_frame=0)
    assert run_pipeline(config, progress=False).count("done") == 1
    # a byte-identical copy of the weights at another path: the same model, the frame stays finished
    shutil.copy(tmp_path / "mine.pt", tmp_path / "copy.pt")
    shutil.copy(tmp_path / "mine.pt.sha256", tmp_path / "copy.pt.sha256")
    copied = make_config(bin_folder, tmp_path / "out", upsample__weights="copy.pt", input__last_frame=0)
    assert run_pipeline(copied, progress=False).count("skipped") == 1  # "replaced (config changed)", before
    # the frame as the earlier versions stored it: its record holds the hash of the weights as given
    parquet = next((tmp_path / "out" / "points").rglob("*.parquet"))
    table = pq.read_table(parquet)
    for earlier in (config.output_hash(legacy=True), resolve_paths(config).output_hash(legacy=True)):
        metadata = {**table.schema.metadata, b"config_hash": earlier.encode()}
        pq.write_table(table.replace_schema_metadata(metadata), parquet)
        rerun = run_pipeline(config, progress=False)
        assert rerun.count("skipped") == 1 and rerun.count("replaced") == 0


def test_a_memory_limit_is_read_as_dask_reads_it() -> None:
    import psutil

    from pipeline.preflight import check_environment, worker_memory_bytes

    total = psutil.virtual_memory().total
    assert worker_memory_bytes(0.5) == worker_memory_bytes("0.5") == int(0.5 * total)  # a share of memory
    assert worker_memory_bytes(2_000_000_000) == worker_memory_bytes("2GB") == 2_000_000_000  # bytes, a size
    # a share and a byte count were refused as "not a valid string"
    for limit in (2_000_000_000, 2.0e9):
        check_environment(load_config([], {"dask.memory_limit": limit}))


def test_an_engine_whose_packages_are_missing_is_said_once_in_one_line(capfd: pytest.CaptureFixture[str]) -> None:
    import importlib.util

    if importlib.util.find_spec("openvino") is not None:
        pytest.skip("openvino is installed")
    from pipeline.preflight import check_weights

    # a raw UserWarning with its source line, before, from this process and from every worker
    check_weights(load_config([], {"upsample.engine": "openvino"}))
    err = capfd.readouterr().err
    assert err.strip().splitlines() == ["kitti-pu: warning: upsample.engine: openvino needs openvino and onnx "
                                        "(pip install 'kitti-pu[engines]'); torch eager runs instead"], err


def test_an_engine_whose_packages_are_missing_is_recorded_as_the_eager_that_runs() -> None:
    import importlib.util

    if importlib.util.find_spec("openvino") is not None:
        pytest.skip("openvino is installed")
    from pipeline.preflight import with_engine_that_runs

    # the frames were hashed and recorded as openvino's though eager made them: eager's finished
    # frames were redone ("config changed"), and skipped as openvino's once it was installed
    asked = load_config([], {"upsample.engine": "openvino"})
    runs = with_engine_that_runs(asked)
    assert runs.upsample.engine == "eager"
    assert runs.output_hash() == load_config([], {}).output_hash() != asked.output_hash()
    default = load_config([], {})
    assert with_engine_that_runs(default) is default  # auto, and an engine that is installed, stay as they are
