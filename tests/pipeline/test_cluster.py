"""A run on an existing Dask cluster, the way a user with one would do it: a real `dask scheduler`
and two `dask worker` processes on 127.0.0.1, and the `kitti-pu` console command pointed at them
with `--scheduler tcp://127.0.0.1:PORT`."""

from __future__ import annotations

import contextlib
import json
import os
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import pyarrow.parquet as pq
import pytest
from distributed import Client, LocalCluster

from pipeline.cluster import (WorkerSetup, cluster_threads, local_cluster, open_client, plan_cluster,
                              share_threads_again, threads_on_each_worker, trim_allocator)
from pipeline.config import load_config
from stages import write

REPO = Path(__file__).resolve().parents[2]
BIN = Path(sys.executable).parent
DRIVE_NAME = "2011_09_26_drive_0001_sync"


def _free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as probe:
        probe.bind(("127.0.0.1", 0))
        return int(probe.getsockname()[1])


def _stop(process: subprocess.Popen) -> None:
    """SIGTERM (a nanny then stops its worker), SIGKILL when it does not exit within 15 s."""
    if process.poll() is None:
        process.terminate()
        try:
            process.wait(timeout=15)
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait(timeout=5)


def _logs(folder: Path) -> str:
    return "\n".join(f"--- {log.name}\n{log.read_text()[-3000:]}" for log in sorted(folder.glob("*.log")))


def _worker_command(address: str, logs: Path, name: str, *worker_args: str) -> list[str]:
    """`dask worker` of one thread for the scheduler at `address`, as the README starts one."""
    return [str(BIN / "dask"), "worker", address, "--nthreads", "1", "--no-dashboard", "--host", "127.0.0.1",
            "--name", name, "--local-directory", str(logs / name), *worker_args]


def _start(command: list[str], log: Path, cwd: Path) -> subprocess.Popen:
    """`command` started in `cwd` with this checkout importable, its output to `log`."""
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, [str(REPO), os.environ.get("PYTHONPATH")]))}
    return subprocess.Popen(command, stdout=log.open("w"), stderr=subprocess.STDOUT, env=env, cwd=cwd)


@contextlib.contextmanager
def _external_cluster(tmp_path: Path, workers: int = 2, *worker_args: str,
                      running: bool = True) -> Iterator[tuple[str, Path]]:
    """A scheduler and `workers` single-threaded workers (started with `worker_args` too), as the
    README starts them; yields (address, folder of their logs) once the workers have joined
    (and, with `running`, run: Dask's own wait counts no paused worker)."""
    if not (BIN / "dask").is_file():
        pytest.skip(f"no `dask` console script beside {sys.executable}")
    logs = tmp_path / "cluster"
    logs.mkdir()
    address = f"tcp://127.0.0.1:{_free_port()}"
    commands = [
        [str(BIN / "dask"), "scheduler", "--host", "127.0.0.1", "--port", address.rsplit(":", 1)[1],
         "--no-dashboard"],
        *[_worker_command(address, logs, f"w{i}", *worker_args) for i in range(workers)],
    ]
    processes: list[subprocess.Popen] = []
    try:
        for index, command in enumerate(commands):
            processes.append(_start(command, logs / f"{index}-{command[1]}.log", tmp_path))
        with Client(address, timeout="60s") as client:
            try:
                if workers and running:
                    client.wait_for_workers(workers, timeout=90)
                elif workers:
                    deadline = time.monotonic() + 90
                    while len(client.scheduler_info()["workers"]) < workers:
                        if time.monotonic() > deadline:
                            raise TimeoutError
                        time.sleep(0.2)
            except TimeoutError:
                pytest.fail(f"{workers} workers did not join {address}\n{_logs(logs)}")
        yield address, logs
    finally:
        for process in reversed(processes):  # workers first, then the scheduler
            _stop(process)


@pytest.fixture()
def cluster(tmp_path: Path) -> Iterator[tuple[str, Path]]:
    """A scheduler and two single-threaded workers; yields (address, folder of their logs)."""
    with _external_cluster(tmp_path) as started:
        yield started


def test_workers_with_too_little_memory_are_refused_before_any_frame(raw_drive_template: Path, weights_file: Path,
                                                                     tmp_path: Path) -> None:
    # Dask pauses a 500 MB worker mid-frame: the run waited for ever, printing nothing
    with _external_cluster(tmp_path, 1, "--memory-limit", "500MB") as (address, _):
        command = [str(BIN / "kitti-pu"), "run", str(raw_drive_template), "--out", str(tmp_path / "out"),
                   "--scheduler", address, "--weights", str(weights_file), "--no-progress"]
        done = subprocess.run(command, capture_output=True, text=True, timeout=120, cwd=tmp_path)
        # and --dry-run, which "runs the same checks", found nothing: it never contacted the cluster (a trial)
        dry = subprocess.run([*command, "--dry-run"], capture_output=True, text=True, timeout=120, cwd=tmp_path)
    for result in (done, dry):
        assert result.returncode == 2, result.stdout + result.stderr
        assert "with a memory limit below the 0.95 GB a worker needs" in result.stderr and "(0.50 GB)" in result.stderr


