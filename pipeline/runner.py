"""A run: check everything, lock the output folder, skip or replace finished frames, push the rest
through Dask, summarise what is on disk.

Each frame is a chain of tasks on a `distributed` client, one per `pipeline.chain.Step`
(load -> ground -> tile -> upsample -> stitch -> snap -> fill -> write), then its report. At most
`max_in_flight` frames are submitted at once, so memory stays flat however long the sequence is. A
failing frame fails alone: its error is recorded, the other frames go on, and the write stage's
atomic renames leave nothing half-written. An interrupted run (Ctrl-C, SIGTERM) still writes its
summary, with the frames done so far.
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import signal
import sys
import threading
import time
import uuid
from collections import Counter
from collections.abc import Callable, Iterator, Mapping
from pathlib import Path

from distributed import Client, Future, as_completed
from filelock import FileLock, Timeout
from tqdm import tqdm

from stages import load, write, write_kitti
from stages.discovery import content_digest
from stages.errors import StageError, first_line
from stages.temporaries import replace_atomically

from .chain import Chain, provenance, report
from .cluster import (FRAME_END_PREFIX, ClusterPlan, SetupFailed, cluster_threads, open_client, plan_cluster,
                      on_prepared_worker, share_threads_again, with_worker_torch_threads, worker_refusals)
from .config import ConfigError, PipelineConfig, absolute
from .export import RECORD_ONLY_REASONS, export_frame, matching_stored_formats, stored_formats_to_export
from .output_lock import LOCK_NAME, output_busy
from .placement import FramePlacement
from .preflight import MIN_WORKER_MEMORY, check_writable, metadata_files, preflight
from .resume import complete_on_disk, decide, metadata_now, same_scan_elsewhere, skipped_report, stored_metadata
from .run_marks import (RUNS_DIR, clear_marks, describe_runs, frames_to_check, leave_mark, settle_marks,
                        unfinished_runs)
from .summary import STORED_COUNTS, FrameReport, RunSummary, SummaryWriteError, Terminated

#: The step whose task is most of a frame's time, followed by `FramePlacement`.
NETWORK_STEP = "upsample"
#: Seconds a run waits for its output folder's lock before it says another run holds it.
LOCK_PATIENCE_S = 1.0
#: The key of the run's identifier in every file's record (`stages.write.frame_record`).
RUN_ID_KEY = "run_id"


class OutputBusy(RuntimeError):
    """Another run holds the output folder's lock; nothing was done."""


def _busy(out_dir: Path) -> OutputBusy:
    return OutputBusy(f"output.dir: another kitti-pu run is writing to {out_dir} (lock {out_dir / LOCK_NAME}); "
                      "nothing was done")


class NoWorkers(RuntimeError):
    """The cluster had no running worker (none, or all paused for memory) for
    `dask.no_workers_timeout` seconds: the run stops."""


#: What a run that lost its scheduler says (once, and in its frames' reports).
SCHEDULER_LOST = "this run lost the Dask scheduler: its client could not reconnect and closed"


class SchedulerLost(NoWorkers):
    """The run's client lost the scheduler and closed (Dask gave up reconnecting): no frame can
    finish, and the run stops as it does without workers."""


class RunInterrupted(Exception):
    """The run was stopped by a signal; `summary` holds what was done (and is written to disk), and
    `summary.exit_code` the exit status (130 or 143)."""

    def __init__(self, summary: RunSummary) -> None:
        earlier = summary.count("skipped")  # finished by earlier runs: on disk as well
        super().__init__(f"interrupted by {summary.interrupted_by}: "
                         f"{summary.count('done') + summary.count('replaced')} of {len(summary.frames)} frames done"
                         + (f", {earlier} finished before" if earlier else ""))
        self.summary = summary


def _interrupted_report(ref: load.FrameRef, *notes: str) -> FrameReport:
    """The report of a frame this run did not finish: never reached, or cancelled by the cluster."""
    return FrameReport(key=ref.key, dataset=ref.dataset, sequence=ref.sequence, index=ref.index,
                       status="interrupted", source=str(ref.source), notes=list(notes))


def _failed_report(ref: load.FrameRef, error: BaseException) -> FrameReport:
    stage = error.stage if isinstance(error, StageError) else None
    return FrameReport(
        key=ref.key,
        dataset=ref.dataset,
        sequence=ref.sequence,
        index=ref.index,
        status="failed",
        source=str(ref.source),
        error=str(error) if isinstance(error, StageError) else f"{type(error).__name__}: {error}",
        failed_stage=stage,
        points_in=getattr(error, "points_in", 0),  # a frame failing at write reported 0 (an operator's trial)
    )


def run_pipeline(config: PipelineConfig, progress: bool = True,
                 on_report: Callable[[FrameReport], None] | None = None,
                 signals_held: contextlib.ExitStack | None = None) -> RunSummary:
    """Process every selected frame that is not already finished and return the run's summary.

    Args:
        config: a validated configuration (see `pipeline.config.load_config`).
        progress: show a progress bar on stderr.
        on_report: called with each frame's report as the frame finishes (processed or failed;
            skipped frames are reported before any work starts; a frame whose report the cluster
            lost but whose files are complete on disk, when the run settles its frames).
        signals_held: where the run's last steps hold SIGINT and SIGTERM (`stop_signals_held`,
            from settling the frames on): a caller that still reports the result passes a stack
            and closes it when done (the CLI, after printing the summary); None releases them when
            the run returns.

    Returns:
        The `RunSummary`, also written to `<output.dir>/summary.json` and
        `<output.dir>/runs/<UTC time>.json`.

    Raises:
        ConfigError: bad configuration, input location, weights, cluster settings or unwritable
            output folder (`pipeline.preflight`). Nothing is processed then.
        OutputBusy: another run holds the output folder. Nothing is processed then.
        RunInterrupted: a signal stopped the run; the summary of what was done is written.
    """
    started = time.perf_counter()
    given = config  # the weights as given: frames versions before `cadpu.weights.portable_name` wrote hashed them so
    if output_busy(Path(config.output.dir)):  # said at once, before the scans and the weights are read
        raise _busy(absolute(config.output.dir))
    config, refs, checksum = preflight(config)
    out_dir = Path(config.output.dir)
    existed = out_dir.exists()
    check_writable(out_dir)
    # a moment's patience: `kitti-pu info` probes the lock with a shared one for an instant
    lock = FileLock(out_dir / LOCK_NAME, timeout=LOCK_PATIENCE_S)
    try:
        lock.acquire()
    except Timeout:  # it began meanwhile
        raise _busy(out_dir) from None
    own_hold = contextlib.ExitStack() if signals_held is None else None
    held = signals_held if signals_held is not None else own_hold
    try:
        try:
            return _run_locked(config, refs, checksum, started, progress, on_report, held, earlier_hashes(given, config))
        finally:
            try:
                lock.release()
            finally:
                if own_hold is not None:
                    own_hold.close()
    except ConfigError:  # found only once running (an unreachable scheduler): nothing was done
        if not existed:
            _remove_unused_output_dir(out_dir)
        raise


