"""Everything a run checks before it starts: paths made absolute, the frames found, the model loaded,
the cluster settings and the environment validated. A failure here is a `ConfigError` (exit status
2), and nothing has been written."""

from __future__ import annotations

import importlib.util
import os
import sys
import tempfile
import uuid
from collections import Counter
from pathlib import Path

from stages import load, upsample, write, write_kitti
from stages.errors import StageError
from stages.temporaries import NAME_MAX_BYTES, TEMPORARY_DIR, file_in_the_way

from .config import ConfigError, PipelineConfig, absolute
from .output_lock import LOCK_NAME
from .info import legacy_points_folders


def resolve_paths(config: PipelineConfig) -> PipelineConfig:
    """The configuration with `input.path`, `output.dir` (its leading `..` folded: `absolute`) and
    `upsample.weights` made absolute:
    workers of a cluster started in another folder read and write the same files as this process.
    Weights that are a shipped file, by name or by path, are named by their shipped name, and
    other weights by their absolute path: the same file gives the same `output_hash` however it
    was named, so a rerun from another folder does not redo finished frames."""
    from cadpu.weights import portable_name

    updates = {"output": config.output.model_copy(update={"dir": absolute(config.output.dir)}),
               "upsample": config.upsample.model_copy(update={"weights": portable_name(config.upsample.weights)})}
    if config.input.path is not None:
        # not folded: the frames' files record their scans' paths as made from it, and finished
        # frames of earlier runs are compared with them as text
        updates["input"] = config.input.model_copy(update={"path": Path(config.input.path).expanduser().absolute()})
    return config.model_copy(update=updates)


def check_environment(config: PipelineConfig) -> None:
    """What the configuration needs of this machine and of the cluster settings.

    Raises:
        ConfigError: CUDA asked for but absent, the optional Patchwork++ or Open3D package missing
            for the ground method that needs it, a scheduler address that is not one, LocalCluster
            settings given with a scheduler, or a memory limit Dask cannot read.
    """
    device = config.upsample.device
    if device.startswith("cuda"):
        import torch

        if not torch.cuda.is_available():
            raise ConfigError(f"upsample.device: {device!r} asked for, but torch finds no CUDA device here "
                              "(use 'auto' or 'cpu')")
    if config.ground.method == "patchworkpp" and not installed("pypatchworkpp"):
        raise ConfigError("ground.method: 'patchworkpp' needs the optional package pypatchworkpp "
                          '(pip install "kitti-pu[patchwork]")')
    if config.ground.method == "ransac" and not installed("open3d"):
        raise ConfigError("ground.method: 'ransac' needs Open3D, the optional open3d extra "
                          '(pip install "kitti-pu[open3d]")')
    dask_section = config.dask
    if dask_section.scheduler:
        from distributed.comm import parse_address

        try:
            protocol, location = parse_address(dask_section.scheduler, strict=True)
        except ValueError as error:
            raise ConfigError(f"dask.scheduler: {dask_section.scheduler!r} is not a Dask scheduler address "
                              f"such as tcp://host:8786 ({error})") from None
        if not location:
            raise ConfigError(f"dask.scheduler: {dask_section.scheduler!r} names no host")
        if protocol not in SCHEDULER_PROTOCOLS:
            raise ConfigError(f"dask.scheduler: {dask_section.scheduler!r}: the {protocol}:// protocol is not one "
                              f"this tool connects with ({', '.join(p + '://' for p in SCHEDULER_PROTOCOLS)})")
        if location.rpartition(":")[2] in ("", location) or not location.rpartition(":")[2].isdigit():
            raise ConfigError(f"dask.scheduler: {dask_section.scheduler!r} names no port (e.g. tcp://host:8786)")
        local_only = {"n_workers": dask_section.n_workers, "threads_per_worker": dask_section.threads_per_worker,
                      "memory_limit": None if dask_section.memory_limit == "auto" else dask_section.memory_limit,
                      "dashboard": dask_section.dashboard or None}
        for key, value in local_only.items():
            if value is not None:
                # named as typed where the option gives it: the user typed --workers (a trial)
                option = " (--workers)" if key == "n_workers" else ""
                raise ConfigError(f"dask.{key}{option}: sets the tool's own LocalCluster; an existing scheduler "
                                  "(dask.scheduler, --scheduler) keeps the workers it has, with their own settings")
    if dask_section.memory_limit != "auto":
        limit = worker_memory_bytes(dask_section.memory_limit)
        if limit < MIN_WORKER_MEMORY:
            raise ConfigError(f"dask.memory_limit: {dask_section.memory_limit!r} ({limit / 1e9:.2f} GB) is below the "
                              f"{MIN_WORKER_MEMORY / 1e9:.2f} GB a worker needs (its frames peak at about "
                              "0.75 GB, and Dask pauses a worker at 80% of its limit)")


