"""A Dask cluster of loopback processes for bench/faults.py: `dask scheduler` and
`dask worker --no-nanny` subprocesses on 127.0.0.1, each in its own process group (so a SIGKILL
of one is the death of that scheduler or worker alone)."""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path
from types import TracebackType

from distributed import Client

from fault_checks import Proc, kill_group, start

DASK = [sys.executable, "-m", "dask"]


class LoopbackCluster:
    """A scheduler and `workers` single-threaded workers on 127.0.0.1, ready on entry, all killed
    on exit. Every process started is also appended to `started` (for the script's last cleanup)."""

    def __init__(self, folder: Path, started: list[Proc], workers: int = 2, timeout: float = 60.0) -> None:
        self.folder = folder
        self.started = started
        self.n_workers = workers
        self.timeout = timeout
        self.scheduler_file = folder / "scheduler.json"
        self.workers: list[Proc] = []
        self.address = ""

    def _start(self, command: list[str], name: str) -> Proc:
        proc = start(command, self.folder / name, self.folder)
        self.started.append(proc)
        return proc

    def add_worker(self) -> Proc:
        """Start one more worker and wait until the scheduler has it; returns its process."""
        expected = sum(worker.popen.poll() is None for worker in self.workers) + 1
        worker = self._start([*DASK, "worker", "--scheduler-file", str(self.scheduler_file), "--host", "127.0.0.1",
                              "--nthreads", "1", "--no-nanny", "--no-dashboard", "--death-timeout", "15",
                              "--name", f"w{len(self.workers)}"], f"worker-{len(self.workers)}")
        self.workers.append(worker)
        with Client(self.address, timeout=self.timeout) as client:
            client.wait_for_workers(expected, timeout=self.timeout)
        return worker

    def __enter__(self) -> "LoopbackCluster":
        self.folder.mkdir(parents=True, exist_ok=True)
        self.scheduler = self._start([*DASK, "scheduler", "--host", "127.0.0.1", "--port", "0", "--no-dashboard",
                                      "--scheduler-file", str(self.scheduler_file)], "scheduler")
        deadline = time.monotonic() + self.timeout
        while not self.scheduler_file.exists():
            if time.monotonic() > deadline or self.scheduler.popen.poll() is not None:
                raise RuntimeError(f"loopback scheduler did not start: {self.scheduler.stderr()[-1000:]}")
            time.sleep(0.1)
        time.sleep(0.2)  # the file is written in one go, but let it be complete
        self.address = json.loads(self.scheduler_file.read_text())["address"]
        if not self.address.startswith("tcp://127.0.0.1:"):
            raise RuntimeError(f"loopback scheduler listens on {self.address}, not on 127.0.0.1")
        for _ in range(self.n_workers):
            self.add_worker()
        return self

    def __exit__(self, kind: type[BaseException] | None, error: BaseException | None,
                 trace: TracebackType | None) -> None:
        for proc in [*self.workers, self.scheduler]:
            kill_group(proc.pid)
            proc.wait(30)