def _remove_unused_output_dir(out_dir: Path) -> None:
    """Remove the output folder this run created, when it holds nothing but the run's lock file and
    empty temporaries and runs folders (a refused run then leaves nothing behind)."""
    for folder in (out_dir / write.TEMPORARY_DIR, out_dir / RUNS_DIR):
        if folder.is_dir() and not any(folder.iterdir()):
            folder.rmdir()
    if {entry.name for entry in out_dir.iterdir()} <= {LOCK_NAME}:
        (out_dir / LOCK_NAME).unlink(missing_ok=True)
        out_dir.rmdir()


@dataclasses.dataclass
class FramePlan:
    """What a run does with each selected frame (`plan_frames`): skip it (with its report), write
    it in the formats it lacks from its stored files (exports: with the formats they are in), or
    run it through the chain (todo; replaced: why, for those that replace finished files)."""

    skipped: list[tuple[load.FrameRef, FrameReport]] = dataclasses.field(default_factory=list)
    exports: list[tuple[load.FrameRef, tuple[str, ...]]] = dataclasses.field(default_factory=list)
    todo: list[load.FrameRef] = dataclasses.field(default_factory=list)
    replaced: dict[str, str] = dataclasses.field(default_factory=dict)
    #: frames that fail before they run, with the error: SemanticKITTI labels that do not fit their
    #: scan, a calibration or timestamps file not there, or no line for them in the timestamps file
    #: (no cluster starts for them alone)
    refused: list[tuple[load.FrameRef, StageError]] = dataclasses.field(default_factory=list)
    #: why frames were refused ("for their labels", "for a missing metadata file", "for a missing
    #: timestamp") -> how many
    refusals: Counter[str] = dataclasses.field(default_factory=Counter)
    #: finished frames whose timestamp or pose changed, of the exports: key -> the record the
    #: dataset gives them now, written into all their files from the stored points (`pipeline.export`)
    rerecorded: dict[str, dict[str, str]] = dataclasses.field(default_factory=dict)
    #: finished frames whose SemanticKITTI labels in the KITTI mirror the run brings up to date, by
    #: what it does to them ("written", "removed": `stages.write_kitti.labels_update_due`)
    label_updates: Counter[str] = dataclasses.field(default_factory=Counter)

    def describe(self) -> str:
        """One line: how many frames of each kind, with the reasons for replacing."""
        refused = (f"; {len(self.refused)} that would fail ("
                   + ", ".join(f"{count} {why}" for why, count in sorted(self.refusals.items())) + ")"
                   if self.refused else "")
        labels = ("; SemanticKITTI labels of finished frames to bring up to date in the KITTI mirror: "
                  + ", ".join(f"{count} {what}" for what, count in sorted(self.label_updates.items()))
                  if self.label_updates else "")
        network = Counter(reason for key, reason in self.replaced.items() if key not in self.rerecorded)
        why = f" ({', '.join(f'{count} {reason}' for reason, count in sorted(network.items()))})" if network else ""
        rerecorded = (f", of which {len(self.rerecorded)} only take a new timestamp, pose or scan path (their points "
                      "unchanged)" if self.rerecorded else "")
        return (f"{len(self.todo)} to run through the network, of which {sum(network.values())} replace finished "
                f"files{why}; {len(self.exports)} to write in added formats from their stored files{rerecorded}; "
                f"{len(self.skipped)} finished, skipped{refused}{labels}")


