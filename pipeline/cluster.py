"""The Dask cluster a run uses: a LocalCluster sized to the machine, or an existing scheduler, and
what every worker needs before its first frame."""

from __future__ import annotations

import asyncio
import contextlib
import ctypes
import functools
import hashlib
import logging
import os
import signal
import threading
import time
import uuid
from collections import Counter
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any
from urllib.parse import urlparse

import dask
from distributed import Client, LocalCluster
from distributed.diagnostics.plugin import WorkerPlugin

from stages.errors import StageError, first_line
from stages.wording import counted

from .config import ConfigError, PipelineConfig
from .process_end import exit_without_teardown


class WorkerSetup(WorkerPlugin):
    """Prepares every worker before its first frame, on a LocalCluster or any existing cluster.

    - Chooses torch's intra-op thread count: Dask's nanny sets OMP_NUM_THREADS=1 in worker
      processes, so without this torch would run the network on one core however many the worker
      was meant to use. `threads` when given (`dask.torch_threads`), else `threads_by_worker`'s
      count for the worker's address, else (a worker that joins later) its host's cores shared
      among the Dask threads of the workers the scheduler then has on that host. Torch keeps a
      count per thread once the thread has run torch, so the network step sets it again in the
      thread that runs it (`with_worker_torch_threads`); this sets it in the worker's main thread.
    - Undoes the nanny's MALLOC_TRIM_THRESHOLD_ (see KEEP_GLIBC_MALLOC_DEFAULTS) where it is set, as
      on clusters started with `dask worker`: `restore_malloc_thresholds`.
    - Imports pykitti, which the load stage otherwise imports on first use, and Open3D when the
      ground method is "ransac" (its only use in a run; an optional extra): time that would
      otherwise land in the first frame's timings on every worker.
    - After each frame's last task (`FRAME_END_PREFIX`), returns the heap memory the frame freed
      to the OS (`trim_allocator`): without it a worker's RSS kept creeping up over hundreds of
      frames, in memory glibc keeps after the frames free it (docs/results.md, "Trimming the heap
      after each frame").
    - With `exit_fast` (the tool's own LocalCluster only, whose worker processes end with the
      run): when the worker closes, its process skips the interpreter's teardown at exit (see
      `exit_without_teardown`), which torch makes slow; every frame is written by then.
    - With `ignore_sigint` (the tool's own LocalCluster only): the worker process ignores SIGINT.
      Ctrl-C in a terminal reaches every process of its group; the run handles it and closes the
      cluster, while each worker would otherwise end on a KeyboardInterrupt and print its
      traceback into the run's log. Workers of an external cluster keep theirs. These workers also
      leave out the warning Dask's worker state machine logs for each task the closing cluster
      cancels (its only warning: "Async instruction ... ended with CancelledError"), which filled
      an interrupted run's log above its one-line message.
    - With `code` (a run on an existing cluster: the client's `code_identity` digest), refuses a
      worker that joins on other kitti-pu code, or with a memory limit below `MIN_WORKER_MEMORY`
      (`unfit_worker`): the reason is left on it as `worker.kitti_pu_refused`, and its setup
      raises (the worker's log says why). Dask keeps such a worker running, so every task of a
      frame checks (`on_prepared_worker`): on a refused worker it returns the reason as the
      frame's error, and no frame any of whose steps it ran is written. The run stops once it
      sees one (`worker_refusals`). The workers there when the run connects are checked before
      any frame (`check_worker_code`, `check_worker_memory`); before this check, one that joined
      later made frames, or steps of frames that others wrote, with whatever code it had. A
      worker on a kitti-pu without this check is not refused.

    What it did is left on the worker as `worker.kitti_pu_setup` (torch_threads, malloc_restored,
    exit_fast, sigint_ignored), and the frames after which it trimmed the heap as
    `worker.kitti_pu_frames_trimmed`, for checks; both stay when a run on a user's cluster takes
    the plugin off at its end (`open_client`).
    """

    #: How the names of its registrations begin; each run registers its own (`name`), so that the
    #: end of one run takes off its own preparation, not another run's on the same cluster.
    NAME_PREFIX = "kitti-pu-worker-setup"

    def __init__(self, threads: int | None, threads_by_worker: dict[str, int] | None = None,
                 open3d: bool = False, exit_fast: bool = False, ignore_sigint: bool = False,
                 owner: str | None = None, code: str | None = None) -> None:
        # the registering client's id, where a user's cluster keeps it: a later run takes off the
        # setups whose client is gone (`remove_stale_setups`)
        self.name = f"{self.NAME_PREFIX}-{owner or uuid.uuid4().hex[:8]}"
        self.threads = threads
        self.threads_by_worker = dict(threads_by_worker or {})
        self.open3d = open3d
        self.exit_fast = exit_fast
        self.ignore_sigint = ignore_sigint
        self.code = code
        self._worker: object | None = None

    async def setup(self, worker: object) -> None:
        worker.kitti_pu_refused = unfit_worker(worker, self.code) if self.code is not None else None  # type: ignore[attr-defined]
        if worker.kitti_pu_refused:  # type: ignore[attr-defined]
            raise RuntimeError(worker.kitti_pu_refused)  # type: ignore[attr-defined]
        # off the worker's event loop: the imports take seconds, and Dask logged "Event loop was
        # unresponsive in Worker for 7.43s" on every fresh worker (a trial; its heartbeats wait too)
        await asyncio.get_running_loop().run_in_executor(None, self._import_modules)
        import torch

        address = str(getattr(worker, "address", ""))
        threads = self.threads or self.threads_by_worker.get(address) or await _host_share(worker, address)
        torch.set_num_threads(threads)
        # signal.signal works in a process's main thread only, where a worker's event loop runs
        sigint_ignored = self.ignore_sigint and threading.current_thread() is threading.main_thread()
        if sigint_ignored:
            signal.signal(signal.SIGINT, signal.SIG_IGN)
        if self.ignore_sigint:
            logging.getLogger(STATE_MACHINE_LOGGER).setLevel(logging.ERROR)
        worker.kitti_pu_setup = {"torch_threads": threads, "malloc_restored": restore_malloc_thresholds(),  # type: ignore[attr-defined]
                                 "exit_fast": self.exit_fast, "sigint_ignored": sigint_ignored}
        if not hasattr(worker, "kitti_pu_frames_trimmed"):  # counted across runs
            worker.kitti_pu_frames_trimmed = 0  # type: ignore[attr-defined]
        self._worker = worker

    def _import_modules(self) -> None:
        """Import what the first frame would otherwise import: pykitti, torch, Open3D for "ransac"."""
        import pykitti  # noqa: F401
        import torch  # noqa: F401

        if self.open3d:
            from cadpu.o3d import o3d  # noqa: F401

    def transition(self, key: object, start: str, finish: str, **kwargs: object) -> None:
        if finish == "memory" and isinstance(key, str) and key.startswith(FRAME_END_PREFIX):
            trimmed = trim_allocator()
            if self._worker is not None:
                self._worker.kitti_pu_frames_trimmed += trimmed  # type: ignore[attr-defined]

    def teardown(self, worker: object) -> None:
        if self.exit_fast:
            exit_without_teardown()


