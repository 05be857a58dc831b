"""What a run does to end quickly (issue 20): the worker processes of the tool's own LocalCluster
and the program end without the interpreter's teardown, with their output flushed and their exit
status kept. (On an existing cluster, the workers are left alone: tests/pipeline/test_cluster.py.)"""

from __future__ import annotations

import os
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path

import pytest

from pipeline.cluster import open_client, plan_cluster
from pipeline.config import PipelineConfig

REPO = Path(__file__).resolve().parents[2]
ConfigFactory = Callable[..., PipelineConfig]


def _python(code: str, *args: str) -> subprocess.CompletedProcess:
    """Run `code` in a new interpreter with this checkout's packages first on the path."""
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, [str(REPO), os.environ.get("PYTHONPATH")]))}
    return subprocess.run([sys.executable, "-c", code, *args], capture_output=True, text=True, cwd=REPO, env=env,
                          timeout=120)


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


@pytest.mark.parametrize("args, status", [
    (["--version"], 0),
    (["config", "--set", "tile.overlap=nope"], 2),  # refused before the weights are loaded
    (["info", "no-such-output"], 2),
    (["run", "no-such-input", "--out", "no-such-output"], 2),  # cadpu.weights' path helpers loaded torch
])
def test_the_command_line_loads_torch_only_where_a_verb_needs_the_model(args: list[str], status: int) -> None:
    # cadpu.patches (imported by the stages) imported torch through cadpu.kernels: about 2 s before any verb ran
    done = _python("import sys\n"
                   "from pipeline.cli import app\n"
                   "try:\n"
                   "    code = app(sys.argv[1:], standalone_mode=False)\n"
                   "except SystemExit as stop:\n"
                   "    code = stop.code\n"
                   "print('exit', code or 0, 'torch loaded' if 'torch' in sys.modules else 'no torch')\n", *args)
    assert done.returncode == 0, done.stderr
    assert done.stdout.splitlines()[-1] == f"exit {status} no torch", done.stdout + done.stderr


def test_the_tools_own_cluster_lets_its_workers_end_fast(bin_folder: Path, make_config: ConfigFactory,
                                                        tmp_path: Path) -> None:
    config = make_config(bin_folder, tmp_path / "out")
    with open_client(config, plan_cluster(config)) as client:
        setups = client.run(lambda dask_worker: dask_worker.kitti_pu_setup)
    assert [setup["exit_fast"] for setup in setups.values()] == [True]