def plan_frames(config: PipelineConfig, refs: list[load.FrameRef], checksum: str,
                also_configs: tuple[str, ...] = ()) -> FramePlan:
    """Decide, from the files in `config.output.dir`, what a run does with each of `refs`
    (`pipeline.resume.decide`, `pipeline.export`); reads the files' records, writes nothing.

    Args:
        config: the resolved configuration (`pipeline.preflight`). checksum: the model's sha256.
        also_configs: other hashes of this configuration that finished frames may carry.
    """
    out_dir = Path(config.output.dir)
    config_hash = config.output_hash()
    formats = tuple(config.output.formats)
    plan = FramePlan()
    absent = functools.cache(_absent_metadata)  # per drive or sequence: its frames share the files
    lines = functools.cache(load.frame_lines)  # of each timestamps file, read once
    for ref in refs:
        refused = write_kitti.labels_problem(ref.dataset, ref.source) if "kitti" in formats else None
        if refused is not None:  # its outputs, finished or not, stay as they are
            plan.refused.append((ref, refused))
            plan.refusals["for their labels"] += 1
            continue
        paths = write.output_paths(out_dir, ref.dataset, ref.sequence, ref.index, formats, ref.source)
        now = functools.cache(functools.partial(metadata_now, ref))  # read once, when needed
        content = functools.cache(functools.partial(content_digest, ref.source))  # read when the scan's state moved

        def metadata(now: Callable[[], tuple] = now) -> Mapping[str, str] | None:
            return now()[0]

        decision = decide(paths, config_hash, checksum, config.output.overwrite, ref.fingerprint,
                          also_configs=also_configs, metadata=metadata, content=content)
        if decision.action == "skip":
            skipped = skipped_report(ref, paths, decision.stored)
            current = metadata()
            # judged without them, what it records could not be checked: said (a pose unknown before
            # and now, a packet never there, is nothing new)
            unchecked = current is None or ("pose" not in current and decision.stored.get("pose"))
            if unchecked and (problem := now()[1]):
                skipped.notes.append(f"kept as stored, though its timestamp or pose cannot be read now: {problem}")
            plan.skipped.append((ref, skipped))
            if "kitti" in formats and (due := write_kitti.labels_update_due(ref.dataset, ref.source, paths["kitti"])):
                plan.label_updates[due] += 1
            continue
        # the run's formats whose files are complete, each read once (a footer or header)
        complete = ({name: path for name, path in paths.items() if write.is_complete({name: path})}
                    if decision.action == "do" else {})
        if decision.action == "do" and not config.output.overwrite:
            stored_formats = stored_formats_to_export(ref, out_dir, formats, config_hash, checksum, also_configs,
                                                      metadata)
            # finished in another format: written from it, no network; unless a complete file of the
            # run's formats records another scan, configuration or model (a kill between two formats'
            # renames): then judged below, and written again in every format
            if stored_formats and set(complete) <= set(stored_formats):
                plan.exports.append((ref, stored_formats))
                continue
        if decision.action == "do":
            # complete files in some of the formats, of another scan, configuration or model: this
            # run replaces them too (it overwrote them as "done", without a word; with --overwrite, too)
            if complete:
                judged = decide(complete, config_hash, checksum, False, ref.fingerprint, also_configs=also_configs,
                                metadata=metadata, content=content)
                decision = judged if judged.action == "replace" else decision
        if not config.output.overwrite and (decision.reason in RECORD_ONLY_REASONS or decision.reason is None):
            # the same points with a new timestamp, pose or scan path (also with a format added):
            # written from the stored files, without the network
            record_only = _record_only_change(ref, out_dir, config_hash, checksum, also_configs, metadata, content)
            if record_only is not None:
                stored_formats, reason, current = record_only
                plan.exports.append((ref, stored_formats))
                plan.replaced[ref.key] = reason
                plan.rerecorded[ref.key] = current
                continue
        files = tuple(metadata_files(ref))  # the timestamps file last
        missing = absent(files)
        # it would fail at load, naming the file: failed here, without a cluster started for it
        # (its finished files, if any, stay as they are); a growing dataset's newest scan may come
        # before its line in the timestamps file (an operator's trial)
        if missing:
            plan.refused.append((ref, load.missing_metadata_error(ref, missing[0], missing[1:])))
            plan.refusals["for a missing metadata file"] += 1
            continue
        if files and lines(files[-1]) <= ref.index:
            plan.refused.append((ref, load.missing_timestamp_error(ref, files[-1])))
            plan.refusals["for a missing timestamp"] += 1
            continue
        if decision.reason:
            plan.replaced[ref.key] = decision.reason
        plan.todo.append(ref)
    if "kitti" in formats:  # a frame mirrored only under an earlier name of its scan: replaced too
        scans = {write_kitti.scan_path(out_dir, ref.dataset, ref.sequence, ref.index, ref.source): ref
                 for ref in plan.todo if ref.key not in plan.replaced}
        for scan in write_kitti.renamed_copies(list(scans)):
            plan.replaced[scans[scan].key] = "source changed"
    return plan


def _absent_metadata(files: tuple[Path, ...]) -> tuple[Path, ...]:
    """Those of a frame's metadata files (`pipeline.preflight.metadata_files`) that are not there."""
    return tuple(path for path in files if not path.is_file())


def _record_only_change(ref: load.FrameRef, out_dir: Path, config_hash: str, checksum: str,
                        also_configs: tuple[str, ...], metadata: Callable[[], Mapping[str, str] | None],
                        content: Callable[[], str]) -> tuple[tuple[str, ...], str, dict[str, str]] | None:
    """(its stored formats, the reason, the record updates) when `ref`'s stored files record this
    run's configuration and model and differ from the dataset only in what they record of the frame
    (`pipeline.export.RECORD_ONLY_REASONS`): its timestamp or pose (the updates: those the dataset
    gives now), or its scan's path or time, the bytes the same (`pipeline.resume.same_scan_elsewhere`;
    the updates: the scan's path and fingerprint now, and its timestamp and pose); else None."""
    stored_formats = matching_stored_formats(ref, out_dir, config_hash, checksum, also_configs, content=content)
    if not stored_formats:
        return None
    records = [stored_metadata(write.output_paths(out_dir, ref.dataset, ref.sequence, ref.index, (name,), ref.source))
               for name in stored_formats]
    stored = records[0]
    current = metadata()
    # any format's: a kill between two formats' renames leaves some recording the new path already
    moved = next((reason for record in records
                  if write.fingerprint_differs(record.get(write.SOURCE_KEY), ref.fingerprint)
                  and (reason := same_scan_elsewhere(record, ref.fingerprint, content)) is not None), None)
    if moved is not None:
        return stored_formats, moved, {**(current or {}), "source": ref.source, write.SOURCE_KEY: ref.fingerprint}
    if current is None:
        return None
    reason = write.metadata_change(stored, current)
    return (stored_formats, reason, dict(current)) if reason in RECORD_ONLY_REASONS else None


def earlier_hashes(given: PipelineConfig, resolved: PipelineConfig) -> tuple[str, ...]:
    """The hashes earlier versions gave this configuration (`PipelineConfig.output_hash(legacy=True)`
    of the weights as given and as resolved), other than this version's: finished frames that carry
    them count as this configuration's."""
    return tuple(sorted({given.output_hash(legacy=True), resolved.output_hash(legacy=True)} - {resolved.output_hash()}))