async def _host_share(worker: object, address: str) -> int:
    """A worker's torch threads when it joined after the run chose them: its host's cores shared
    among the Dask threads of the workers the scheduler has on that host now (itself included)."""
    identity = await worker.scheduler.identity()  # type: ignore[attr-defined]
    host = urlparse(address).hostname
    frames = sum(int(info.get("nthreads") or 1) for other, info in identity.get("workers", {}).items()
                 if urlparse(other).hostname == host)
    return host_share(os.cpu_count(), frames)


def _this_worker() -> object | None:
    """The Dask worker running this task, or None outside one."""
    from distributed import get_worker

    try:
        return get_worker()
    except ValueError:  # not in a worker
        return None


def _refusal(worker: object | None, step: Callable[[Any], Any], subject: Any) -> StageError | None:
    """The frame's StageError, naming the stage of `step`, when `worker` (`_this_worker`) is one
    the run's `WorkerSetup` refused (`worker.kitti_pu_refused`); None elsewhere, outside a worker
    too, or when `subject` already is a StageError (handed on as it is)."""
    refused = getattr(worker, "kitti_pu_refused", None)
    if not refused or isinstance(subject, StageError):
        return None
    name = getattr(step, "name", None) or getattr(step, "__name__", "frame")
    return StageError(str(name), str(getattr(subject, "source", "") or getattr(subject, "key", "") or "frame"), refused)


