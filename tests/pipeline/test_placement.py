"""Frame placement on a real (in-process) LocalCluster: each new frame goes to the worker with the
least network work ahead, so no worker idles while another holds two frames' networks; and frames
waiting on a cluster without workers stop the run after `dask.no_workers_timeout`."""

from __future__ import annotations

import time
from collections import Counter
from collections.abc import Iterator
from pathlib import Path
from typing import Callable

import dask
import numpy as np
import pytest
from distributed import Client, Event, LocalCluster, as_completed, get_task_stream

from pipeline.chain import Chain
from pipeline.placement import FramePlacement
from pipeline.preflight import discover_frames
from pipeline.runner import NETWORK_STEP, NoWorkers, _as_finished, _process


@pytest.fixture(scope="module")
def client() -> Iterator[Client]:
    # without work stealing, which moves a loosely pinned task of a few frames in 30 to the other worker
    # (pipeline.placement; it failed the test of one worker a frame once): these tests check the placement
    with dask.config.set({"distributed.scheduler.work-stealing": False}), \
            LocalCluster(n_workers=2, threads_per_worker=1, processes=False, dashboard_address="127.0.0.1:0") as cluster, \
            Client(cluster) as connected:
        yield connected


def _workers(client: Client) -> list[str]:
    return list(client.scheduler_info()["workers"])


def test_frames_alternate_between_idle_workers(client: Client) -> None:
    placement = FramePlacement(client)
    chosen = []
    for _ in range(4):
        worker = placement.take()
        placement.placed(worker, None)
        chosen.append(worker)
    assert Counter(chosen) == Counter({address: 2 for address in _workers(client)})
    assert placement.frames() == {address: 2 for address in _workers(client)}


def test_a_finished_frame_frees_its_worker(client: Client) -> None:
    placement = FramePlacement(client)
    first, second = placement.take(), None
    placement.placed(first, None)
    second = placement.take()
    placement.placed(second, None)
    assert first != second
    placement.give_back(first)
    assert placement.take() == first


def test_a_worker_whose_frames_are_past_the_network_is_chosen_over_one_still_running_it(client: Client) -> None:
    busy, nearly_free = _workers(client)
    release = Event("network step may end", client=client)  # Dask's: tasks are pickled even in-process
    running = client.submit(lambda: Event("network step may end").wait(30), workers=[busy], pure=False)
    finished = client.submit(lambda: 1, workers=[nearly_free], pure=False)
    finished.result()
    placement = FramePlacement(client)
    placement.placed(busy, running)  # one frame, its network step still running
    placement.placed(nearly_free, finished)  # two frames, both past their network step
    placement.placed(nearly_free, finished)
    try:
        assert placement.network_steps_ahead(busy) == 1
        assert placement.network_steps_ahead(nearly_free) == 0
        assert placement.take() == nearly_free
    finally:
        release.set()
    running.result()
    assert placement.network_steps_ahead(busy) == 0  # and the finished future is no longer held
    assert placement._network_steps[busy] == []


def test_a_lone_worker_gets_no_pins() -> None:
    # pinned to a worker that died, its frames' tasks waited for ever: Dask moves parked tasks only
    # onto the workers their restrictions name, and the restarted worker has another address
    with LocalCluster(n_workers=1, threads_per_worker=2, processes=False, dashboard_address="127.0.0.1:0") as cluster, \
            Client(cluster) as lone:
        assert FramePlacement(lone).take() is None


def test_with_no_workers_the_scheduler_places_the_frame() -> None:
    with LocalCluster(n_workers=0, processes=False, dashboard_address="127.0.0.1:0") as cluster, \
            Client(cluster) as empty:
        placement = FramePlacement(empty)
        assert placement.take() is None
        placement.placed(None, None)
        placement.give_back(None)
        assert placement.frames() == {}


def test_every_task_of_a_frame_runs_on_one_worker_and_both_workers_get_frames(
        client: Client, template_scans: list[np.ndarray], tmp_path: Path, make_config: Callable) -> None:
    folder = tmp_path / "scans"
    folder.mkdir()
    for index in range(4):
        template_scans[index % 2].tofile(folder / f"{index:06d}.bin")
    config = make_config(folder, tmp_path / "out", dask__n_workers=2)
    refs = discover_frames(config)
    with get_task_stream(client) as stream:
        reports = [frame_report for _, frame_report in _process(client, refs, Chain(config, {}), 4, False)]
    assert [r.status for r in reports] == ["done"] * 4
    workers_of_frame: dict[str, set[str]] = {}
    for task in stream.data:
        frame = task["key"].split("-", 1)[1]
        workers_of_frame.setdefault(frame, set()).add(task["worker"])
    assert all(len(workers) == 1 for workers in workers_of_frame.values())
    network = Counter(task["worker"] for task in stream.data if task["key"].startswith(NETWORK_STEP + "-"))
    assert sorted(network.values()) == [2, 2]


def test_frames_waiting_on_a_cluster_that_lost_its_workers_stop_after_the_timeout() -> None:
    # Dask keeps such tasks for ever: the run waited, silent, holding the output folder's lock
    with LocalCluster(n_workers=1, threads_per_worker=1, processes=False, dashboard_address="127.0.0.1:0") as cluster, \
            Client(cluster) as lost:
        cluster.scale(0)
        deadline = time.monotonic() + 30
        while lost.scheduler_info()["workers"] and time.monotonic() < deadline:
            time.sleep(0.1)
        waiting = as_completed([lost.submit(sum, [1, 2], pure=False)])
        started = time.monotonic()
        with pytest.raises(NoWorkers, match=r"no running worker for 3 s \(dask.no_workers_timeout\): every worker it "
                                             "had left or died"):
            list(_as_finished(waiting, lost, 3))
        assert 3 <= time.monotonic() - started < 15


def test_a_worker_that_is_not_running_gets_no_frames() -> None:
    # a worker whose setup failed as it joined an external cluster stayed "closing" for minutes,
    # and took every new frame as the least busy one (an external-cluster user's trial); a paused
    # one (at Dask's memory limit) is no better
    from distributed.core import Status

    with LocalCluster(n_workers=3, threads_per_worker=1, processes=False, dashboard_address="127.0.0.1:0") as cluster, \
            Client(cluster) as client:
        stopped = _workers(client)[0]

        def pause(dask_worker: object) -> None:
            dask_worker.status = Status.paused  # type: ignore[attr-defined]

        client.run(pause, workers=[stopped])
        deadline = time.monotonic() + 10
        while client.scheduler_info()["workers"][stopped].get("status") != "paused":
            assert time.monotonic() < deadline, "the worker was not reported paused"
            time.sleep(0.05)
        placement = FramePlacement(client, refresh_seconds=0)
        chosen = []
        for _ in range(4):
            chosen.append(worker := placement.take())
            placement.placed(worker, None)
        assert stopped not in chosen and Counter(chosen) == Counter({w: 2 for w in _workers(client) if w != stopped})
