"""Fault injection against `kitti-pu run` (issue 21): kill -9 of the main process, of a Dask worker
and of the scheduler, a full disk and two concurrent runs, each followed by a rerun.

Usage:
    python bench/faults.py [--trials 20] [--out DIR] [--seed 0] [--frames 6] [--quick]

It writes a small synthetic KITTI raw drive (every 32nd point of each simulated scan) and an
untrained ratio-4 model, makes a reference with one uninterrupted run, then runs the trials:

- `--trials` SIGKILLs of `kitti-pu run` (one-worker LocalCluster) at seeded random moments: odd
  trials anywhere up to 1.1 times the reference's wall time, even ones while frames are written;
- on a loopback cluster (`dask scheduler` and two `dask worker --no-nanny` processes on 127.0.0.1):
  a SIGKILL of one worker once the first frame is reported, then of the scheduler (the rerun gets a
  new scheduler and new workers);
- as root, a full disk: a tmpfs about half the output's size mounted as the output folder, then
  remounted with room for the rerun (skipped, with the reason, when not root or mounting fails);
- a kill -9 of a run that replaces every frame with another configuration in Parquet alone (the
  PLY files of the old one are its to remove), once its first frame is reported;
- two runs started at once on one output folder.

After each faulted run and each rerun: no file but data under points/ and ply/ (and nothing left in
OUT/.tmp after the rerun), and OUT/points reads with pandas, pyarrow.dataset, dask.dataframe and
DuckDB (when installed). After the rerun: exit 0, and every frame's sha256 of its sorted x, y, z
equals the reference's. It prints a table of the trials and a line of counts, and exits 1 when a
trial fails its checks. `--quick` (for the test suite): 3 frames, the main-process kills and the
concurrent runs only (the configuration change's fault is tested in process there:
`tests/pipeline/test_run_guarantees.py`).

Every process it starts runs in its own process group, is bounded by --timeout, and is killed
(with its group) at the end; a tmpfs it mounted is unmounted.
"""

from __future__ import annotations

import argparse
import os
import random
import shutil
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from fault_checks import (CLI, Proc, duckdb_available, frame_hashes, group_members, kill_group, lock_held,
                          make_input, readers_ok, run_command, start, stray_files, summary_matches_disk)
from loopback import LoopbackCluster

#: Keep one point in this many of a simulated scan (about 3.9k points per scan).
KEEP_EVERY = 32


@dataclass
class Bench:
    """The input, the reference output's per-frame hashes and the limits every trial shares."""

    work: Path
    raw: Path
    model: Path
    reference: dict[str, str]
    reference_bytes: int
    timeout: float
    started: list[Proc]
    #: Seconds between the reference's first and last frame lines (the frames being written).
    frame_window: float = 0.0


@dataclass
class Row:
    """One trial's line of the table."""

    trial: int
    fault: str
    moment: float | None = None
    rc_fault: int | None = None
    rc_rerun: int | None = None
    identical: bool = False
    readers: bool = False
    note: str = ""
    ok: bool = False
    skipped: bool = False


def _launch(bench: Bench, command: list[str], log: Path, cwd: Path | None = None) -> Proc:
    proc = start(command, log, cwd or bench.work)
    bench.started.append(proc)
    return proc


def _problems_of_fault(bench: Bench, out: Path) -> list[str]:
    """Checks of the folder a faulted run left: only data under points/ and ply/, readable."""
    problems = [f"stray after fault: {', '.join(stray_files(out, after_rerun=False)[:3])}"] \
        if stray_files(out, after_rerun=False) else []
    ok, why = readers_ok(out)
    if not ok:
        problems.append(f"readers after fault: {why}")
    return problems