def worker_memory_bytes(limit: str | int | float) -> int:
    """The bytes a `dask.memory_limit` gives each worker, read as Dask reads it: a share of the
    machine's memory for a number up to 1 (also written as a string, "0.5"), else a number of
    bytes or a size ("4GiB"). ConfigError for anything else."""
    from dask.utils import parse_bytes

    try:
        number = None if isinstance(limit, bool) else float(limit)
    except (TypeError, ValueError):
        number = None  # a size such as "4GiB", or not a limit
    try:
        if number is not None and 0 < number <= 1:
            import psutil

            return int(number * psutil.virtual_memory().total)
        return int(number) if number is not None else int(parse_bytes(limit))
    except (ValueError, TypeError):
        raise ConfigError(f"dask.memory_limit: {limit!r} is not 'auto', a size such as '4GiB', a number of "
                          "bytes, nor a share of the machine's memory such as 0.5") from None


#: Protocols of a `dask.scheduler` address the tool connects with (TLS needs certificates it is not
#: given; inproc is one process's own).
SCHEDULER_PROTOCOLS = ("tcp", "ws", "ucx")

#: The smallest `dask.memory_limit` accepted, bytes: a worker's memory peaks at about 0.75 GB over a
#: run (`python bench/memory.py`, docs/speed.md), and Dask pauses a worker at 80% of its limit
#: (0.75 / 0.8 = 0.94 GB), where the run would wait for ever (500 MiB did) or the worker die mid-task.
MIN_WORKER_MEMORY = 950_000_000


def installed(module: str) -> bool:
    """Whether `module` can be imported here, without importing it."""
    try:
        return importlib.util.find_spec(module) is not None
    except (ImportError, ValueError):  # a parent package that fails, or a module set to None
        return False


def check_weights(config: PipelineConfig) -> str:
    """Load the model once in this process to fail fast on a missing or corrupt weights file, or a
    ratio the weights cannot make.

    Returns:
        The weight file's sha256.

    Raises:
        ConfigError naming the file or the ratio, or `tile.patch_size` when the model cannot
        upsample patches of that size at that ratio (`cadpu.inference.Upsampler.check_patch_points`).
    """
    from cadpu.weights import WeightsError

    try:
        model = upsample.model(config.upsample)
    except WeightsError as error:
        raise ConfigError(f"upsample.weights: {error}") from None
    except ValueError as error:  # a ratio the weights cannot make
        raise ConfigError(f"upsample.ratio: {error}" if "ratio" in str(error) else f"upsample: {error}") from None
    runs = _engine_that_runs(config)
    if config.upsample.engine not in ("auto", runs):  # its packages are missing: said once, here
        from cadpu.engines import REQUIRES

        needs = " and ".join(REQUIRES.get(config.upsample.engine, ()))
        print(f"kitti-pu: warning: upsample.engine: {config.upsample.engine} needs {needs or 'packages'} "
              f"(pip install 'kitti-pu[engines]'); torch {runs} runs instead", file=sys.stderr)
    check_patch_points = getattr(model, "check_patch_points", None)  # a baseline has no limits
    if check_patch_points is not None:
        try:
            check_patch_points(config.tile.patch_size)
        except ValueError as error:
            raise ConfigError(f"tile.patch_size: {config.tile.patch_size} with upsample.ratio "
                              f"{config.upsample.ratio} and {config.upsample.weights}: "
                              f"{str(error).removeprefix('upsample_patches: ')}") from None
    return model.checksum  # type: ignore[attr-defined]


