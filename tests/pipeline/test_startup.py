"""What a run does to start and end quickly (issue 20): its LocalCluster started while the weights
load, when the run will surely use it; worker processes and the program ending without the
interpreter's teardown, with their output flushed and their exit status kept."""

from __future__ import annotations

import subprocess
import sys
import threading
from collections.abc import Callable
from pathlib import Path

import psutil
import pytest
from filelock import FileLock

from pipeline.config import ConfigError, PipelineConfig
from pipeline.runner import LOCK_NAME, needs_cluster, run_pipeline
from pipeline.preflight import discover_frames, resolve_paths
from stages import write

REPO = Path(__file__).resolve().parents[2]
ConfigFactory = Callable[..., PipelineConfig]


def _python(code: str, *args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-c", code, *args], capture_output=True, text=True, cwd=REPO, timeout=120)


def test_a_worker_process_ends_with_its_output_flushed_and_status_0_skipping_later_teardown() -> None:
    done = _python(
        "import atexit, sys\n"
        "from pipeline.cluster import exit_without_teardown\n"
        "atexit.register(lambda: print('an exit handler registered earlier ran'))\n"
        "exit_without_teardown()\n"
        "print('written, not flushed', end='')\n"
        "sys.exit(0)\n")
    assert done.returncode == 0, done.stderr
    assert done.stdout == "written, not flushed"  # flushed; the earlier handler never ran


@pytest.mark.parametrize("args, status, stream, text", [
    (["--version"], 0, "stdout", "kitti-pu "),
    (["run", "/no/such/folder", "--out", "/tmp/kitti-pu-never"], 2, "stderr", "does not exist"),
])
def test_the_program_keeps_its_status_output_and_exit_handlers(args: list[str], status: int, stream: str,
                                                               text: str) -> None:
    done = _python("import atexit\n"
                   "from pipeline.cli import app\n"
                   "atexit.register(lambda: print('exit handler ran'))\n"
                   "app()\n", *args)
    assert done.returncode == status, done.stderr
    assert text in getattr(done, stream) and done.stdout.rstrip().endswith("exit handler ran")


def test_the_program_called_not_standalone_returns_as_a_typer_app() -> None:
    done = _python("from pipeline.cli import app\n"
                   "try:\n"
                   "    app(['--version'], standalone_mode=False)\n"
                   "except SystemExit as stop:\n"
                   "    print('raised', stop.code)\n"
                   "print('still running')\n")
    assert done.returncode == 0 and done.stdout.rstrip().endswith("still running"), done.stderr


def _resolved(make_config: ConfigFactory, bin_folder: Path, out: Path, **overrides: object):
    config = resolve_paths(make_config(bin_folder, out, **overrides))
    return config, discover_frames(config)


def test_the_cluster_starts_early_only_when_the_run_will_use_it(bin_folder: Path, make_config: ConfigFactory,
                                                                tmp_path: Path) -> None:
    out = tmp_path / "out"
    config, refs = _resolved(make_config, bin_folder, out)
    assert needs_cluster(config, refs)  # nothing written yet
    formats = tuple(config.output.formats)
    for ref in refs:  # every output file present: the run may have nothing to do
        for path in write.output_paths(out, ref.dataset, ref.sequence, ref.index, formats, ref.source).values():
            path.parent.mkdir(parents=True, exist_ok=True)
            path.touch()
    assert not needs_cluster(config, refs)
    overwrite, _ = _resolved(make_config, bin_folder, out, **{"output.overwrite": True})
    assert needs_cluster(overwrite, refs)
    next(iter(write.output_paths(out, refs[0].dataset, refs[0].sequence, refs[0].index, formats,
                                 refs[0].source).values())).unlink()
    assert needs_cluster(config, refs)
    (out / LOCK_NAME).touch()  # a lock file left by an earlier run, not held: no obstacle
    assert needs_cluster(config, refs)
    with FileLock(out / LOCK_NAME):  # another run holds the folder: this one exits with status 4
        assert not needs_cluster(config, refs)
    scheduler, _ = _resolved(make_config, bin_folder, out, **{"dask.scheduler": "tcp://127.0.0.1:1",
                                                              "dask.n_workers": None})
    assert not needs_cluster(scheduler, refs)


def _worker_processes() -> set[int]:
    return {child.pid for child in psutil.Process().children(recursive=True)
            if any("spawn_main" in part for part in child.cmdline())}


def test_a_check_that_fails_after_the_cluster_started_leaves_no_worker_behind(
        bin_folder: Path, make_config: ConfigFactory, tmp_path: Path) -> None:
    before = _worker_processes()
    out = tmp_path / "out"
    with pytest.raises(ConfigError, match="nosuch"):  # the weights fail after discovery started the cluster
        run_pipeline(make_config(bin_folder, out, **{"upsample.weights": "nosuch"}), progress=False)
    assert not out.exists()
    starting = [thread for thread in threading.enumerate() if thread.name == "kitti-pu-cluster-start"]
    assert not starting  # the start was waited for, and its cluster closed:
    assert _worker_processes() <= before