def _rerun_and_check(bench: Bench, row: Row, out: Path, problems: list[str], scheduler: str | None = None,
                     extra: tuple[str, ...] = (), reference: dict[str, str] | None = None) -> Row:
    """Rerun into `out` (with `extra` arguments), fill in the row's rerun columns and verdict; the
    frames must equal `reference`'s (the bench's uninterrupted run when None)."""
    rerun = _launch(bench, [*run_command(bench.raw, bench.model, out, scheduler), *extra],
                    out.parent / f"{out.name}-rerun")
    row.rc_rerun = rerun.wait(bench.timeout)
    if row.rc_rerun != 0:
        problems.append(f"rerun exit {row.rc_rerun}: {rerun.stderr().strip().splitlines()[-1:]}")
    row.identical = frame_hashes(out) == (bench.reference if reference is None else reference)
    if not row.identical:
        problems.append("rerun output differs from the reference")
    stray = stray_files(out, after_rerun=True)
    if stray:
        problems.append(f"left after rerun: {', '.join(stray[:3])}")
    readers_fine, why = readers_ok(out)
    row.readers = readers_fine and not any(p.startswith("readers") for p in problems)
    if not readers_fine:
        problems.append(f"readers after rerun: {why}")
    row.ok = not problems
    row.note = "; ".join([row.note, *problems]).strip("; ")
    return row


def _settle_orphans(proc: Proc, grace: float = 15.0) -> int:
    """Wait up to `grace` s for what the killed run started (its process group) to exit by itself;
    kill what is left. Returns how many processes were still there after the grace period."""
    deadline = time.monotonic() + grace
    while group_members(proc.pid) and time.monotonic() < deadline:
        time.sleep(0.2)
    left = len(group_members(proc.pid))
    kill_group(proc.pid)
    return left


def kill_main(bench: Bench, trial: int, moment: float, after_first_frame: bool = False) -> Row:
    """SIGKILL `kitti-pu run` `moment` seconds after its start (after its first frame line when
    `after_first_frame`: a kill while frames are written), then rerun."""
    out = bench.work / "trials" / f"{trial:02d}-kill-main"
    row = Row(trial, "kill -9 main" + (" (frames)" if after_first_frame else ""))
    proc = _launch(bench, run_command(bench.raw, bench.model, out), out.parent / out.name)
    if after_first_frame:
        _first_frame_reported(proc, time.monotonic() + bench.timeout)
        moment += proc.elapsed()
    while proc.elapsed() < moment and proc.popen.poll() is None:
        time.sleep(0.01)
    row.moment = proc.elapsed()
    if proc.popen.poll() is None:
        proc.kill9()
    row.rc_fault = proc.wait(30)
    on_disk = len(list((out / "points").rglob("*.parquet")))
    stage = "finished first" if row.rc_fault == 0 else ("running" if lock_held(out) else "starting")
    orphans = _settle_orphans(proc)
    row.note = f"{stage}, {on_disk} frame(s) on disk" + (f", {orphans} orphan(s) after 15 s" if orphans else "")
    problems = _problems_of_fault(bench, out)
    if orphans:
        problems.append("orphaned processes outlived the killed run")
    return _rerun_and_check(bench, row, out, problems)


def _first_frame_reported(proc: Proc, deadline: float) -> None:
    """Wait until the run prints its first frame line, exits, or `deadline` (monotonic) passes."""
    while time.monotonic() < deadline and proc.popen.poll() is None and " points " not in proc.stdout():
        time.sleep(0.02)


def _run_until_first_frame(bench: Bench, out: Path, address: str) -> tuple[Any, float]:
    """Start `kitti-pu run` on the cluster at `address`; return it and the seconds it had run when
    its first frame was reported (or it exited, or the bench's timeout passed)."""
    proc = _launch(bench, run_command(bench.raw, bench.model, out, address), out.parent / out.name)
    _first_frame_reported(proc, time.monotonic() + bench.timeout)
    return proc, proc.elapsed()


def _reported(proc: Proc) -> int:
    """How many frame lines (`--no-progress`) the run has printed so far."""
    return sum(" points " in line and " -> " in line for line in proc.stdout().splitlines())


def kill_worker(bench: Bench, trial: int) -> Row:
    """On a loopback cluster, SIGKILL one of two workers once the first frame is reported; rerun
    on the same scheduler with a replacement worker."""
    out = bench.work / "trials" / f"{trial:02d}-kill-worker"
    row = Row(trial, "kill -9 worker")
    with LoopbackCluster(bench.work / "trials" / f"{trial:02d}-cluster", bench.started) as cluster:
        proc, row.moment = _run_until_first_frame(bench, out, cluster.address)
        cluster.workers[0].kill9()
        row.note = f"killed after {_reported(proc)} of {len(bench.reference)} frame(s) reported"
        row.rc_fault = proc.wait(bench.timeout)
        problems = _problems_of_fault(bench, out)
        if row.rc_fault != 0:
            problems.append(f"the run did not survive the worker: exit {row.rc_fault}")
        cluster.add_worker()
        return _rerun_and_check(bench, row, out, problems, cluster.address)