def _engine_that_runs(config: PipelineConfig) -> str:
    """The engine this process's model of `config` runs (the one named, or eager where its packages
    are missing); the model is built once per process (`stages.upsample.model`)."""
    return getattr(upsample.model(config.upsample), "engine", config.upsample.engine)


def with_engine_that_runs(config: PipelineConfig) -> PipelineConfig:
    """`config` with `upsample.engine` the engine that runs here: torch eager where the one named
    lacks its packages (`check_weights` warned of it). So the frames' records, the output hash
    and the summary name what made the points: frames made by the fallback were recorded under
    the engine asked for, and skipped as its frames once it was installed."""
    runs = _engine_that_runs(config)
    if config.upsample.engine in ("auto", runs):
        return config
    return config.model_copy(update={"upsample": config.upsample.model_copy(update={"engine": runs})})


def discover_frames(config: PipelineConfig) -> list[load.FrameRef]:
    """The frames the configuration selects; ConfigError when the input is missing or empty."""
    section = config.input
    if section.path is None:
        raise ConfigError("input.path: no input given (a KITTI raw/odometry folder or a folder of .bin)")
    if not Path(section.path).exists():
        raise ConfigError(f"input.path: {section.path} does not exist")
    try:
        refs = load.discover(section.path, kind=section.kind, sequences=section.sequences,
                             frames=section.frame_range(), exclude=write.data_folders(config.output.dir))
    except StageError as error:
        raise ConfigError(f"input.path: {error}") from None
    if not refs:
        raise ConfigError(f"input.path: no frames found under {section.path} (kind {section.kind})")
    return refs


def metadata_files(ref: load.FrameRef) -> list[Path]:
    """The files besides the scan that loading a frame of its layout reads (`stages.load.run`):
    a raw drive's calibration and OXTS timestamps, an odometry sequence's calib.txt and times.txt;
    none for a plain .bin folder."""
    if ref.dataset == "raw":
        date_dir = Path(ref.base, ref.date)
        return [*(date_dir / f"calib_{name}.txt" for name in ("cam_to_cam", "imu_to_velo", "velo_to_cam")),
                date_dir / ref.sequence / "oxts" / "timestamps.txt"]
    if ref.dataset == "odometry":
        sequence_dir = Path(ref.base, "sequences", ref.sequence)
        return [sequence_dir / "calib.txt", sequence_dir / "times.txt"]
    return []


def missing_metadata(refs: list[load.FrameRef]) -> list[str]:
    """One line per selected drive or sequence whose metadata files (`metadata_files`) are not all
    there, or whose timestamps file (the last of them) has no line for some of its frames: those
    frames would fail at load, naming the file, while other drives' frames are done; or whose
    poses file has no line for some frames: those would be done without a pose (`--dry-run`
    prints these lines first)."""
    frames = Counter((ref.dataset, ref.sequence) for ref in refs)
    last = {}
    for ref in refs:
        key = (ref.dataset, ref.sequence)
        last[key] = max(last.get(key, ref), ref, key=lambda r: r.index)
    lines = []
    for key, ref in last.items():
        files = metadata_files(ref)
        missing = [path for path in files if not path.is_file()]
        count = frames[key]
        if missing:
            lines.append(f"{ref.dataset}/{ref.sequence}: {', '.join(map(str, missing))} missing: its {count} "
                         f"frame{'s' if count != 1 else ''} would fail ({load.MISSING_METADATA_HINT})")
        else:
            for per_frame in _per_frame_files(ref, files):
                entries = load.frame_lines(per_frame)
                if entries > ref.index:
                    continue
                beyond = sorted(r.index for r in refs if (r.dataset, r.sequence) == key and r.index >= entries)
                # a frame without its timestamp fails; one without its pose is done with the pose
                # unknown (a note), and redone once the poses file has it (`pipeline.resume`)
                outcome = (f"would fail ({load.MISSING_METADATA_HINT})" if per_frame == files[-1] else
                           f"would be done without a pose, and redone once the file has "
                           f"{'its' if len(beyond) == 1 else 'theirs'}")
                held = (f"has {entries} line{'s' if entries != 1 else ''}, one a frame from frame 0" if entries
                        else "has no line it can read")
                which = (f"frame {beyond[0]}" if len(beyond) == 1 else
                         f"its {len(beyond)} frames from frame {beyond[0]} on")
                lines.append(f"{ref.dataset}/{ref.sequence}: {per_frame} {held}: {which} {outcome}")
                break
    return lines