def on_prepared_worker(step: Callable[[Any], Any], subject: Any) -> Any:
    """`step(subject)`, a task of a frame's chain, unless this worker was refused by the run's
    setup (`_refusal`): then the reason, as the frame's error. Every task of a frame goes through
    this (the network step through `with_worker_torch_threads`): Dask's work stealing moved single
    steps of other workers' frames onto a refused worker, idle as it was, and those frames were
    written with steps of its code (an operator's trial)."""
    return _refusal(_this_worker(), step, subject) or step(subject)


def with_worker_torch_threads(step: Callable[[Any], Any], subject: Any) -> Any:
    """`step(subject)` with torch's thread count in this thread set to the one the worker's
    `WorkerSetup` chose (`worker.kitti_pu_setup`), where it differs: a thread of a worker's pool
    that has run torch keeps its own count, so a count set in the worker's main thread (a later
    run's, or one worker's of two) did not reach it, and the network ran on the wrong number of
    cores (5x slower on an external cluster's warm workers: a trial). The count is left on the
    worker as `worker.kitti_pu_network_threads`, for checks. Outside a worker, or on a worker the
    plugin has not prepared, the step runs as it is. On a worker the plugin refused, it returns
    the reason as the frame's error (`on_prepared_worker`)."""
    worker = _this_worker()
    if worker is None:
        return step(subject)
    refused = _refusal(worker, step, subject)
    if refused is not None:
        return refused
    wanted = getattr(worker, "kitti_pu_setup", {}).get("torch_threads")
    if wanted:
        import torch

        if torch.get_num_threads() != wanted:
            torch.set_num_threads(wanted)
        worker.kitti_pu_network_threads = wanted  # type: ignore[attr-defined]  # for checks
    return step(subject)


#: The logger of Dask's worker state machine, whose one warning is a cancelled task's (`WorkerSetup`).
STATE_MACHINE_LOGGER = "distributed.worker.state_machine"

#: Key prefix of a frame's last task, its report (`pipeline.runner`), after which its arrays are freed.
FRAME_END_PREFIX = "report-"


@functools.cache
def _glibc() -> ctypes.CDLL | None:
    """glibc, or None where the C library is another (musl, macOS, Windows)."""
    try:
        libc = ctypes.CDLL("libc.so.6")
        libc.malloc_trim  # noqa: B018 (glibc only)
    except (OSError, AttributeError):
        return None
    return libc


def trim_allocator() -> bool:
    """Give the heap memory this process has freed back to the OS (glibc's `malloc_trim(0)`, every
    arena). Returns True where it ran (glibc), False elsewhere."""
    libc = _glibc()
    if libc is None:
        return False
    libc.malloc_trim(0)
    return True


#: glibc mallopt parameters and the values its dynamic thresholds settle at on 64-bit Linux
#: (DEFAULT_MMAP_THRESHOLD_MAX, and twice that for trimming, as glibc's own rule sets them).
M_TRIM_THRESHOLD, M_MMAP_THRESHOLD = -1, -3
SETTLED_MMAP_THRESHOLD = 32 * 1024 * 1024
SETTLED_TRIM_THRESHOLD = 2 * SETTLED_MMAP_THRESHOLD