def kill_scheduler(bench: Bench, trial: int) -> Row:
    """On a loopback cluster, SIGKILL the scheduler once the first frame is reported; the summary
    must report what is on disk; rerun on a new scheduler and new workers."""
    out = bench.work / "trials" / f"{trial:02d}-kill-scheduler"
    row = Row(trial, "kill -9 scheduler")
    with LoopbackCluster(bench.work / "trials" / f"{trial:02d}-cluster", bench.started) as cluster:
        proc, row.moment = _run_until_first_frame(bench, out, cluster.address)
        cluster.scheduler.kill9()
        reported = _reported(proc)
        row.rc_fault = proc.wait(bench.timeout)
    problems = _problems_of_fault(bench, out)
    if row.rc_fault not in (0, 3):
        problems.append(f"faulted run exit {row.rc_fault} (expected 3, or 0 when it had finished)")
    matches, why = summary_matches_disk(out)
    if not matches:
        problems.append(why)
    row.note = (f"killed after {reported} of {len(bench.reference)} frame(s) reported; "
                f"{len(list((out / 'points').rglob('*.parquet')))} on disk")
    with LoopbackCluster(bench.work / "trials" / f"{trial:02d}-cluster2", bench.started) as cluster:
        return _rerun_and_check(bench, row, out, problems, cluster.address)


def disk_full(bench: Bench, trial: int) -> Row:
    """A tmpfs of about half the output's size as the output folder: exit 3, one-line errors,
    every frame on disk complete; then remounted with room, rerun."""
    out = bench.work / "trials" / f"{trial:02d}-disk-full"
    row = Row(trial, "disk full (tmpfs)")
    out.mkdir(parents=True)
    size_kib = max(64, bench.reference_bytes // 2 // 1024)
    mounted = subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size_kib}k", "tmpfs", str(out)],
                             capture_output=True, text=True, timeout=30)
    if mounted.returncode != 0:
        row.skipped, row.ok = True, True
        row.note = f"skipped: mount failed ({mounted.stderr.strip() or mounted.returncode})"
        return row
    try:
        proc = _launch(bench, run_command(bench.raw, bench.model, out), out.parent / out.name)
        row.rc_fault = proc.wait(bench.timeout)
        problems = _problems_of_fault(bench, out)
        if row.rc_fault != 3:
            problems.append(f"faulted run exit {row.rc_fault}, expected 3")
        output = proc.stdout() + proc.stderr()
        errors = [line for line in output.splitlines() if "No space left" in line or "cannot write" in line]
        if "Traceback" in output or "RPly" in output or len(output.splitlines()) > 100:
            problems.append(f"not one-line errors ({len(output.splitlines())} lines of output)")
        partial = [name for name, digest in frame_hashes(out).items() if bench.reference.get(name) != digest]
        if partial:
            problems.append(f"half-written: {partial[:3]}")
        row.note = f"tmpfs {size_kib} KiB: {len(frame_hashes(out))} frame(s) written, {len(errors)} error line(s)"
        subprocess.run(["mount", "-o", "remount,size=256m", str(out)], check=True, timeout=30)
        return _rerun_and_check(bench, row, out, problems)
    finally:
        if subprocess.run(["umount", str(out)], capture_output=True, timeout=60).returncode != 0:
            subprocess.run(["umount", "-l", str(out)], capture_output=True, timeout=60)


#: A configuration change that changes every frame's points, in Parquet alone (`config_change`).
CHANGED_CONFIG = ("--format", "parquet", "--set", "tile.overlap=1.3333")