def _run_locked(config: PipelineConfig, refs: list[load.FrameRef], checksum: str, started: float,
                progress: bool, on_report: Callable[[FrameReport], None] | None,
                held: contextlib.ExitStack, also_configs: tuple[str, ...] = ()) -> RunSummary:
    """`run_pipeline` once the checks passed and the output folder is locked."""
    out_dir = Path(config.output.dir)
    write.sweep_stale_temporaries(out_dir)  # left by a killed run; ours are not written yet
    config_hash = config.output_hash()
    formats = tuple(config.output.formats)
    # run_id tells this run's files from an earlier run's (`_settled`)
    run_id = uuid.uuid4().hex
    metadata = provenance(config, given={"model_checksum": checksum, RUN_ID_KEY: run_id})
    told: set[str] = set()  # the frames whose report went to `on_report`

    def notify(report: FrameReport) -> None:
        told.add(report.key)
        if on_report is not None:
            on_report(report)

    if "kitti" in formats:  # an earlier version's ".BIN" copy of a frame is the frame's, renamed
        for ref in refs:
            write_kitti.adopt_case_copy(write_kitti.scan_path(out_dir, ref.dataset, ref.sequence, ref.index,
                                                              ref.source), ref.source)
    frame_plan = plan_frames(config, refs, checksum, also_configs)
    # a run killed before it settled its frames may have left files of a replaced frame's old
    # configuration in formats it did not write: this run checks every finished frame's
    unsettled = unfinished_runs(out_dir)
    if unsettled:
        tqdm.write(f"kitti-pu: {describe_runs(unsettled)} into {out_dir} did not finish (killed?): the other "
                   "formats of the frames it set out to write are checked against their files", file=sys.stderr)
    to_check = frames_to_check(unsettled)
    mark = leave_mark(out_dir, run_id, config_hash,
                      [ref.key for ref in frame_plan.todo] + [ref.key for ref, _ in frame_plan.exports])
    reports: dict[str, FrameReport] = {}
    for ref, skipped in frame_plan.skipped:
        reports[ref.key] = skipped
        notify(skipped)
    for ref, error in frame_plan.refused:
        reports[ref.key] = _failed_report(ref, error)
        notify(reports[ref.key])
    replaced, todo, exports = frame_plan.replaced, frame_plan.todo, frame_plan.exports
    if replaced:
        reasons = ", ".join(sorted(set(replaced.values())))
        # said before the frames run: one may then fail (its report says so, and what became of its files)
        again = len(replaced) - len(frame_plan.rerecorded)
        what = (" and will be done again" if not frame_plan.rerecorded else
                " and will be recorded again with their new timestamp, pose or scan path, the points unchanged"
                if not again else
                f": {again} will be done again, {len(frame_plan.rerecorded)} only recorded again with their new "
                "timestamp, pose or scan path, the points unchanged")
        tqdm.write(f"kitti-pu: warning: {len(replaced)} finished frame(s) in {out_dir} were made from another "
                   f"scan, configuration, model, timestamp or pose, or record another path of their scan "
                   f"({reasons}){what}"
                   + ("" if config.output.overwrite else "; --overwrite redoes every frame"),
                   file=sys.stderr)

    plan = plan_cluster(config)
    scheduler = config.dask.scheduler or f"LocalCluster({plan.workers} workers)"
    work = _FrameWork(config, plan, Chain(config, metadata), todo, replaced, reports, notify, progress)
    try:
        work.run(exports, lambda ref, stored: export_frame(ref, out_dir, formats, stored, {
            RUN_ID_KEY: run_id, "tool_version": metadata["tool_version"], **frame_plan.rerecorded.get(ref.key, {})},
            rewrite=ref.key in frame_plan.rerecorded))
    except ConfigError:  # found once running (an unreachable scheduler): no frame was written
        clear_marks([mark] if mark else [])
        raise
    workers, interrupted, contacted = work.workers, work.interrupted, work.contacted
    if not contacted:  # nothing for the network: no cluster was started nor contacted
        why = ("every frame failed before it ran" if frame_plan.refused and not exports and not todo and
               not frame_plan.skipped else
               "nothing to do" if not exports and not todo else "no frame needed the network" if not todo
               else "interrupted before the frames that need the network")
        scheduler = (f"{config.dask.scheduler} (not contacted: {why})" if config.dask.scheduler
                     else f"none ({why})")
    elif not work.todo and config.dask.scheduler:  # reached first, in case an added format needed it
        # it said "no worker ran a frame: the cluster failed", exit 0 (an external-cluster user's trial)
        scheduler = f"{config.dask.scheduler} (contacted: no frame needed the network)"

    held.enter_context(stop_signals_held())  # the frames are over: what the summary says must stand
    write.sweep_stale_temporaries(out_dir)  # a worker killed mid-write left its temporary behind
    frames = [_settled(ref, reports.get(ref.key), replaced.get(ref.key), out_dir, formats, config_hash, checksum,
                       run_id, also_configs,
                       check_skipped=bool(unsettled) and (to_check is None or ref.key in to_check)) for ref in refs]
    for frame in frames:  # found complete on disk, the cluster's report lost: its line too
        if frame.key not in told and frame.status in ("done", "replaced"):
            notify(frame)
    _remove_renamed_mirror_scans(refs, frames, out_dir)
    if "kitti" in formats:
        _update_mirror_metadata(refs, frames, out_dir, {ref.key for ref, _ in frame_plan.refused})
    # the frames are settled: this run's mark goes, and an earlier run's keeps those not checked now
    clear_marks([mark] if mark else [])
    settle_marks(unsettled, {frame.key for frame in frames if frame.status in ("skipped", "done", "replaced")})
    summary = RunSummary(frames=frames, wall_seconds=time.perf_counter() - started, config_hash=config_hash,
                         output_settings=config.output_settings(),
                         model_checksum=checksum, ratio=config.upsample.ratio, workers=workers,
                         scheduler=scheduler, output_dir=str(out_dir),
                         interrupted_by=None if interrupted is None else
                         "SIGTERM" if isinstance(interrupted, Terminated) else "SIGINT")
    # the run's record first: summary.json then says whether it is missing, and the exit status
    # (3) that follows from it
    stamp = time.strftime("%Y%m%dT%H%M%SZ", time.gmtime())
    record = out_dir / RUNS_DIR / f"{stamp}-{uuid.uuid4().hex[:6]}.json"
    try:
        summary.write_json(record, skipped_frames=False)
    except SummaryWriteError as error:
        summary.record_missing = str(error)
    try:
        summary.write_json(out_dir / "summary.json")
    except SummaryWriteError as error:
        summary.summary_missing = str(error)
        # an earlier run's summary.json must not stand for this one (on a full disk it did, exit 0
        # and all: an operator's trial), and its space is what the record needs to say so
        with contextlib.suppress(OSError):
            (out_dir / "summary.json").unlink()
        record_missing, summary.record_missing = summary.record_missing, None
        try:  # the record then says the summary is missing, with the exit status (3)
            summary.write_json(record, skipped_frames=False)
        except SummaryWriteError:
            summary.record_missing = record_missing
        raise
    if interrupted is not None:
        raise RunInterrupted(summary) from None
    return summary