def restore_malloc_thresholds() -> bool:
    """In a process started with MALLOC_TRIM_THRESHOLD_ set (Dask's nanny sets it), set glibc's
    mmap and trim thresholds to where its dynamic thresholds would have settled, so numpy's large
    temporaries come from the heap again instead of fresh page-faulted mmaps.

    The variable cannot be unset from inside the process: glibc read it at start-up, and any
    explicit threshold turns the dynamic ones off for good; fixing both at their settled values
    is the closest state. Returns True when it changed them (glibc, variable set), else False.
    """
    libc = _glibc()
    if "MALLOC_TRIM_THRESHOLD_" not in os.environ or libc is None:  # not glibc: it meant nothing there
        return False
    return bool(libc.mallopt(M_MMAP_THRESHOLD, SETTLED_MMAP_THRESHOLD)
                and libc.mallopt(M_TRIM_THRESHOLD, SETTLED_TRIM_THRESHOLD))


def threads_on_each_worker(client: Client) -> dict[str, int]:
    """Torch threads for each worker of an existing cluster: its host's cores shared evenly among
    the frames that host runs at once, one per Dask thread of its workers (at least 1 each)."""
    cores = client.run(os.cpu_count)
    workers = client.scheduler_info().get("workers", {})
    frames_on_host: Counter = Counter()
    for address in cores:
        frames_on_host[urlparse(address).hostname] += int(workers.get(address, {}).get("nthreads") or 1)
    return {address: host_share(count, frames_on_host[urlparse(address).hostname]) for address, count in cores.items()}