def config_change(bench: Bench, trial: int) -> Row:
    """kill -9 of a run that replaces every finished frame (Parquet and PLY) with another
    configuration in Parquet alone, once its first frame is reported: a run removes a replaced
    frame's PLY file of the old configuration only when it settles its frames, at its end. Then
    rerun: its frames must equal an uninterrupted run's of the new configuration, and no frame may
    keep a PLY file of the old one (`kitti-pu info --verify` compares every format's record)."""
    out = bench.work / "trials" / f"{trial:02d}-config-change"
    row = Row(trial, "kill -9 main, config change")
    target = bench.work / "trials" / f"{trial:02d}-config-change-reference"
    uninterrupted = _launch(bench, [*run_command(bench.raw, bench.model, target), *CHANGED_CONFIG],
                            target.parent / target.name)
    if uninterrupted.wait(bench.timeout) != 0:
        row.note = f"the uninterrupted run of the new configuration failed: {uninterrupted.stderr()[-300:]}"
        return row
    shutil.copytree(bench.work / "reference", out)
    proc = _launch(bench, [*run_command(bench.raw, bench.model, out), *CHANGED_CONFIG], out.parent / out.name)
    _first_frame_reported(proc, time.monotonic() + bench.timeout)
    row.moment = proc.elapsed()
    if proc.popen.poll() is None:
        proc.kill9()
    row.rc_fault = proc.wait(30)
    _settle_orphans(proc)
    left = _plys_of_another_config(out)
    row.note = f"{len(left)} PLY file(s) of the old configuration left by the kill"
    problems = _problems_of_fault(bench, out)
    if row.rc_fault != -9 or not left or not list((out / "runs").glob("*.unfinished")):
        # the run ended (or settled) before the kill: nothing of what the trial is for was tested
        problems.append("the kill did not land while the run had frames to settle: the trial tested nothing")
    row = _rerun_and_check(bench, row, out, problems, extra=CHANGED_CONFIG, reference=frame_hashes(target))
    stale = _plys_of_another_config(out)
    if stale:
        row.ok = False
        row.note += f"; {len(stale)} PLY file(s) of the old configuration after the rerun, e.g. {stale[0]}"
    verify = subprocess.run([*CLI[:-1], "info", str(out), "--verify"], capture_output=True, text=True, cwd=bench.work,
                            timeout=bench.timeout)
    if verify.returncode != 0:
        row.ok = False
        row.note += f"; info --verify exit {verify.returncode}: {verify.stdout.strip().splitlines()[-1:]}"
    return row


def _plys_of_another_config(out: Path) -> list[str]:
    """The PLY files of `out` whose record names another configuration than their frame's Parquet
    file (records read with `stages.write.stored_record`; the comparison is the script's own)."""
    from stages.write import stored_record

    stale = []
    for ply in sorted((out / "ply").rglob("*.ply")):
        parquet = out / "points" / ply.relative_to(out / "ply").with_suffix(".parquet")
        config = stored_record({"parquet": parquet}).get("config_hash") if parquet.is_file() else None
        if config is not None and stored_record({"ply": ply}).get("config_hash") != config:
            stale.append(str(ply.relative_to(out)))
    return stale


def concurrent(bench: Bench, trial: int) -> Row:
    """Two runs started at once on one output folder: one exits 4 with the lock message, or both
    end consistent (exit 0); then rerun."""
    out = bench.work / "trials" / f"{trial:02d}-concurrent"
    row = Row(trial, "two concurrent runs")
    procs = [_launch(bench, run_command(bench.raw, bench.model, out), out.parent / f"{out.name}-{i}")
             for i in range(2)]
    codes = [proc.wait(bench.timeout) for proc in procs]
    row.rc_fault = max(codes, key=lambda code: -1 if code is None else code)
    row.note = f"exits {codes[0]} and {codes[1]}"
    problems = _problems_of_fault(bench, out)
    busy = [proc for proc, code in zip(procs, codes) if code == 4]
    if sorted(codes, key=str) not in ([0, 4], [0, 0]):
        problems.append(f"exits {codes}, expected 0 and 4, or 0 and 0")
    if busy and "another kitti-pu run" not in busy[0].stderr():
        problems.append("the refused run did not print the lock message")
    return _rerun_and_check(bench, row, out, problems)


def reference(work: Path, raw: Path, model: Path, timeout: float, started: list[Proc]) -> tuple[Bench, float]:
    """One uninterrupted run; returns the shared bench state and its wall time (s)."""
    out = work / "reference"
    proc = start(run_command(raw, model, out), work / "reference-run", work)
    started.append(proc)
    frame_times = []
    while proc.popen.poll() is None and proc.elapsed() < timeout:
        if _reported(proc) > len(frame_times):
            frame_times.append(proc.elapsed())
        time.sleep(0.01)
    code = proc.wait(timeout)
    wall = proc.elapsed()
    hashes = frame_hashes(out)
    if code != 0 or not hashes:
        raise SystemExit(f"faults: the reference run failed (exit {code}):\n{proc.stderr()[-2000:]}")
    size = sum(p.stat().st_size for folder in ("points", "ply") for p in (out / folder).rglob("*") if p.is_file())
    window = frame_times[-1] - frame_times[0] if frame_times else 0.0
    return Bench(work, raw, model, hashes, size, timeout, started, window), wall