def _per_frame_files(ref: load.FrameRef, files: list[Path]) -> list[Path]:
    """The files of a layout that hold a line per frame: the timestamps (the last of
    `metadata_files`), and an odometry sequence's poses when it has them."""
    per_frame = files[-1:]
    poses = load.odometry_poses_file(Path(ref.base), ref.sequence) if ref.dataset == "odometry" else None
    if poses is not None:
        per_frame.append(poses)
    return per_frame


def check_writable(out_dir: Path) -> None:
    """Create `out_dir` if needed and check a file can be written in it (ConfigError otherwise)."""
    try:
        out_dir.mkdir(parents=True, exist_ok=True)
        probe = out_dir / f".write-test-{uuid.uuid4().hex}"
        probe.touch()
        probe.unlink()
    except OSError as error:
        raise ConfigError(f"output.dir: {out_dir} is not writable ({error.strerror or error})") from None


def check_output_layout(out_dir: Path) -> None:
    """ConfigError when `out_dir` holds folders of the earlier `points/dataset=.../sequence=...`
    layout (readers of `OUT/points` would read their frames beside the new ones), or when one of
    the places a run writes is of the wrong kind: its folder of temporaries (`OUT/.tmp`, where every
    file is written before it is renamed into place) or a data folder that is a file (every frame
    failed at its write after the network had run), or its lock that is a folder (a traceback, exit
    1: a hostile-input trial). A summary or run record that cannot be written is said at the run's
    end (exit 3): its frames are written by then."""
    folders = {TEMPORARY_DIR: "where files are written before they are renamed into place",
               **{name: "a data folder" for name in write.DATA_FOLDERS.values()}}
    for name, role in folders.items():
        place = out_dir / name
        if (place.exists() or place.is_symlink()) and not place.is_dir():
            raise ConfigError(f"output.dir: {place}, {role}, is not a folder: remove it, or write elsewhere")
    if (out_dir / LOCK_NAME).is_dir():
        raise ConfigError(f"output.dir: {out_dir / LOCK_NAME}, the lock a run holds, is a folder: remove it, or "
                          "write elsewhere")
    legacy = legacy_points_folders(out_dir)
    if legacy:
        raise ConfigError(f"output.dir: {legacy[0]} is in the earlier points/dataset=.../sequence=... "
                          "layout; readers of points/ would read it beside the new files: move or "
                          "remove it, or write elsewhere")


def check_output_names(config: PipelineConfig, refs: list[load.FrameRef]) -> None:
    """ConfigError when a frame's output file would have a name, or lie in a folder named, longer
    than a file system takes (`NAME_MAX_BYTES`): a plain folder's name with its hash suffix could
    pass 255 bytes, and the run then crashed at its planning with "File name too long" (exit 1,
    after --dry-run passed: a hostile-input trial). Checked on the first frame of each sequence
    (the folder names) and on every frame's mirrored file name (an input's own name)."""
    out_dir = Path(config.output.dir)
    formats = tuple(config.output.formats)
    first_of_sequence = {(ref.dataset, ref.sequence): ref for ref in reversed(refs)}
    for ref in first_of_sequence.values():
        for path in write.output_paths(out_dir, ref.dataset, ref.sequence, ref.index, formats, ref.source).values():
            long = next((part for part in path.relative_to(out_dir).parts
                         if len(part.encode("utf-8", "surrogateescape")) > NAME_MAX_BYTES), None)
            if long is not None:
                raise ConfigError(f"output.dir: the output of {ref.source} would lie under a name of "
                                  f"{len(long.encode('utf-8', 'surrogateescape'))} bytes ({long[:40]}...), more than "
                                  f"the {NAME_MAX_BYTES} a file system takes; give its folder a shorter name")