def host_share(cores: int | None, frames: int) -> int:
    """Torch threads for each frame of a host with `cores` cores running `frames` frames at once
    (at least 1)."""
    return max(1, (cores or 1) // max(1, frames))


def share_threads_again(client: Client) -> None:
    """Give every prepared worker of an existing cluster its host's share of cores anew
    (`threads_on_each_worker`), for its next frame (`with_worker_torch_threads` reads it): a worker
    that joined during the run took its share, but those already on its host kept theirs, and the
    host ran more torch threads than cores."""
    shares = threads_on_each_worker(client)

    def take(dask_worker: object) -> None:
        setup = getattr(dask_worker, "kitti_pu_setup", None)
        address = getattr(dask_worker, "address", "")
        if setup is not None and address in shares:
            setup["torch_threads"] = shares[address]

    client.run(take)


def cluster_threads(client: Client) -> int:
    """The Dask threads of all the client's workers: the frames the cluster runs at once."""
    return sum(int(info.get("nthreads") or 1) for info in client.scheduler_info().get("workers", {}).values())


def check_worker_memory(client: Client, address: str) -> None:
    """ConfigError naming the workers of an existing cluster whose memory limit is below what a
    worker needs (`preflight.MIN_WORKER_MEMORY`): Dask would pause them mid-frame and the run
    would wait for ever."""
    from .preflight import MIN_WORKER_MEMORY

    small = {worker: info["memory_limit"] for worker, info in client.scheduler_info().get("workers", {}).items()
             if info.get("memory_limit") and info["memory_limit"] < MIN_WORKER_MEMORY}
    if small:
        named = ", ".join(f"{worker} ({limit / 1e9:.2f} GB)" for worker, limit in sorted(small.items()))
        raise ConfigError(f"dask.scheduler: {address}: worker(s) with a memory limit below the "
                          f"{MIN_WORKER_MEMORY / 1e9:.2f} GB a worker needs: {named}; start them with a larger "
                          "--memory-limit (their frames peak at about 0.75 GB, and Dask pauses a worker at 80%)")


#: The packages whose Python sources make a run's frames (`code_identity`).
CODE_PACKAGES = ("cadpu", "pipeline", "stages")


@functools.lru_cache(maxsize=1)
def code_identity() -> tuple[str, str]:
    """This process's kitti-pu: (its version, the first digits of a sha256 over the Python sources
    of `CODE_PACKAGES`, their paths within the checkout and their bytes). Two installations of one
    release, or one checkout, have the same digest; a worker on other code does not, though its
    version may read the same (a checkout on PYTHONPATH), and one on the same code may read another
    (an installation's stale metadata)."""
    from .chain import tool_version

    root = Path(__file__).resolve().parents[1]
    digest = hashlib.sha256()
    for package in CODE_PACKAGES:
        for source in sorted((root / package).rglob("*.py")):
            digest.update(source.relative_to(root).as_posix().encode())
            digest.update(source.read_bytes())
    return tool_version(), digest.hexdigest()[:12]


def describe_code(identity: tuple[str, str]) -> str:
    """A `code_identity` as said: "0.1.0 (code 3f2a9c0d1b7e)"."""
    version, digest = identity
    return f"{version} (code {digest})"


def check_worker_code(client: Client, address: str) -> None:
    """ConfigError naming the running workers of an existing cluster that cannot import kitti-pu,
    or run other kitti-pu code than this process (by `code_identity`'s digest: the version, read
    from an installation's metadata, may lag the code on a path). A run on them crashed with a
    traceback (exit 1) or lost its workers to the first task they could not unpickle, and reported
    "no workers" (an external-cluster user's trial). A worker that joins later is checked by the
    run's `WorkerSetup` (`unfit_worker`), and the run stops when it refuses one; one that cannot
    import kitti-pu cannot start while the setup is registered."""
    mine = code_identity()
    running = [worker for worker, info in client.scheduler_info().get("workers", {}).items()
               if info.get("status", "running") == "running"]
    found = client.run(code_identity, workers=running, on_error="return") if running else {}
    failed = {worker: first_line(result) for worker, result in found.items() if isinstance(result, BaseException)}
    other = {worker: tuple(result) for worker, result in found.items()
             if not isinstance(result, BaseException) and tuple(result)[1] != mine[1]}
    install = (f"install kitti-pu {describe_code(mine)} in the workers' environment (`pip install` of this "
               "checkout or release) and restart them")
    if failed:
        named = "; ".join(f"{worker}: {reason}" for worker, reason in sorted(failed.items()))
        raise ConfigError(f"dask.scheduler: {address}: worker(s) that cannot run kitti-pu ({named}); {install}")
    if other:
        named = ", ".join(f"{worker} runs {describe_code(identity)}" for worker, identity in sorted(other.items()))
        raise ConfigError(f"dask.scheduler: {address}: worker(s) on other kitti-pu code than this one, "
                          f"{describe_code(mine)}: {named}; {install}")


def unfit_worker(worker: object, code: str) -> str | None:
    """Why `worker` must make no frame of a run on code of digest `code`: it runs other kitti-pu
    code, or its memory limit is below `MIN_WORKER_MEMORY` (what `check_worker_code` and
    `check_worker_memory` refuse in the workers a run finds); None when it may."""
    from .preflight import MIN_WORKER_MEMORY

    address = getattr(worker, "address", "this worker")
    identity = code_identity()
    if identity[1] != code:
        return (f"worker {address} joined the cluster during the run on other kitti-pu code, "
                f"{describe_code(identity)}, than the run's (code {code}): install the run's kitti-pu in its "
                "environment and restart it")
    limit = getattr(getattr(worker, "memory_manager", None), "memory_limit", None)
    if limit and limit < MIN_WORKER_MEMORY:
        return (f"worker {address} joined the cluster during the run with a memory limit of {limit / 1e9:.2f} GB, "
                f"below the {MIN_WORKER_MEMORY / 1e9:.2f} GB a worker needs: start it with a larger --memory-limit")
    return None


def worker_refusals(client: Client, addresses: list[str]) -> dict[str, str | None]:
    """The run's setup's verdict on each worker of `addresses`: the reason it refused it
    (`unfit_worker`), or None when it took it; a worker whose setup has not run yet, or that
    could not be asked (gone meanwhile), is left out."""
    if not addresses:
        return {}
    found = client.run(lambda dask_worker: (hasattr(dask_worker, "kitti_pu_refused"),  # by value: the worker's
                                            getattr(dask_worker, "kitti_pu_refused", None)),  # code may differ
                       workers=addresses, on_error="return")
    return {address: answer[1] for address, answer in found.items()
            if not isinstance(answer, BaseException) and answer[0]}


@dataclass(frozen=True)
class ClusterPlan:
    """How many LocalCluster workers, frames at once per worker (Dask threads) and torch threads
    per frame a run uses."""

    workers: int
    torch_threads: int
    threads_per_worker: int = 1


def plan_cluster(config: PipelineConfig) -> ClusterPlan:
    """Size the LocalCluster to the machine: one worker per core (at most 4) by default.

    The cores the workers leave go to more frames at once in each worker (Dask threads), not to
    torch threads, unless `dask.threads_per_worker` or `dask.torch_threads` is set: one worker
    running a frame per core made nearly twice the frames per minute of one frame on every core's
    torch thread (docs/speed.md, "Worker layouts"). Torch threads are then the cores left per frame,
    at least 1.
    """
    cores = os.cpu_count() or 1
    section = config.dask
    workers = section.n_workers or max(1, min(cores, 4))
    spare = max(1, cores // workers)
    if section.threads_per_worker is not None:
        threads_per_worker = section.threads_per_worker
    else:
        threads_per_worker = 1 if section.torch_threads else spare
    torch_threads = section.torch_threads or max(1, cores // (workers * threads_per_worker))
    return ClusterPlan(workers=workers, torch_threads=torch_threads, threads_per_worker=threads_per_worker)


@contextlib.contextmanager
def open_client(config: PipelineConfig, plan: ClusterPlan) -> Iterator[Client]:
    """A client on `config.dask.scheduler`, or on a new LocalCluster closed on exit."""
    if config.dask.scheduler:
        client = _checked_client(config.dask.scheduler)
        setup: WorkerSetup | None = None
        try:
            by_worker = {} if config.dask.torch_threads else threads_on_each_worker(client)
            remove_stale_setups(client)
            setup = WorkerSetup(config.dask.torch_threads, by_worker, open3d=config.ground.method == "ransac",
                                owner=client.id, code=code_identity()[1])
            register_setup(client, setup)
            yield client
        finally:
            _unregister_setup(client, setup)
            client.close()
        return
    from .preflight import worker_memory_bytes

    limit = config.dask.memory_limit
    with local_cluster(plan.workers, plan.threads_per_worker, limit if limit == "auto" else worker_memory_bytes(limit),
                       config.dask.dashboard) as cluster, Client(cluster) as client:
        register_setup(client, WorkerSetup(plan.torch_threads, open3d=config.ground.method == "ransac",
                                           exit_fast=True, ignore_sigint=True))
        yield client


def _checked_client(address: str) -> Client:
    """A client on the scheduler at `address` whose workers can run this kitti-pu
    (`check_worker_memory`, `check_worker_code`); ConfigError when it does not answer within 20 s
    or a worker cannot (the client closed)."""
    try:
        client = Client(address, timeout="20s")
    except OSError as error:
        raise ConfigError(f"dask.scheduler: cannot reach {address} ({error})") from None
    try:
        check_worker_memory(client, address)
        check_worker_code(client, address)
    except BaseException:
        client.close()
        raise
    return client


def describe_existing_cluster(address: str) -> str:
    """What `kitti-pu run --dry-run` says of the cluster at `address` once it has checked it as a run
    does before its first frame (`_checked_client`): its workers and threads. It never contacted
    one, and passed clusters a run then refused (an external-cluster user's trial)."""
    client = _checked_client(address)
    try:
        workers = client.scheduler_info().get("workers", {})
        return (f"{address} answers: {counted(len(workers), 'worker')}, {counted(cluster_threads(client), 'thread')}, "
                f"each on this kitti-pu, {describe_code(code_identity())}" if workers else
                f"{address} answers, with no worker yet (a run waits up to dask.no_workers_timeout for one)")
    finally:
        client.close()


#: Registrations of the worker setup tried before a run counts its cluster lost, and the pause
#: between them (seconds).
SETUP_ATTEMPTS = 3
SETUP_RETRY_PAUSE_S = 1.0


class SetupFailed(ConnectionError):
    """The worker setup did not reach the cluster (`register_setup`), and why: a run's frames are
    then not reached, as with a lost cluster."""


def register_setup(client: Client, setup: WorkerSetup) -> None:
    """Register `setup` on the cluster's workers (and those that join later). The scheduler keeps
    the plugin, then sends it to every worker, and a worker that dies meanwhile (killed, or
    restarted by its nanny) fails the whole call with a CommClosedError, which a run took for a
    lost cluster: exit 3, every frame interrupted, the scheduler and the other workers fine (an
    operator's trial). So it is sent again, under the same name, up to `SETUP_ATTEMPTS` times; a
    cluster that is really gone fails every attempt and raises the last error; a SetupFailed says
    why when the scheduler still answers (a worker closed each time) or the client closed meanwhile
    (the scheduler lost)."""
    for attempt in range(1, SETUP_ATTEMPTS + 1):
        try:
            client.register_plugin(setup)
            return
        except OSError as error:  # CommClosedError among them
            if attempt < SETUP_ATTEMPTS:
                time.sleep(SETUP_RETRY_PAUSE_S)
            elif client.status == "running":  # the scheduler answers: a worker closed each time (a
                # worker crashing at start was reported as "the cluster was lost": an operator's trial)
                raise SetupFailed(f"a worker closed during each of {SETUP_ATTEMPTS} attempts to set up the "
                                  f"workers (one crashing at start? its log says why): {first_line(error)}") from None
            else:
                raise
        except AttributeError:  # Dask's, once its client has closed: a run whose scheduler died here
            # crashed with exit 1 (an operator's trial); a lost cluster is an OSError to the runner
            if client.status not in ("closing", "closed"):
                raise
            raise SetupFailed("the scheduler was lost while the run set up its workers: the Dask client "
                              "could not reconnect and closed") from None


def remove_stale_setups(client: Client) -> list[str]:
    """Take off a user's cluster the worker setups of runs that ended without taking theirs off
    (killed with SIGKILL, or their machine lost): they stayed registered for good, and every
    worker joining later was prepared with a dead run's choices (an operator's trial). A setup
    whose client is still connected (a run going on) stays, and so does everything when the
    scheduler cannot be asked (best effort: the run goes on). Returns the names removed."""
    prefix = f"{WorkerSetup.NAME_PREFIX}-"
    try:
        # a lambda, sent by value: the scheduler need not have this package installed
        plugins, clients = client.run_on_scheduler(
            lambda dask_scheduler: (list(dask_scheduler.worker_plugins), list(dask_scheduler.clients)))
    except Exception:  # noqa: BLE001 (an older scheduler, a refused call: nothing removed)
        return []
    stale = [name for name in plugins if name.startswith(prefix) and name[len(prefix):] not in clients]
    if stale:
        with contextlib.suppress(Exception):  # best effort, as above
            take_off_setups(client, stale)
    return stale


def take_off_setups(client: Client, names: list[str]) -> None:
    """Take the worker setups `names` off the scheduler's registry, so no worker joining later gets
    them, and have it tell its workers to tear them down, without waiting for their answers.

    `Client.unregister_worker_plugin` waits for every worker's answer: a worker that stayed
    "closing" (its own setup failed as it joined) never answered, and a run whose frames were all
    written waited on it for minutes, until Dask's heartbeat timeout removed it (an
    external-cluster user's trial)."""
    def take_off(dask_scheduler: Any, names: list[str] = list(names)) -> None:
        # the broadcasts' tasks are kept on the scheduler until done: asyncio holds only weak references
        pending = dask_scheduler.__dict__.setdefault("kitti_pu_setup_removals", set())
        for name in names:
            if dask_scheduler.worker_plugins.pop(name, None) is not None:
                task = asyncio.ensure_future(dask_scheduler.broadcast(msg={"op": "plugin-remove", "name": name},
                                                                      on_error="ignore"))
                pending.add(task)
                task.add_done_callback(pending.discard)

    client.run_on_scheduler(take_off)  # a nested function, sent by value: the scheduler need not have this package


def _unregister_setup(client: Client, setup: WorkerSetup | None) -> None:
    """Take the run's `setup` (None: not registered) off a user's cluster, so that workers joining
    after the run (its own next run's, or another job's) are not prepared with this run's choices;
    a cluster already gone is left as it is."""
    if setup is None or client.status != "running":
        return
    with contextlib.suppress(Exception):  # the scheduler may be going away: the run's result stands
        take_off_setups(client, [setup.name])


#: Dask's nanny starts every worker with MALLOC_TRIM_THRESHOLD_=65536 so that freed memory goes
#: back to the OS. Setting that variable at all switches off glibc's dynamic mmap threshold: every
#: array over 128 KiB is then mmapped and page-faulted afresh, and the numpy stages ran about 2x
#: slower than in a plain process (ground: 189 vs 83 ms per frame, side by side, one thread).
#: Worker memory here is bounded by the frames in flight, so glibc's defaults are kept.
KEEP_GLIBC_MALLOC_DEFAULTS = {"distributed.nanny.pre-spawn-environ.MALLOC_TRIM_THRESHOLD_": None}

#: Each worker's statistical profiler samples the running task's stack every 10 ms and keeps one
#: call tree per second for the last 1,000 seconds, so over a run's first 1,000 seconds the worker
#: holds more and more of them (measured with `bench/memory.py`: docs/results.md, "The workers'
#: statistical profiler"). Without a dashboard nothing reads those trees, so the tool's own workers
#: run without it; with `dask.dashboard: true` it stays on for the dashboard's profile page.
NO_WORKER_PROFILER = {"distributed.worker.profile.enabled": False}


@contextlib.contextmanager
def local_cluster(workers: int, threads_per_worker: int = 1, memory_limit: str | float = "auto",
                  dashboard: bool = False) -> Iterator[LocalCluster]:
    """A LocalCluster of `workers` processes with glibc's malloc defaults (see
    KEEP_GLIBC_MALLOC_DEFAULTS) and, without the dashboard, no worker profiler
    (NO_WORKER_PROFILER), closed on exit."""
    settings = {**KEEP_GLIBC_MALLOC_DEFAULTS, **({} if dashboard else NO_WORKER_PROFILER)}
    # SIGINT is held back in this process while the cluster starts: one in the meantime reaches it
    # once the cluster has started, inside the `with` that closes it (it interrupted the start, and
    # the half-started cluster's exit handler then failed with an AssertionError). The worker
    # processes do not inherit the held-back signal (their SigBlk is 0 in a fresh process); they
    # ignore SIGINT once the worker setup is registered (`WorkerSetup`, ignore_sigint), and one in
    # their first seconds may still print a KeyboardInterrupt traceback
    held = _block_sigint()
    try:
        with dask.config.set(settings):
            cluster = LocalCluster(
                n_workers=workers,
                threads_per_worker=threads_per_worker,
                processes=True,
                memory_limit=memory_limit,
                # dashboard_address=None still listens on 8787 (dask/distributed#8136): the HTTP server
                # (without the dashboard, health and metrics routes only) takes a free loopback port.
                dashboard_address="127.0.0.1:0",  # the run prints the dashboard's link when it is on
                scheduler_kwargs={"dashboard": dashboard},
            )
    except BaseException:
        _restore_signal_mask(held)
        raise
    with cluster:
        _restore_signal_mask(held)
        yield cluster


def _block_sigint() -> set[int] | None:
    """Block SIGINT in this thread (the main one; POSIX), returning the mask to restore; None where
    nothing was changed (another thread, or no signal masks)."""
    if not hasattr(signal, "pthread_sigmask") or threading.current_thread() is not threading.main_thread():
        return None
    return signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})


def _restore_signal_mask(mask: set[int] | None) -> None:
    """Put back the mask `_block_sigint` returned (a SIGINT that came meanwhile is delivered now)."""
    if mask is not None:
        signal.pthread_sigmask(signal.SIG_SETMASK, mask)