def test_a_cluster_without_workers_stops_the_run_after_the_timeout_and_frees_the_folder(
        raw_drive_template: Path, weights_file: Path, tmp_path: Path) -> None:
    # with no worker (none joined, or all lost) the run waited for ever, holding the output's lock
    with _external_cluster(tmp_path, 0) as (address, _):
        started = time.monotonic()
        done = subprocess.run([str(BIN / "kitti-pu"), "run", str(raw_drive_template), "--out", str(tmp_path / "out"),
                               "--scheduler", address, "--weights", str(weights_file), "--no-progress",
                               "--set", "dask.no_workers_timeout=3"],
                              capture_output=True, text=True, timeout=120, cwd=tmp_path)
        took = time.monotonic() - started
    assert done.returncode == 3, done.stdout + done.stderr
    # it said "no running worker ...: no workers", the same twice (a trial)
    assert "the cluster has had no running worker for 3 s (dask.no_workers_timeout): no worker joined" in done.stderr
    summary = json.loads((tmp_path / "out" / "summary.json").read_text())
    assert summary["workers"] == 0  # it said 2, the LocalCluster's count, before
    assert [frame["status"] for frame in summary["frames"]] == ["interrupted", "interrupted"]
    assert took < 60
    assert not (tmp_path / "out" / ".kitti-pu.lock").exists() or _lock_is_free(tmp_path / "out" / ".kitti-pu.lock")