@contextlib.contextmanager
def stop_signals_held() -> Iterator[None]:
    """While inside, SIGINT and SIGTERM are received and dropped (in the main thread; elsewhere
    signals cannot be handled and nothing changes). Around a run's last steps, once its frames are
    over: settling the frames against the disk and writing the summary. A signal there used to end
    the process with 130 or 143 after a summary saying 0 (or before any summary); the run is
    complete by then, so its summary and exit status stand."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    numbers = {signal.SIGINT, signal.SIGTERM}
    # blocked while the handlers are swapped, so that none lands between the two swaps; one
    # pending then is delivered to SIG_IGN when unblocked (POSIX only: Windows has no signal mask)
    can_block = hasattr(signal, "pthread_sigmask")
    blocked = signal.pthread_sigmask(signal.SIG_BLOCK, numbers) if can_block else set()
    try:
        previous = {number: signal.signal(number, signal.SIG_IGN) for number in sorted(numbers)}
    finally:
        if can_block:
            signal.pthread_sigmask(signal.SIG_SETMASK, blocked)
    try:
        yield
    finally:
        for number, handler in previous.items():
            if handler is not None:  # None: installed outside Python; it cannot be put back from here
                signal.signal(number, handler)


def _settled(ref: load.FrameRef, frame_report: FrameReport | None, replaced: str | None, out_dir: Path,
             formats: tuple[str, ...], config_hash: str, checksum: str, run_id: str | None = None,
             also_configs: tuple[str, ...] = (), check_skipped: bool = False) -> FrameReport:
    """A frame's final report: what the run reported, corrected by what is on disk, and the
    folder made to hold nothing stale of the frame.

    - A frame the cluster lost (no report, or a failure that is not a stage's) whose outputs this
      run wrote (their record holds `run_id`; any complete ones with this configuration and model
      when `run_id` is None) is done; one never reached is "interrupted".
    - A frame done in place of outputs of another scan, configuration or model is "replaced". Of
      any frame done now, the files in the formats this run does not write are removed when they
      record another scan, configuration or model.
    - A frame that is not done keeps no outputs of an earlier scan of its name (they are removed);
      earlier complete outputs of its own scan stay, and its report counts them.
    - With `check_skipped` (an earlier run was killed before it settled its frames:
      `pipeline.run_marks`), a skipped frame's files in the other formats are checked as a done
      frame's are.
    """
    paths = write.output_paths(out_dir, ref.dataset, ref.sequence, ref.index, formats, ref.source)
    lost = frame_report is None or frame_report.status == "interrupted" or (
        frame_report.status == "failed" and frame_report.failed_stage is None)
    if lost and complete_on_disk(paths, config_hash, checksum):
        stored = stored_metadata(paths)
        if run_id is None or stored.get(RUN_ID_KEY) == run_id:
            found = skipped_report(ref, paths, stored)
            found.status = "done"
            found.notes.append("complete on disk; the cluster did not report it")
            frame_report = found
    if frame_report is None:
        frame_report = _interrupted_report(ref)
    if frame_report.status in ("done", "replaced"):
        if replaced:
            frame_report.status = "replaced"
            frame_report.reason = replaced
            picture = write.preview_path(out_dir, ref.dataset, ref.sequence, ref.index)
            if picture.is_file() and replaced not in RECORD_ONLY_REASONS:  # it shows the output just replaced
                picture.unlink()
                frame_report.notes.append("removed its preview of the replaced output")
        frame_report.notes += _remove_stale_formats(ref, out_dir, formats, config_hash, checksum, also_configs)
    elif frame_report.status == "skipped" and check_skipped:
        frame_report.notes += _remove_stale_formats(ref, out_dir, formats, config_hash, checksum, also_configs)
    elif frame_report.status in ("failed", "interrupted"):
        _account_for_earlier_outputs(frame_report, ref, replaced, out_dir)
    return frame_report


def _update_mirror_metadata(refs: list[load.FrameRef], frames: list[FrameReport], out_dir: Path,
                            refused: set[str]) -> None:
    """Bring the KITTI mirror's copies of each selected sequence's metadata files up to date
    (`stages.write_kitti.copy_metadata`), also when no frame was written: a corrected calibration,
    or times of frames still to come, change no finished frame and reached the mirror only with the
    next frame written. So do SemanticKITTI labels the input gained or changed after its frames were
    written (`stages.write_kitti.update_labels`), with a note on the frame's report (`frames`, in
    the order of `refs`), but for the frames `refused` (keys) for labels that do not fit. A file
    that cannot be written is said in one line; the frames stand."""
    def atomic(path: Path, write_file: Callable[[Path], None]) -> None:
        replace_atomically(path, write_file, out_dir / write.TEMPORARY_DIR)

    last = {(ref.dataset, ref.sequence): ref for ref in sorted(refs, key=lambda ref: ref.index)}
    for ref in last.values():
        scan = write_kitti.scan_path(out_dir, ref.dataset, ref.sequence, ref.index, ref.source)
        if not scan.parent.is_dir():  # no frame of it mirrored (yet)
            continue
        try:
            write_kitti.copy_metadata(ref.dataset, ref.sequence, ref.index, ref.source, scan, atomic)
        except OSError as error:
            print(f"kitti-pu: warning: the KITTI mirror's metadata of {ref.dataset}/{ref.sequence} could not be "
                  f"updated ({error.strerror or error})", file=sys.stderr)
    changed: Counter[str] = Counter()
    for ref, frame_report in zip(refs, frames):
        if ref.dataset != "odometry" or ref.key in refused:
            continue  # a frame whose labels do not fit failed, and says so
        scan = write_kitti.scan_path(out_dir, ref.dataset, ref.sequence, ref.index, ref.source)
        try:
            done = write_kitti.update_labels(ref.dataset, ref.source, scan, atomic)
        except (OSError, ValueError, StageError) as error:
            print(f"kitti-pu: warning: the KITTI mirror's labels of {ref.key} could not be updated "
                  f"({getattr(error, 'strerror', None) or error})", file=sys.stderr)
            continue
        if done:  # said: a run that redid no frame changed files (a trial)
            changed[done] += 1
            frame_report.notes.append(f"its SemanticKITTI labels in the KITTI mirror {done}, from the input's")
    if changed:
        print("kitti-pu: the KITTI mirror's SemanticKITTI labels of finished frames brought up to date with the "
              "input's: " + ", ".join(f"{count} {what}" for what, count in sorted(changed.items())), file=sys.stderr)


def _remove_renamed_mirror_scans(refs: list[load.FrameRef], frames: list[FrameReport], out_dir: Path) -> None:
    """Remove the KITTI mirror's copies of `refs`' frames under an earlier name of their input file
    (`stages.write_kitti.renamed_copies`; the mirror names a scan after its input file, so a renamed
    input left the old copy beside the new one, two scans of one frame), with a note on each frame's
    report (`frames`, in the order of `refs`)."""
    if not (out_dir / "kitti").is_dir():
        return
    scans = {write_kitti.scan_path(out_dir, ref.dataset, ref.sequence, ref.index, ref.source): report
             for ref, report in zip(refs, frames)}
    for scan, copies in write_kitti.renamed_copies(list(scans)).items():
        write_kitti.remove_copies(scan, copies)
        names = ", ".join(copy.name for copy in copies)
        scans[scan].notes.append(f"removed the KITTI mirror's copy of this frame under an earlier name ({names})")


def _account_for_earlier_outputs(frame_report: FrameReport, ref: load.FrameRef, replaced: str | None,
                                 out_dir: Path) -> None:
    """For a frame this run did not do: its files of an earlier run, in every format (also those
    this run does not write, and with `--overwrite` too), are removed when they record another
    scan than `ref`'s (a scan replaced under the same name) or none; the complete ones of its own
    scan stay, and the report carries their stored counts, so that the summary adds up to the
    folder."""
    every = write.output_paths(out_dir, ref.dataset, ref.sequence, ref.index, write.FORMATS, ref.source)
    complete = {name: path for name, path in every.items() if write.is_complete({name: path})}
    other_scan = {name: path for name, path in complete.items()
                  if ref.fingerprint and write.source_changed({name: path}, ref.fingerprint)}
    if other_scan:
        write.remove_outputs(other_scan)
        frame_report.notes.append("the outputs of the earlier scan of this name were removed")
    kept = {name: path for name, path in complete.items() if name not in other_scan}
    if not kept:
        return
    stored = skipped_report(ref, kept)
    for count in STORED_COUNTS:  # every count (ground, fill and dropped were 0: an operator's trial)
        setattr(frame_report, count, getattr(stored, count))
    frame_report.outputs = stored.outputs
    why = f"; {replaced}" if replaced and replaced != "source changed" else ""
    frame_report.notes.append(f"not done now: the complete outputs of an earlier run stay in the folder{why}")


def _remove_stale_formats(ref: load.FrameRef, out_dir: Path, formats: tuple[str, ...], config_hash: str,
                          checksum: str, also_configs: tuple[str, ...] = ()) -> list[str]:
    """Remove a frame's files in the formats this run did not write that record another scan,
    configuration, model, timestamp or pose than the files just written (files that record none of
    these, from an earlier version, are left). Returns a note per format removed."""
    notes = []
    written: dict[str, str] | None = None
    for name in write.FORMATS:
        if name in formats:
            continue
        other = write.output_paths(out_dir, ref.dataset, ref.sequence, ref.index, (name,), ref.source)
        if not other[name].is_file():
            continue
        if written is None:
            written = stored_metadata(write.output_paths(out_dir, ref.dataset, ref.sequence, ref.index, formats,
                                                         ref.source))
        record = stored_metadata(other)
        # the scan as the new files were read from it: it may have been replaced since discovery
        fingerprint = written.get(write.SOURCE_KEY) or ref.fingerprint
        differs = (record.get("config_hash", config_hash) not in (config_hash, *also_configs)
                   or record.get("model_checksum", checksum) != checksum
                   or bool(fingerprint and write.SOURCE_KEY in record
                           and write.fingerprint_differs(record[write.SOURCE_KEY], fingerprint))
                   or bool(written) and write.metadata_change(record, written) is not None)
        if differs:
            write.remove_outputs(other)
            notes.append(f"removed its {name} file of another scan, configuration, model, timestamp or pose")
    return notes


def _submit_chain(client: Client, chain: Chain, ref: load.FrameRef, token: str,
                  worker: str | None = None) -> tuple[Future, Future | None]:
    """Submit one task per step of the chain for one frame, then its report, all on `worker` when
    given (loosely: elsewhere if it leaves; `pipeline.placement`).

    Returns the future of the report (a FrameReport, or the StageError of the step that failed)
    and that of the network step (None when the chain has none).
    """
    name = f"{ref.dataset}-{ref.sequence}-{ref.index:06d}-{token}"
    where = {} if worker is None else {"workers": [worker], "allow_other_workers": True}
    subject, network_step = ref, None
    for step in chain.steps:
        if step.name == NETWORK_STEP:  # torch's threads as the worker's setup chose, in the thread that runs it
            subject = network_step = client.submit(with_worker_torch_threads, step, subject, key=f"{step.name}-{name}",
                                                   **where)
        else:  # through the check of a worker the run's setup refused, as every task of the frame
            subject = client.submit(on_prepared_worker, step, subject, key=f"{step.name}-{name}", **where)
    return client.submit(on_prepared_worker, report, subject, key=f"{FRAME_END_PREFIX}{name}", **where), network_step


class _FrameWork:
    """The frames of a run that need work: formats added from stored files (`export_frame`), and
    frames for the network on the cluster. Each frame's report goes into `reports` and to `notify`.

    The cluster is reached before anything is written (an unreachable scheduler stops the run with
    the folder as it was). A stop (SIGINT, SIGTERM), a cluster without running workers or a lost
    cluster end the work: `interrupted` holds a stop, and the frames not reached get reports saying
    why. `workers` is the count the cluster had, `contacted` whether it was started or reached.
    A stop that comes once every frame has its report, while the cluster closes, stops nothing and
    is dropped: the run ends as one that did all its frames (it exited 130 or 143, "6 of 6 frames
    done", which a scheduler reads as a run to repeat: an operator's trial).
    """

    def __init__(self, config: PipelineConfig, plan: ClusterPlan, chain: Chain, todo: list[load.FrameRef],
                 replaced: dict[str, str], reports: dict[str, FrameReport],
                 notify: Callable[[FrameReport], None], progress: bool) -> None:
        self.config, self.plan, self.chain, self.todo = config, plan, chain, todo
        self.replaced, self.reports, self.notify, self.progress = replaced, reports, notify, progress
        self.client: Client | None = None
        self.contacted = False
        self.workers = 0
        self.interrupted: BaseException | None = None

    def run(self, exports: list[tuple[load.FrameRef, tuple[str, ...]]],
            export: Callable[[load.FrameRef, tuple[str, ...]], FrameReport | None]) -> None:
        """Reach the cluster when frames need the network, add the formats of `exports` (`export`
        returns None for a frame whose stored files are damaged: it joins the network's frames),
        then run the network's frames."""
        frames_over = False
        try:  # a stop before every frame has its report is taken; one while the cluster closes after, dropped
            with contextlib.ExitStack() as self._cluster:
                # an added format may find its stored file damaged and need the network after all:
                # an existing cluster is reached first, so that an unreachable one stops the run
                # before anything is written (a local one is started only when needed)
                if self.todo or (exports and self.config.dask.scheduler):
                    self._guarded(self._connect)
                if self.interrupted is None and (self.client is not None or not self.todo):
                    self._export(exports, export)
                if self.todo and self.interrupted is None and (self.client is not None or not self.contacted):
                    self._guarded(self._process)
                frames_over = self.interrupted is None
        except (KeyboardInterrupt, Terminated) as stop:
            if not frames_over:
                self.interrupted = self.interrupted or stop

    def _guarded(self, step: Callable[[], None]) -> None:
        """Run `step` (which contacts the cluster), turning a stop, a cluster without running
        workers or a lost cluster into the reports of the frames not reached."""
        try:
            step()
        except (KeyboardInterrupt, Terminated) as stop:
            self.interrupted = stop
        except NoWorkers as error:  # the frames not done are "interrupted" (`_settled`), said once here
            self._not_reached(str(error))
        except SetupFailed as error:  # says why itself
            self._not_reached(str(error))
        except (OSError, RuntimeError) as error:  # the cluster went away (not a frame's fault): not reached
            self._not_reached(f"the cluster was lost ({type(error).__name__}: {first_line(error)})")
        except AttributeError as error:  # what Dask raises for a call on a client that has closed (its
            # scheduler comm is None); any other AttributeError is a bug and goes on up
            if self.client is None or self.client.status not in ("closing", "closed"):
                raise
            self._not_reached(f"{SCHEDULER_LOST} ({type(error).__name__}: {first_line(error)})")

    def _not_reached(self, why: str) -> None:
        print(f"kitti-pu: {why}; stopping the run", file=sys.stderr)
        for ref in self.todo:
            self.reports.setdefault(ref.key, _interrupted_report(ref, why))

    def _connect(self) -> None:
        self.contacted = True
        self.client = self._cluster.enter_context(open_client(self.config, self.plan))
        if self.config.dask.dashboard:  # on a free loopback port: say which
            print(f"kitti-pu: Dask dashboard at {self.client.dashboard_link}", file=sys.stderr)

    def _export(self, exports: list[tuple[load.FrameRef, tuple[str, ...]]],
                export: Callable[[load.FrameRef, tuple[str, ...]], FrameReport | None]) -> None:
        try:
            for ref, stored_formats in tqdm(exports, unit="frame", disable=not self.progress or not exports,
                                            desc="kitti-pu: added formats"):
                exported = export(ref, stored_formats)
                if exported is None:  # its stored files are damaged inside: done in full, and said
                    self.todo.append(ref)
                    self.replaced[ref.key] = "stored files damaged"
                    tqdm.write(f"kitti-pu: warning: the stored files of {ref.key} do not read back (damaged): "
                               "done again through the network", file=sys.stderr)
                    continue
                self._report(ref, exported)
        except (KeyboardInterrupt, Terminated) as stop:
            self.interrupted = stop

    def _process(self) -> None:
        if self.client is None:
            self._connect()
        client, dask_settings = self.client, self.config.dask
        self.workers = _wait_for_workers(client, dask_settings.no_workers_timeout)
        threads = cluster_threads(client) if dask_settings.scheduler else self.workers * self.plan.threads_per_worker
        limit = dask_settings.max_in_flight or 2 * max(1, threads)
        last_count = self.workers
        judged: set[str] = set()  # workers of an existing cluster the run's setup took

        def running(addresses: list[str]) -> None:
            nonlocal last_count
            count = len(addresses)
            if dask_settings.scheduler:  # a worker that joined since on other code, or too small
                _stop_on_refused_workers(client, addresses, judged)
            if 0 < count < last_count:  # a lost worker's frames are redone on the others, and the run said
                # nothing of it (a new user's trial); none left at all is NoWorkers' to say
                lost = last_count - count
                tqdm.write(f"kitti-pu: warning: {lost} of the cluster's {last_count} workers stopped running (lost, "
                           "restarting or paused); their frames in flight go to the others", file=sys.stderr)
            if count != last_count and count and dask_settings.scheduler and not dask_settings.torch_threads:
                # a worker joined or left: each host's cores shared anew; best effort, as a worker
                # may leave meanwhile (the frames run on whatever counts the workers hold)
                with contextlib.suppress(Exception):
                    share_threads_again(client)
            last_count = count
            self.workers = max(self.workers, count)  # the summary's count: workers that joined later ran frames too

        for ref, frame_report in _process(client, self.todo, self.chain, limit, self.progress,
                                          dask_settings.no_workers_timeout, running):
            self._report(ref, frame_report)

    def _report(self, ref: load.FrameRef, frame_report: FrameReport) -> None:
        """Keep a frame's report and pass it on, a frame done in place of another's files as
        "replaced", as the summary says it (its line said "done": an operator's trial)."""
        if ref.key in self.replaced and frame_report.status == "done":
            frame_report.status, frame_report.reason = "replaced", self.replaced[ref.key]
        self.reports[ref.key] = frame_report
        self.notify(frame_report)


#: How often a run waiting for frames asks whether its cluster still has workers (seconds).
WORKER_CHECK_SECONDS = 2.0
#: How often it looks for finished frames meanwhile (seconds; a frame takes about a second).
FINISHED_POLL_SECONDS = 0.02


def _stop_on_refused_workers(client: Client, running: list[str], judged: set[str]) -> None:
    """SetupFailed naming those of the cluster's `running` workers (addresses) that the run's setup
    refused as they joined (`pipeline.cluster.worker_refusals`: other kitti-pu code, too little
    memory); `judged` holds the workers already found fit, and gains those found now. Their tasks
    fail each frame they touch, and an idle worker drew most frames: a trial's run failed 28 of 42."""
    verdicts = worker_refusals(client, [address for address in running if address not in judged])
    refused = {address: reason for address, reason in verdicts.items() if reason}
    judged.update(address for address, reason in verdicts.items() if not reason)
    if refused:
        raise SetupFailed("; ".join(sorted(refused.values())) + ". The frames done so far are kept; stop or fix "
                          f"{'that worker' if len(refused) == 1 else 'those workers'} and run again")


def _worker_states(client: Client) -> dict[str, str]:
    """The status of each of the cluster's workers ("running", "paused", ...), by address."""
    return {address: str(info.get("status", "running"))
            for address, info in client.scheduler_info().get("workers", {}).items()}


def _no_running_workers(states: list[str], seconds: float, had_workers: bool) -> NoWorkers:
    """The NoWorkers of a cluster whose workers (`states`) have run nothing for `seconds`;
    `had_workers`: whether one ran during this run (so they left, rather than never came)."""
    paused = states.count("paused")
    why = (f"its {paused} worker(s) paused: Dask pauses a worker at 80% of its memory limit, and a frame "
           f"needs about {MIN_WORKER_MEMORY / 1e9:.2f} GB (start workers with a larger --memory-limit)"
           if paused else
           f"its {len(states)} worker(s) are {' or '.join(sorted(set(states)))}" if states else
           "every worker it had left or died" if had_workers else "no worker joined")
    return NoWorkers(f"the cluster has had no running worker for {seconds:g} s (dask.no_workers_timeout): {why}")


def _wait_for_workers(client: Client, timeout: float) -> int:
    """The cluster's worker count once one of them runs, waiting up to `timeout` seconds (an
    external cluster may be scaling up); NoWorkers when none came, or all stayed paused."""
    deadline = time.monotonic() + timeout
    while "running" not in (states := _worker_states(client)).values():
        if time.monotonic() >= deadline:
            raise _no_running_workers(list(states.values()), timeout, had_workers=False)
        time.sleep(min(WORKER_CHECK_SECONDS, max(0.0, deadline - time.monotonic())))
    return len(states)


def _as_finished(finished: as_completed, client: Client, no_workers_timeout: float,
                 on_workers: Callable[[list[str]], None] = lambda running: None) -> Iterator[Future]:
    """The futures of `finished` as they finish (more may be added meanwhile); NoWorkers when the
    cluster has had no running worker (none, or all paused for memory) for `no_workers_timeout`
    seconds while frames wait: Dask would wait for ever, and the run would hold the output
    folder's lock; and at once when the client has closed, having lost the scheduler (it waited
    out the whole timeout, then blamed the workers: a trial). `on_workers` hears the addresses of
    the running workers at each check."""
    without_workers_since: float | None = None
    checked = time.monotonic()
    while not finished.is_empty():
        batch = finished.next_batch(block=False)
        if batch:
            without_workers_since = None
            yield from batch
            continue
        time.sleep(FINISHED_POLL_SECONDS)
        now = time.monotonic()
        if now - checked >= WORKER_CHECK_SECONDS:
            checked = now
            if client.status in ("closing", "closed"):  # Dask's client gave up reconnecting to the scheduler
                raise SchedulerLost(SCHEDULER_LOST)
            states = _worker_states(client)
            running = [address for address, state in states.items() if state == "running"]
            on_workers(running)
            if running:
                without_workers_since = None
            elif without_workers_since is None:
                without_workers_since = now
            elif now - without_workers_since >= no_workers_timeout:
                raise _no_running_workers(list(states.values()), no_workers_timeout, had_workers=True)


#: The longest a run waits, on a frame cancelled while its client reconnects to the scheduler,
#: for the client to reconnect or give up (its own reconnect timeout is 20 s: `open_client`).
RECONNECT_WAIT_S = 30.0


def _status_once_settled(client: Client, wait_s: float = RECONNECT_WAIT_S) -> str:
    """The client's status once it is no longer reconnecting ("connecting"), waiting up to
    `wait_s` seconds: a frame cancelled while it reconnects is a lost scheduler only if the client
    then gives up ("closing", "closed"); one that reconnects ("running") goes on with the run."""
    deadline = time.monotonic() + wait_s
    while client.status == "connecting" and time.monotonic() < deadline:
        time.sleep(FINISHED_POLL_SECONDS * 5)
    return str(client.status)


def _process(client: Client, refs: list[load.FrameRef], chain: Chain, limit: int,
             progress: bool, no_workers_timeout: float = float("inf"),
             on_workers: Callable[[list[str]], None] = lambda running: None) -> Iterator[tuple[load.FrameRef, FrameReport]]:
    """Keep at most `limit` frames in flight; yield each frame's report as it finishes (NoWorkers
    when the cluster has had no workers for `no_workers_timeout` seconds; `on_workers`: see
    `_as_finished`)."""
    token = uuid.uuid4().hex[:8]
    placement = FramePlacement(client)
    pending = iter(refs)
    by_future: dict = {}  # the future of a frame's report -> (its ref, the worker it was placed on)
    finished = as_completed()

    def submit(next_ref: load.FrameRef) -> None:
        worker = placement.take()
        future, network_step = _submit_chain(client, chain, next_ref, token, worker)
        placement.placed(worker, network_step)
        by_future[future] = (next_ref, worker)
        finished.add(future)

    for ref in pending:
        submit(ref)
        if len(by_future) >= limit:
            break
    bar = tqdm(total=len(refs), unit="frame", disable=not progress, desc="kitti-pu")
    try:
        for future in _as_finished(finished, client, no_workers_timeout, on_workers):
            ref, worker = by_future.pop(future)
            placement.give_back(worker)
            if future.status == "finished":  # a FrameReport, or the StageError of the stage that failed
                result = future.result()
                frame_report = result if isinstance(result, FrameReport) else _failed_report(ref, result)
            elif future.cancelled():  # the scheduler lost the task's workers, or the client lost the scheduler
                if _status_once_settled(client) in ("closing", "closed"):  # the scheduler is gone: every
                    # frame in flight was cancelled at once, and the run ended without a line of its
                    # own, blaming "the task's worker, or the scheduler" (an operator's trial)
                    raise SchedulerLost(SCHEDULER_LOST)
                frame_report = _interrupted_report(ref, "cancelled by the Dask cluster (it lost the task's worker, or "
                                                        "this run lost the scheduler)")
            else:
                frame_report = _failed_report(ref, future.exception())
            future.release()
            bar.update(1)
            if frame_report.status == "failed" and progress:  # without the bar, `on_report` prints it
                bar.write(f"failed: {frame_report.error}", file=sys.stderr)
            yield ref, frame_report
            next_ref = next(pending, None)
            if next_ref is not None:
                submit(next_ref)
    finally:
        bar.close()
