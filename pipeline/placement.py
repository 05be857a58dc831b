"""Which worker runs each frame: the one with the least network work ahead per Dask thread.

A frame is a chain of tasks (load -> ground -> tile -> upsample -> ... -> write) whose data follow
its first task, so the worker that loads a frame runs all of it. Dask places that first task by its
own expected duration, tens of milliseconds, and cannot know the second of network work that
follows. Two frames submitted together then land on the same worker, and the other can sit idle
for a whole frame (docs/results.md, "Frame placement").

So the runner chooses each frame's worker here and pins the frame's tasks to it loosely
(`allow_other_workers=True`: if the worker leaves the cluster, the scheduler runs them elsewhere).
Loose pins also let Dask's work stealing move a task of a frame to another worker when the pinned
one is behind (distributed's `WorkStealing._get_thief`); the frame's data travel with it, and its
result is the same. It is left on: runs were faster with it (docs/results.md, "Frame placement").
The choice counts, per thread, the frames on each worker whose network step has not finished (the
bulk of a frame's time), then all the frames it holds: a worker whose frames are only writing
will soon be free.

A cluster of one worker gets no pins. When that worker dies, its tasks wait while no worker runs,
and Dask parks them as "no-worker"; the restarted worker has another address, and Dask
(distributed 2026.8) moves parked tasks only onto workers their restrictions name, loose or not:
the run waited for ever. With two workers or more, a lost worker's frames go to a running one.
"""

from __future__ import annotations

import time
from collections import defaultdict

from distributed import Client, Future

#: How often the list of workers and their threads is asked of the scheduler (seconds): workers
#: may join or leave an external cluster mid-run.
REFRESH_SECONDS = 2.0


class FramePlacement:
    """Chooses a worker for each new frame and follows the frames each worker holds.

    `take()` before a frame is submitted, `placed(worker, network_step)` once it is (with the future
    of its network step), `give_back(worker)` when its report has come back.
    """

    def __init__(self, client: Client, refresh_seconds: float = REFRESH_SECONDS) -> None:
        self._client = client
        self._refresh_seconds = refresh_seconds
        self._threads: dict[str, int] = {}
        self._frames: dict[str, int] = defaultdict(int)
        self._network_steps: dict[str, list[Future]] = defaultdict(list)
        self._refreshed_at = -float("inf")

    def take(self) -> str | None:
        """The address of the worker for a new frame: the fewest unfinished network steps per
        thread, then the fewest frames per thread, then the first in the scheduler's order. None
        when the cluster reports fewer than two workers (the scheduler then places the frame)."""
        self._refresh()
        if len(self._threads) < 2:  # nothing to choose, and a lone worker is never pinned (module docstring)
            return None
        return min(self._threads, key=lambda address: (self.network_steps_ahead(address) / self._threads[address],
                                                       self._frames[address] / self._threads[address]))

    def placed(self, worker: str | None, network_step: Future | None) -> None:
        """A frame was submitted to `worker` (from `take`); `network_step` is the future of its
        network step, followed until it finishes."""
        if worker is None:
            return
        self._frames[worker] += 1
        if network_step is not None:
            self._network_steps[worker].append(network_step)

    def give_back(self, worker: str | None) -> None:
        """A frame placed on `worker` has finished, failed or been cancelled."""
        if worker is not None and self._frames[worker] > 0:
            self._frames[worker] -= 1
            self.network_steps_ahead(worker)  # drops the futures of finished steps

    def network_steps_ahead(self, worker: str) -> int:
        """The frames on `worker` whose network step has not finished. The futures of finished
        steps are dropped here, so their results are not kept alive by this object."""
        pending = [future for future in self._network_steps[worker] if not future.done()]
        self._network_steps[worker] = pending
        return len(pending)

    def frames(self) -> dict[str, int]:
        """Frames held per worker address (those holding none left out)."""
        return {worker: count for worker, count in self._frames.items() if count}

    def _refresh(self) -> None:
        now = time.monotonic()
        if self._threads and now - self._refreshed_at < self._refresh_seconds:
            return
        workers = self._client.scheduler_info().get("workers", {})
        # running ones alone: a worker closing (one whose setup failed as it joined stayed so for
        # minutes) or paused holds no frames, and took every new one as the least busy (a trial)
        self._threads = {address: max(1, int(info.get("nthreads") or 1)) for address, info in workers.items()
                         if info.get("status", "running") == "running"}
        self._refreshed_at = now