def test_a_cluster_whose_workers_are_all_paused_stops_the_run_after_the_timeout(
        raw_drive_template: Path, weights_file: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    # a worker paused for memory (as one too small for a frame that joins after the run's check of
    # the workers is, a new-user trial) counted as a worker: the run waited for ever holding the
    # output's lock. This worker's memory limit passes the check, and Dask's own memory monitor
    # pauses it at once and keeps it paused (its pause threshold at 1% of the limit).
    monkeypatch.setenv("DASK_DISTRIBUTED__WORKER__MEMORY__PAUSE", "0.01")
    with _external_cluster(tmp_path, 1, "--memory-limit", "4GB", running=False) as (address, _):
        monkeypatch.delenv("DASK_DISTRIBUTED__WORKER__MEMORY__PAUSE")
        done = subprocess.run([str(BIN / "kitti-pu"), "run", str(raw_drive_template), "--out", str(tmp_path / "out"),
                               "--scheduler", address, "--weights", str(weights_file), "--no-progress",
                               "--set", "dask.no_workers_timeout=3"],
                              capture_output=True, text=True, timeout=100, cwd=tmp_path)
    assert done.returncode == 3, done.stdout + done.stderr
    assert "no running worker for 3 s (dask.no_workers_timeout): its 1 worker(s) paused" in done.stderr
    summary = json.loads((tmp_path / "out" / "summary.json").read_text())
    assert {frame["status"] for frame in summary["frames"]} == {"interrupted"}


def _lock_is_free(path: Path) -> bool:
    from filelock import FileLock, Timeout

    try:
        with FileLock(path, timeout=0):
            return True
    except Timeout:
        return False


def _models_per_worker(address: str) -> dict[str, int]:
    """How many CAD-PU models each worker process holds (stages.upsample keeps one per model key)."""

    def count() -> int:
        from stages import upsample

        return len(upsample._MODELS)

    with Client(address, timeout="30s") as client:
        return client.run(count)


def test_run_on_an_existing_cluster(cluster: tuple[str, Path], raw_drive_template: Path, weights_file: Path,
                                    tmp_path: Path) -> None:
    address, logs = cluster
    out = tmp_path / "out"
    command = [str(BIN / "kitti-pu"), "run", str(raw_drive_template), "--out", str(out), "--scheduler", address,
               "--weights", str(weights_file), "--no-progress", "--set", "dask.torch_threads=1",
               "--set", "upsample.device=cpu"]
    done = subprocess.run(command, capture_output=True, text=True, timeout=240, cwd=tmp_path)
    assert done.returncode == 0, f"{done.stdout}\n{done.stderr}\n{_logs(logs)}"
    assert "done 2, skipped 0, failed 0 of 2 frames" in done.stdout

    summary = json.loads((out / "summary.json").read_text())
    assert summary["scheduler"] == address and summary["workers"] == 2
    for report in summary["frames"]:
        assert report["status"] == "done"
        paths = write.output_paths(out, "raw", DRIVE_NAME, report["index"])
        assert write.is_complete(paths)
        assert pq.read_metadata(paths["parquet"]).num_rows == report["points_out"] > report["points_in"]
    # the model is loaded at most once per worker process, not shipped with every task
    models = _models_per_worker(address)
    assert len(models) == 2 and set(models.values()) <= {0, 1} and sum(models.values()) >= 1
    # the tool prepared each worker itself: torch threads as set, the nanny's malloc setting undone
    with Client(address, timeout="30s") as client:
        setups = client.run(lambda dask_worker: dask_worker.kitti_pu_setup)
        # and left the interpreter's teardown to the user's workers (exit_fast is for the tool's own)
        # and their Ctrl-C: a user's `dask worker` in a terminal still stops on it
        assert list(setups.values()) == [{"torch_threads": 1, "malloc_restored": True, "exit_fast": False,
                                          "sigint_ignored": False}] * 2
        # and gave each frame's freed heap back to the OS after the frame (glibc)
        trimmed = client.run(lambda dask_worker: dask_worker.kitti_pu_frames_trimmed)
        assert sum(trimmed.values()) == (2 if trim_allocator() else 0)
        # without dask.torch_threads: the host's cores shared by its two workers
        assert threads_on_each_worker(client) == {a: max(1, (os.cpu_count() or 1) // 2) for a in setups}
        # and took its setup off the user's cluster: workers joining later are not prepared with
        # this run's choices (it stayed registered for every later worker: a trial)
        assert not any(name.startswith(WorkerSetup.NAME_PREFIX)
                       for plugins in client.run(lambda dask_worker: list(dask_worker.plugins)).values()
                       for name in plugins)
    # a second run with another thread count: the threads that run the frames take it (torch keeps a
    # count per thread, and the one set in the worker's main thread did not reach them: 5x slower)
    with Client(address, timeout="30s") as client:
        client.run(lambda dask_worker: dask_worker.__dict__.pop("kitti_pu_network_threads", None))
    again = subprocess.run([*command, "--overwrite", "--set", "dask.torch_threads=2"], capture_output=True, text=True,
                           timeout=240, cwd=tmp_path)
    assert again.returncode == 0, f"{again.stdout}\n{again.stderr}\n{_logs(logs)}"
    with Client(address, timeout="30s") as client:
        import torch

        ran = [worker for worker, threads in client.run(
            lambda dask_worker: getattr(dask_worker, "kitti_pu_network_threads", None)).items() if threads]
        assert ran  # the workers that ran a frame's network in this run, each on its one Dask thread
        assert {client.submit(torch.get_num_threads, pure=False, workers=[worker]).result() for worker in ran} == {2}


def test_a_worker_that_joins_after_the_run_began_gets_its_hosts_share_of_threads(tmp_path: Path) -> None:
    # a late worker got the smallest count of the workers there at the start, however many
    # workers its host then ran (2 single-threaded workers on 2 cores ran 2 torch threads each: a trial)
    cores = os.cpu_count() or 1
    with _external_cluster(tmp_path, 1) as (address, logs), Client(address, timeout="30s") as client:
        by_worker = threads_on_each_worker(client)
        assert list(by_worker.values()) == [cores]
        client.register_plugin(WorkerSetup(None, by_worker))
        late = _start(_worker_command(address, logs, "late"), logs / "late.log", tmp_path)
        try:
            client.wait_for_workers(2, timeout=90)
            deadline = time.monotonic() + 60
            while len(setups := client.run(lambda dask_worker: getattr(dask_worker, "kitti_pu_setup", None))) < 2 \
                    or None in setups.values():
                assert time.monotonic() < deadline, _logs(logs)
                time.sleep(0.2)
            threads = {worker: setup["torch_threads"] for worker, setup in setups.items()}
            first = next(iter(by_worker))
            assert threads == {first: cores, **{w: max(1, cores // 2) for w in threads if w != first}}
            # the run then gives the worker already there its new share too: the host ran 2 + 1
            # torch threads on 2 cores (a review)
            share_threads_again(client)
            setups = client.run(lambda dask_worker: dask_worker.kitti_pu_setup["torch_threads"])
            assert set(setups.values()) == {max(1, cores // 2)}
        finally:
            _stop(late)


def test_a_worker_that_joins_on_other_code_makes_no_frame_the_run_writes() -> None:
    # only the workers there when the run connected were checked: one joining later, on another
    # revision, made frames with its own code, and the run wrote them (an earlier note); Dask keeps
    # a worker whose plugin setup raised running, and its work stealing moved single steps of
    # other workers' frames onto it (an operator's trial), so every task checks, and the run stops
    from types import SimpleNamespace

    from pipeline.cluster import (SetupFailed, code_identity, describe_code, on_prepared_worker, register_setup,
                                  with_worker_torch_threads, worker_refusals)
    from pipeline.runner import _stop_on_refused_workers
    from stages.errors import StageError

    def upsample(subject: SimpleNamespace) -> str:
        return f"made {subject.source}"

    def stitch(subject: SimpleNamespace) -> str:
        return f"stitched {subject.source}"

    upsample.name, stitch.name = "upsample", "stitch"  # type: ignore[attr-defined]  # as a chain's Steps are named
    scan = SimpleNamespace(source="scan.bin")
    with LocalCluster(n_workers=0, threads_per_worker=1, processes=False, dashboard_address="127.0.0.1:0") as cluster, \
            Client(cluster) as client:
        register_setup(client, WorkerSetup(1, code="0" * 12, owner="run"))  # the run's code: not this process's
        cluster.scale(1)
        client.wait_for_workers(1, timeout=60)
        (worker,) = client.scheduler_info()["workers"]
        deadline = time.monotonic() + 30
        while worker not in (verdicts := worker_refusals(client, [worker])):  # until its setup has run
            assert time.monotonic() < deadline
            time.sleep(0.1)
        assert f"on other kitti-pu code, {describe_code(code_identity())}, than the run's (code 000000000000)" \
            in verdicts[worker] and "restart it" in verdicts[worker]
        for wrapper, step in ((with_worker_torch_threads, upsample), (on_prepared_worker, stitch)):
            made = client.submit(wrapper, step, scan, pure=False).result()
            assert isinstance(made, StageError) and made.stage == step.name and made.source == "scan.bin"
            assert made.reason == verdicts[worker]
        judged: set[str] = set()
        with pytest.raises(SetupFailed, match=r"joined the cluster during the run on other kitti-pu code.* The frames "
                                              r"done so far are kept; stop or fix that worker and run again"):
            _stop_on_refused_workers(client, [worker], judged)
        register_setup(client, WorkerSetup(1, code=code_identity()[1], owner="run"))  # a run on its own code
        assert client.submit(with_worker_torch_threads, upsample, scan, pure=False).result() == "made scan.bin"
        assert client.submit(on_prepared_worker, stitch, scan, pure=False).result() == "stitched scan.bin"
        _stop_on_refused_workers(client, [worker], judged)
        assert judged == {worker}


@pytest.mark.parametrize("in_flight", [1, 3])
def test_a_run_that_loses_its_scheduler_stops_once_its_client_gives_up(raw_drive_template: Path, weights_file: Path,
                                                                        tmp_path: Path, in_flight: int) -> None:
    import psutil

    # a frame submitted once the client had given up and closed never finished: the run waited the
    # whole dask.no_workers_timeout more, then blamed the workers (a trial). One frame in flight:
    # the first is cancelled at the loss, the second when the client closes, the third comes after.
    # All three in flight: all cancelled when the client closes, and the run ended without a line
    # of its own (an operator's trial).
    scans = tmp_path / "scans"
    scans.mkdir()
    first = sorted(raw_drive_template.rglob("velodyne_points/data/*.bin"))[0]
    for index in range(3):
        (scans / f"{index:06d}.bin").write_bytes(first.read_bytes())
    out = tmp_path / "out"
    with _external_cluster(tmp_path, 1) as (address, logs):
        port = int(address.rsplit(":", 1)[1])
        scheduler = next(process for process in psutil.process_iter(["cmdline"])
                         if "scheduler" in (process.info["cmdline"] or []) and str(port) in (process.info["cmdline"] or []))
        run = _start([str(BIN / "kitti-pu"), "run", str(scans), "--out", str(out), "--scheduler", address,
                      "--weights", str(weights_file), "--no-progress", "--set", "dask.no_workers_timeout=600",
                      "--set", f"dask.max_in_flight={in_flight}"],
                     tmp_path / "run.log", tmp_path)
        deadline = time.monotonic() + 120
        with Client(address, timeout="30s") as watcher:
            while not any(watcher.processing().values()):  # the run's frames have reached the worker
                assert time.monotonic() < deadline and run.poll() is None, (tmp_path / "run.log").read_text()
                time.sleep(0.05)
            scheduler.kill()
        killed = time.monotonic()
        try:
            status = run.wait(timeout=180)
        finally:
            _stop(run)
        took = time.monotonic() - killed
    output = (tmp_path / "run.log").read_text()
    assert status == 3 and "this run lost the Dask scheduler" in output, output
    assert took < 120  # the client's reconnect timeout (20 s) and a check, not the 600 s
    assert {frame["status"] for frame in json.loads((out / "summary.json").read_text())["frames"]} <= {"done", "interrupted"}


def test_trimming_gives_freed_heap_memory_back() -> None:
    """Memory freed in the middle of the heap stays in the process until `trim_allocator`."""
    code = """
import psutil, sys
from pipeline.cluster import trim_allocator
if not trim_allocator():
    print("not glibc"); sys.exit()
rss = lambda: psutil.Process().memory_info().rss / 2**20
blocks = [bytearray(64 * 1024) for _ in range(4000)]  # 250 MiB of heap blocks (under the mmap threshold)
del blocks[::2]  # free every other block: the heap cannot shrink from its top
before = rss(); trim_allocator(); after = rss()
print(round(before - after))
"""
    env = {k: v for k, v in os.environ.items() if k != "MALLOC_TRIM_THRESHOLD_"}
    env["PYTHONPATH"] = os.pathsep.join(filter(None, [str(REPO), os.environ.get("PYTHONPATH")]))
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=60)
    if done.stdout.strip() == "not glibc":
        pytest.skip("malloc_trim is glibc's")
    assert int(done.stdout) > 100, done.stderr  # MiB returned of the 125 freed


@pytest.mark.parametrize("variable, restored", [("65536", "True"), (None, "False")])
def test_malloc_thresholds_are_restored_only_where_the_nanny_set_them(variable: str | None, restored: str) -> None:
    env = {k: v for k, v in os.environ.items() if k != "MALLOC_TRIM_THRESHOLD_"}
    if variable is not None:
        env["MALLOC_TRIM_THRESHOLD_"] = variable
    env["PYTHONPATH"] = os.pathsep.join(filter(None, [str(REPO), os.environ.get("PYTHONPATH")]))
    done = subprocess.run([sys.executable, "-c", "from pipeline.cluster import restore_malloc_thresholds as r; print(r())"],
                          capture_output=True, text=True, env=env, timeout=60)
    assert done.stdout.strip() == restored, done.stderr


@pytest.mark.parametrize("cores, settings, expected", [
    # the default: one worker per core, one frame and one torch thread each
    (2, {}, (2, 1, 1)),
    (8, {}, (4, 2, 1)),
    # fewer workers than cores: the spare cores run more frames, not more torch threads
    (2, {"dask.n_workers": 1}, (1, 2, 1)),
    # what is set is kept, and torch gets the cores left per frame
    (2, {"dask.n_workers": 1, "dask.torch_threads": 2}, (1, 1, 2)),
    (2, {"dask.n_workers": 1, "dask.threads_per_worker": 1}, (1, 1, 2)),
    (8, {"dask.n_workers": 2, "dask.threads_per_worker": 2}, (2, 2, 2)),
])
def test_the_cluster_plan_gives_spare_cores_to_frames(monkeypatch: pytest.MonkeyPatch, cores: int,
                                                      settings: dict[str, int], expected: tuple[int, int, int]) -> None:
    from pipeline.cluster import plan_cluster
    from pipeline.config import load_config

    monkeypatch.setattr(os, "cpu_count", lambda: cores)
    plan = plan_cluster(load_config([], settings))
    assert (plan.workers, plan.threads_per_worker, plan.torch_threads) == expected


def _sigint_disposition() -> str:
    import signal as signals

    return "ignored" if signals.getsignal(signals.SIGINT) == signals.SIG_IGN else "handled"


def test_the_tools_own_workers_leave_ctrl_c_to_the_run(tmp_path: Path) -> None:
    config = load_config(overrides={"input.path": str(tmp_path), "output.dir": str(tmp_path / "out"),
                                    "dask.n_workers": 1, "dask.torch_threads": 1})
    with open_client(config, plan_cluster(config)) as client:
        assert list(client.run(_sigint_disposition).values()) == ["ignored"]
        assert [s["sigint_ignored"] for s in client.run(lambda dask_worker: dask_worker.kitti_pu_setup).values()] == [True]
        # nor do they log a warning for each task a closing cluster cancels (an interrupted run's log)
        assert list(client.run(_state_machine_warns).values()) == [False]


def _state_machine_warns() -> bool:
    import logging

    from pipeline.cluster import STATE_MACHINE_LOGGER

    return logging.getLogger(STATE_MACHINE_LOGGER).isEnabledFor(logging.WARNING)


def test_an_existing_clusters_threads_share_each_hosts_cores_and_size_the_frames_in_flight() -> None:
    with LocalCluster(n_workers=1, threads_per_worker=2, processes=False, dashboard_address="127.0.0.1:0") as local, \
            Client(local) as client:
        # one worker of 2 Dask threads runs 2 frames at once: each frame gets half the host's cores
        assert cluster_threads(client) == 2
        assert list(threads_on_each_worker(client).values()) == [max(1, (os.cpu_count() or 1) // 2)]


def test_a_memory_limit_given_as_a_share_reaches_the_workers_as_that_share_of_memory() -> None:
    import psutil

    config = load_config([], {"dask.memory_limit": "0.5", "dask.n_workers": 1, "dask.threads_per_worker": 1})
    with open_client(config, plan_cluster(config)) as client:
        client.wait_for_workers(1, timeout=60)  # the client's view of the workers lags on a loaded machine
        limits = [info["memory_limit"] for info in client.scheduler_info()["workers"].values()]
    # the workers get the share the checks read (`preflight.worker_memory_bytes`)
    assert limits == [int(0.5 * psutil.virtual_memory().total)]


def _sigint_blocked() -> bool:
    return signal.SIGINT in signal.pthread_sigmask(signal.SIG_BLOCK, [])


@pytest.mark.skipif(not hasattr(signal, "pthread_sigmask"), reason="no signal masks (not POSIX)")
def test_the_run_holds_ctrl_c_back_while_its_cluster_starts_and_gets_it_back(monkeypatch: pytest.MonkeyPatch) -> None:
    # a Ctrl-C while the cluster started interrupted the start, and the half-started cluster's exit
    # handler failed with an AssertionError. (The workers are not covered by the held-back signal:
    # in a fresh process their SigBlk is 0, so an assertion that they inherited it passed or failed
    # by the order of the tests; they ignore SIGINT once the worker setup is registered, tested
    # above by `sigint_ignored`.)
    assert not _sigint_blocked()
    held = []
    real = LocalCluster.__init__

    def starting(self, *args, **kwargs):  # noqa: ANN001, ANN002, ANN003, ANN202
        held.append(_sigint_blocked())
        return real(self, *args, **kwargs)

    monkeypatch.setattr(LocalCluster, "__init__", starting)
    with local_cluster(1) as cluster, Client(cluster):
        assert not _sigint_blocked()  # the run's own process takes Ctrl-C again once the cluster is up
    assert held == [True] and not _sigint_blocked()


def test_a_users_cluster_loses_the_setups_of_runs_that_were_killed_and_keeps_a_running_ones(tmp_path: Path) -> None:
    from pipeline.cluster import remove_stale_setups

    with LocalCluster(n_workers=1, threads_per_worker=1, processes=False, memory_limit="2GB",
                      dashboard_address=None) as cluster, Client(cluster) as client, Client(cluster) as other:
        # a run killed with SIGKILL left its setup registered for good: every worker joining later
        # was prepared with its choices (an operator's trial); one of an earlier version, named
        # without its client, and one of a run still going (its client connected)
        killed = WorkerSetup(1, owner="Client-0123456789abcdef")
        earlier = WorkerSetup(1)
        running = WorkerSetup(1, owner=other.id)
        for setup in (killed, earlier, running):
            client.register_plugin(setup)
        assert sorted(remove_stale_setups(client)) == sorted([killed.name, earlier.name])
        names = client.run_on_scheduler(lambda dask_scheduler: list(dask_scheduler.worker_plugins))
        assert running.name in names and killed.name not in names and earlier.name not in names
        config = load_config([], settings={"dask.scheduler": cluster.scheduler_address, "dask.torch_threads": 1})
        with open_client(config, plan_cluster(config)) as run_client:  # a run on that cluster removes them itself
            client.register_plugin(killed)
            ours = [name for name in client.run_on_scheduler(lambda dask_scheduler: list(dask_scheduler.worker_plugins))
                    if name.endswith(run_client.id)]
            assert len(ours) == 1
        with open_client(config, plan_cluster(config)):
            names = client.run_on_scheduler(lambda dask_scheduler: list(dask_scheduler.worker_plugins))
            assert killed.name not in names and running.name in names and ours[0] not in names


def test_a_worker_lost_while_the_setup_reaches_the_workers_does_not_stop_the_run(
        monkeypatch: pytest.MonkeyPatch) -> None:
    import pipeline.cluster
    from distributed.comm.core import CommClosedError

    real = Client.register_plugin
    calls = []

    def worker_lost_once(self: Client, plugin: object, *args: object, **kwargs: object) -> object:
        calls.append(plugin)
        if len(calls) == 1:  # what a worker killed (or restarted by its nanny) mid-broadcast raised
            raise CommClosedError("in <TCP (closed) ConnectionPool.register_worker_plugin local=tcp://127.0.0.1:1>")
        return real(self, plugin, *args, **kwargs)

    monkeypatch.setattr(Client, "register_plugin", worker_lost_once)
    monkeypatch.setattr(pipeline.cluster, "SETUP_RETRY_PAUSE_S", 0.0)
    config = load_config([], settings={"dask.n_workers": 1, "dask.torch_threads": 1})
    # the run took it for a lost cluster: exit 3, every frame interrupted, the cluster fine
    with open_client(config, plan_cluster(config)) as client:
        assert len(calls) == 2
        assert list(client.run(lambda dask_worker: "kitti_pu_setup" in dask_worker.__dict__).values()) == [True]


def test_a_worker_closing_at_every_attempt_of_the_setup_is_said_as_such(monkeypatch: pytest.MonkeyPatch) -> None:
    import pipeline.cluster
    from distributed.comm.core import CommClosedError
    from pipeline.cluster import SetupFailed, register_setup

    # a worker crash-looping at start was reported as "the cluster was lost", the scheduler fine
    # (an operator's trial)
    def worker_lost(self: Client, plugin: object, *args: object, **kwargs: object) -> object:
        raise CommClosedError("in <TCP (closed) ConnectionPool.register_worker_plugin local=tcp://127.0.0.1:1>")

    monkeypatch.setattr(Client, "register_plugin", worker_lost)
    monkeypatch.setattr(pipeline.cluster, "SETUP_RETRY_PAUSE_S", 0.0)
    with LocalCluster(n_workers=1, threads_per_worker=1, processes=False, dashboard_address=None) as cluster, \
            Client(cluster) as client:
        with pytest.raises(SetupFailed, match=r"a worker closed during each of 3 attempts to set up the workers "
                                              r"\(one crashing at start\? its log says why\): in <TCP"):
            register_setup(client, WorkerSetup(1))


def test_a_client_closed_while_the_setup_is_registered_is_a_lost_cluster_not_a_crash() -> None:
    from pipeline.cluster import register_setup

    # Dask raises an AttributeError once its client has closed (the scheduler died, the client gave
    # up reconnecting): the run crashed with exit 1 and a traceback (an operator's trial); the
    # runner takes an OSError for a lost cluster, its frames not reached
    with LocalCluster(n_workers=1, threads_per_worker=1, processes=False, dashboard_address=None) as cluster:
        client = Client(cluster)
        client.close()
        with pytest.raises(ConnectionError, match="the scheduler was lost while the run set up its workers"):
            register_setup(client, WorkerSetup(1))


def _shadowed_worker(address: str, logs: Path, name: str, shadow: Path, cwd: Path) -> subprocess.Popen:
    """A `dask worker` whose imports find the packages in `shadow` before this checkout's."""
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(shadow), str(REPO)])}
    return subprocess.Popen(_worker_command(address, logs, name), stdout=(logs / f"{name}.log").open("w"),
                            stderr=subprocess.STDOUT, env=env, cwd=cwd)


@pytest.mark.parametrize("kind", ["without kitti-pu", "other code", "this code, another version's metadata"])
def test_workers_that_cannot_run_this_kitti_pu_are_refused_before_any_frame(
        kind: str, raw_drive_template: Path, weights_file: Path, tmp_path: Path) -> None:
    # a worker without the tool crashed the run with a traceback (exit 1) and left it marked
    # unfinished; workers of another version lost every worker to the first task, and the run
    # said "no workers" after 120 s (an external-cluster user's trial)
    import shutil

    shadow = tmp_path / "shadow"
    if kind == "without kitti-pu":  # what a worker's environment without it raises at the first import
        (shadow / "pipeline").mkdir(parents=True)
        (shadow / "pipeline" / "__init__.py").write_text(
            "raise ModuleNotFoundError(\"No module named 'pipeline'\", name='pipeline')\n")
    elif kind.startswith("this code"):  # an installation's stale metadata before this checkout: the same code
        (shadow / "kitti_pu-0.0.9.dist-info").mkdir(parents=True)
        (shadow / "kitti_pu-0.0.9.dist-info" / "METADATA").write_text("Metadata-Version: 2.1\nName: kitti-pu\nVersion: 0.0.9\n")
    else:  # this checkout's sources with one line more: a worker on another revision
        for package in ("cadpu", "pipeline", "stages"):
            shutil.copytree(REPO / package, shadow / package,
                            ignore=shutil.ignore_patterns("__pycache__", "*.pt", "*.csv", "checkpoints"))
        with (shadow / "stages" / "tile.py").open("a") as source:
            source.write("# another revision\n")
    with _external_cluster(tmp_path, 1) as (address, logs):
        extra = _shadowed_worker(address, logs, "shadowed", shadow, tmp_path)
        try:
            with Client(address, timeout="60s") as client:
                client.wait_for_workers(2, timeout=90)
            done = subprocess.run([str(BIN / "kitti-pu"), "run", str(raw_drive_template), "--out", str(tmp_path / "out"),
                                   "--scheduler", address, "--weights", str(weights_file), "--no-progress"],
                                  capture_output=True, text=True, timeout=120, cwd=tmp_path)
        finally:
            _stop(extra)
    if kind.startswith("this code"):  # the code is what runs the frames: taken (it was refused by its version)
        assert done.returncode == 0, done.stdout + done.stderr
        return
    assert done.returncode == 2, done.stdout + done.stderr
    said = done.stderr
    assert "Traceback" not in said
    if kind == "without kitti-pu":
        assert "worker(s) that cannot run kitti-pu (tcp://127.0.0.1:" in said and "No module named 'pipeline'" in said
    else:
        assert "worker(s) on other kitti-pu code than this one" in said and " runs 0." in said
    assert "install kitti-pu" in said
    assert not list((tmp_path / "out").glob("runs/*.unfinished")) and not list((tmp_path / "out").rglob("*.parquet"))


def test_adding_a_format_on_an_existing_cluster_says_no_frame_needed_the_network(
        raw_drive_template: Path, weights_file: Path, tmp_path: Path) -> None:
    # the cluster is reached first (an added format may find its stored file damaged), and the
    # summary then said "no worker ran a frame: the cluster failed", exit 0 (an external-cluster user's trial)
    with _external_cluster(tmp_path, 1) as (address, _):
        command = [str(BIN / "kitti-pu"), "run", str(raw_drive_template), "--out", str(tmp_path / "out"),
                   "--scheduler", address, "--weights", str(weights_file), "--no-progress"]
        first = subprocess.run([*command, "--format", "parquet"], capture_output=True, text=True, timeout=180, cwd=tmp_path)
        assert first.returncode == 0, first.stdout + first.stderr
        # a dry run that only adds formats reaches the cluster too, as the run does (a reviewer's find)
        dry = subprocess.run([*command, "--format", "parquet,ply", "--dry-run"], capture_output=True,
                             text=True, timeout=180, cwd=tmp_path)
        added = subprocess.run([*command, "--format", "parquet,ply"], capture_output=True, text=True, timeout=180,
                               cwd=tmp_path)
    assert dry.returncode == 0, dry.stdout + dry.stderr
    assert f"# cluster: {address} answers: 1 worker, 1 thread, each on this kitti-pu, 0." in dry.stdout
    assert added.returncode == 0, added.stdout + added.stderr
    assert "(no worker ran a frame: no frame needed the network)" in added.stdout + added.stderr
    assert "the cluster failed" not in added.stdout + added.stderr
    summary = json.loads((tmp_path / "out" / "summary.json").read_text())
    assert summary["scheduler"] == f"{address} (contacted: no frame needed the network)"


def test_the_worker_setup_imports_off_the_worker_s_event_loop(monkeypatch: pytest.MonkeyPatch) -> None:
    # imported on the event loop, torch and pykitti blocked every fresh worker for 3-7 s ("Event loop
    # was unresponsive in Worker"), its heartbeats included (an external-cluster user's trial)
    import threading

    threads: list[str] = []

    def imports(self: WorkerSetup) -> None:
        threads.append(threading.current_thread().name)

    monkeypatch.setattr(WorkerSetup, "_import_modules", imports)
    with LocalCluster(n_workers=1, threads_per_worker=1, processes=False, dashboard_address="127.0.0.1:0") as cluster, \
            Client(cluster) as client:
        loop_thread = client.run(lambda: threading.current_thread().name)
        client.register_plugin(WorkerSetup(1))
    assert len(threads) == 1 and threads[0] not in loop_thread.values()


class _SlowToTearDown:
    """A worker plugin whose teardown takes `seconds`: a worker that does not answer for that long."""

    def __init__(self, seconds: float) -> None:
        self.seconds = seconds

    async def teardown(self, worker: object) -> None:
        import asyncio

        await asyncio.sleep(self.seconds)


def test_a_run_s_setup_is_taken_off_without_waiting_for_every_worker_s_answer() -> None:
    # a worker that stayed "closing" (its setup failed as it joined) never answered the plugin's
    # removal, and a run whose frames were all written waited for it for minutes (a trial)
    from distributed.diagnostics.plugin import WorkerPlugin

    from pipeline.cluster import _unregister_setup

    class SlowPlugin(_SlowToTearDown, WorkerPlugin):
        name = "kitti-pu-worker-setup-slow"

    with LocalCluster(n_workers=1, threads_per_worker=1, processes=False, dashboard_address="127.0.0.1:0") as cluster, \
            Client(cluster) as client:
        slow = SlowPlugin(30.0)
        client.register_plugin(slow)
        started = time.monotonic()
        _unregister_setup(client, slow)  # type: ignore[arg-type]
        took = time.monotonic() - started
        registered = client.run_on_scheduler(lambda dask_scheduler: list(dask_scheduler.worker_plugins))
    assert took < 10 and SlowPlugin.name not in registered