def table(rows: list[Row]) -> str:
    """The trials as a Markdown table."""
    def yes(value: bool, row: Row) -> str:
        return "-" if row.skipped else ("yes" if value else "no")

    lines = ["| trial | fault | moment (s) | faulted exit | rerun exit | identical | readers OK | note |",
             "|---|---|---|---|---|---|---|---|"]
    for row in rows:
        moment = "-" if row.moment is None else f"{row.moment:.2f}"
        lines.append(f"| {row.trial} | {row.fault} | {moment} | {'-' if row.skipped else row.rc_fault} | "
                     f"{'-' if row.skipped else row.rc_rerun} | {yes(row.identical, row)} | "
                     f"{yes(row.readers, row)} | {row.note} |")
    return "\n".join(lines)


def main() -> int:
    """Run the trials (see the module docstring); returns 0 when every trial passed its checks."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--trials", type=int, default=20, help="kill -9 trials of the main process")
    parser.add_argument("--out", type=Path, default=None, help="work folder (kept); a temporary one otherwise")
    parser.add_argument("--seed", type=int, default=0, help="seed of the kill moments")
    parser.add_argument("--frames", type=int, default=None, help="frames in the drive (6; 3 with --quick)")
    parser.add_argument("--timeout", type=float, default=180.0, help="limit of each process (s)")
    parser.add_argument("--quick", action="store_true", help="main-process kills and concurrent runs only")
    args = parser.parse_args()
    work = Path(tempfile.mkdtemp(prefix="kitti-pu-faults-")) if args.out is None else args.out.absolute()
    if args.out is not None and work.exists() and any(work.iterdir()):
        parser.error(f"--out {work} is not empty")
    work.mkdir(parents=True, exist_ok=True)
    started: list[Proc] = []
    rows: list[Row] = []
    try:
        raw, model = make_input(work, args.frames or (3 if args.quick else 6), KEEP_EVERY)
        bench, wall = reference(work, raw, model, args.timeout, started)
        print(f"reference: {len(bench.reference)} frames, {wall:.1f} s ({bench.frame_window:.2f} s from the "
              f"first frame line to the last); duckdb "
              f"{'installed' if duckdb_available() else 'not installed: that reader is skipped'}", flush=True)
        rng = random.Random(args.seed)
        trial = 0
        for _ in range(args.trials):
            trial += 1
            if trial % 2:  # anywhere in the run: start-up, frames, summary, cluster shutdown
                rows.append(kill_main(bench, trial, rng.uniform(0.5, 1.1 * wall)))
            else:  # while frames are written (a short part of a small run)
                rows.append(kill_main(bench, trial, rng.uniform(0.0, bench.frame_window + 0.2), True))
            print(f"trial {trial}: {rows[-1].fault} {'ok' if rows[-1].ok else 'FAILED: ' + rows[-1].note}", flush=True)
        plan = [concurrent] if args.quick else [kill_worker, kill_scheduler, disk_full, config_change, concurrent]
        for make in plan:
            trial += 1
            if make is disk_full and os.geteuid() != 0:
                rows.append(Row(trial, "disk full (tmpfs)", skipped=True, ok=True, note="skipped: not root"))
            else:
                rows.append(make(bench, trial))
            print(f"trial {trial}: {rows[-1].fault} {'ok' if rows[-1].ok else 'FAILED: ' + rows[-1].note}", flush=True)
    finally:
        for proc in started:
            kill_group(proc.pid)
        if args.out is None:
            shutil.rmtree(work, ignore_errors=True)
    print(table(rows))
    failed = sum(not row.ok for row in rows)
    skipped = sum(row.skipped for row in rows)
    print(f"{len(rows)} trials: {len(rows) - failed - skipped} passed, {failed} failed, {skipped} skipped")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