def preflight(config: PipelineConfig) -> tuple[PipelineConfig, list[load.FrameRef], str]:
    """All checks that leave nothing written, in the order a user fixes them (`kitti-pu run --dry-run`
    runs these; `run_pipeline` then checks that the output folder is writable).

    Returns:
        (the configuration with absolute paths, the selected frames, the model's sha256).
    """
    config = resolve_paths(config)
    check_environment(config)
    refs = discover_frames(config)
    for line in load.odometry_folders_read_as_bin(refs):
        print(f"kitti-pu: warning: {line}", file=sys.stderr)
    checksum = check_weights(config)
    config = with_engine_that_runs(config)
    check_output_target(Path(config.output.dir))
    check_output_layout(Path(config.output.dir))
    check_output_names(config, refs)
    check_mirror_metadata(config, refs)
    return config, refs, checksum


def check_mirror_metadata(config: PipelineConfig, refs: list[load.FrameRef]) -> None:
    """With the `kitti` format: refuse a run whose input shares a sequence name with frames the
    mirror holds from another input folder, when the two folders' calibration, times or poses
    differ (`stages.write_kitti.shared_metadata_conflict`): the run would rewrite the files those
    frames are read with. Raises ConfigError naming the folders."""
    if "kitti" not in config.output.formats:
        return
    out_dir = Path(config.output.dir)
    first: dict[tuple[str, str], load.FrameRef] = {}
    selected: dict[str, set[tuple[str, int]]] = {}
    for ref in refs:
        first.setdefault((ref.dataset, ref.sequence), ref)
        selected.setdefault(ref.dataset, set()).add((ref.sequence, ref.index))
    at_odds = write_kitti.inputs_at_odds([
        (dataset, sequence, ref.source, write_kitti.scan_path(out_dir, dataset, sequence, ref.index, ref.source))
        for (dataset, sequence), ref in first.items()])
    if at_odds:
        raise ConfigError(f"output.formats: kitti: {at_odds}")
    memo = write_kitti.ConflictMemo()  # a date's calibration checked once, each sidecar read once
    for (dataset, sequence), ref in first.items():
        scan = write_kitti.scan_path(out_dir, dataset, sequence, ref.index, ref.source)
        conflict = write_kitti.shared_metadata_conflict(dataset, sequence, ref.source, scan, selected[dataset], memo)
        if conflict:
            raise ConfigError(f"output.formats: kitti: {conflict}")


def check_output_target(out_dir: Path, option: str = "output.dir") -> None:
    """ConfigError naming `option` when `out_dir`, or the nearest part of it that exists, is not a
    folder (a file there) or nothing can be created in it (a read-only folder or file system):
    found leaving nothing behind (a probe folder made and removed), so `--dry-run` finds it as
    the run would."""
    blocking = file_in_the_way(out_dir)
    if blocking is not None:
        raise ConfigError(f"{option}: {out_dir} is not writable: {blocking} is a file, not a folder")
    existing = next((part for part in (out_dir, *out_dir.parents) if part.exists()), None)
    if existing is None:
        return
    try:
        os.rmdir(tempfile.mkdtemp(prefix=".kitti-pu-probe-", dir=existing))
    except OSError as error:
        raise ConfigError(f"{option}: {out_dir} is not writable: nothing can be created in {existing} "
                          f"(creating a folder there failed: {error.strerror or error})") from None
