"""What bench/faults.py needs besides its trials: the small input, the `kitti-pu run` and Dask
subprocesses (each in its own process group, bounded in time), and the checks made on an output
folder after each trial (per-frame hash of the sorted points, temporaries, the four readers).

Imported by bench/faults.py from its own folder (the script's folder is on the path of a script).
"""

from __future__ import annotations

import hashlib
import importlib.util
import json
import os
import signal
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq
import torch

from cadpu import weights
from cadpu.network import Generator
from pipeline.runner import LOCK_NAME
from pipeline.synthetic_drive import write_synthetic_drive
from stages.temporaries import TEMPORARY_DIR

#: The command line of `kitti-pu run` without the installed entry point (any venv, any checkout).
CLI = [sys.executable, "-c", "from pipeline.cli import app; app()", "run"]
#: Settings of every run: one torch thread (the same arithmetic on a LocalCluster and on loopback
#: workers), the CPU, every patch upsampled (the cut scans are sparse: most patches are wide).
RUN_SETTINGS = ["--no-progress", "--set", "dask.torch_threads=1", "--set", "upsample.device=cpu",
                "--set", "upsample.max_patch_radius=0"]


def make_input(work: Path, frames: int, keep_every: int, seed: int = 0) -> tuple[Path, Path]:
    """Write a synthetic KITTI raw drive of `frames` scans, each cut to every `keep_every`-th point
    (KITTI ring order kept), and an untrained ratio-4 generator saved by `cadpu.weights.save`.

    Returns:
        (the raw base folder, the weights file).
    """
    raw = work / "kitti_raw"
    drive = write_synthetic_drive(raw, n_frames=frames, seed=seed)
    for scan_file in sorted((drive / "velodyne_points" / "data").glob("*.bin")):
        scan = np.fromfile(scan_file, dtype=np.float32).reshape(-1, 4)
        np.ascontiguousarray(scan[::keep_every]).tofile(scan_file)
    torch.manual_seed(seed)
    model = work / "untrained_r4.pt"
    weights.save(Generator(ratio=4), model)
    return raw, model


def group_members(pgid: int) -> list[int]:
    """Process ids of the live (not zombie) processes in process group `pgid` (from /proc)."""
    members = []
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            fields = (entry / "stat").read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        if fields[0] != "Z" and int(fields[2]) == pgid:
            members.append(int(entry.name))
    return members


def kill_group(pgid: int) -> None:
    """SIGKILL every process of group `pgid` (a group this script started); no error if gone."""
    try:
        os.killpg(pgid, signal.SIGKILL)
    except ProcessLookupError:
        pass


@dataclass
class Proc:
    """A subprocess started by `start`, in its own session (its process group id is its pid), with
    stdout and stderr in files beside `log`."""

    popen: subprocess.Popen
    log: Path
    started: float = field(default_factory=time.monotonic)

    @property
    def pid(self) -> int:
        return self.popen.pid

    def elapsed(self) -> float:
        """Seconds since the process was started."""
        return time.monotonic() - self.started

    def wait(self, timeout: float) -> int | None:
        """The exit status (negative: killed by that signal), or None after `timeout` seconds, when
        the whole group is killed."""
        try:
            return self.popen.wait(timeout=timeout)
        except subprocess.TimeoutExpired:
            kill_group(self.pid)
            self.popen.wait(timeout=30)
            return None

    def kill9(self) -> None:
        """SIGKILL this process alone (not its group)."""
        try:
            os.kill(self.pid, signal.SIGKILL)
        except ProcessLookupError:
            pass

    def stdout(self) -> str:
        return self.log.with_suffix(".out").read_text(errors="replace")

    def stderr(self) -> str:
        return self.log.with_suffix(".err").read_text(errors="replace")


def start(command: list[str], log: Path, cwd: Path) -> Proc:
    """Start `command` in a new session with stdout/stderr to `log`.out/.err."""
    log.parent.mkdir(parents=True, exist_ok=True)
    with open(log.with_suffix(".out"), "w") as out, open(log.with_suffix(".err"), "w") as err:
        popen = subprocess.Popen(command, stdout=out, stderr=err, stdin=subprocess.DEVNULL, cwd=cwd,
                                 start_new_session=True, env={**os.environ, "PYTHONUNBUFFERED": "1"})
    return Proc(popen, log)


def run_command(raw: Path, model: Path, out: Path, scheduler: str | None = None) -> list[str]:
    """`kitti-pu run` of the bench input into `out`: on a one-worker LocalCluster, or on `scheduler`."""
    where = ["--scheduler", scheduler] if scheduler else ["--workers", "1"]
    return [*CLI, str(raw), "--out", str(out), "--weights", str(model), *where, *RUN_SETTINGS]


def frame_hashes(out: Path) -> dict[str, str]:
    """sha256 of each frame's x, y, z (float32, rows sorted by x, then y, then z), by the Parquet
    file's path relative to `out/points`; a file that does not read hashes to its error."""
    hashes = {}
    for path in sorted((out / "points").rglob("*.parquet")):
        try:
            table = pq.read_table(path, columns=["x", "y", "z"])
        except Exception as error:  # noqa: BLE001 - an unreadable file is a finding, not a crash
            hashes[str(path.relative_to(out / "points"))] = f"unreadable: {type(error).__name__}"
            continue
        xyz = np.column_stack([table[name].to_numpy() for name in ("x", "y", "z")]).astype(np.float32)
        xyz = xyz[np.lexsort((xyz[:, 2], xyz[:, 1], xyz[:, 0]))]
        hashes[str(path.relative_to(out / "points"))] = hashlib.sha256(xyz.tobytes()).hexdigest()
    return hashes


def stray_files(out: Path, after_rerun: bool) -> list[str]:
    """Files that are not data: anything under points/ but visible .parquet files, under ply/ but
    visible .ply files; after a rerun also anything left in `OUT/.tmp` (a killed run's temporaries
    there are legitimate until the next run sweeps them)."""
    stray = []
    for folder, suffix in (("points", ".parquet"), ("ply", ".ply")):
        for path in (out / folder).rglob("*"):
            if path.is_file() and (path.name.startswith((".", "_")) or path.suffix != suffix):
                stray.append(str(path.relative_to(out)))
    if after_rerun and (out / TEMPORARY_DIR).is_dir():
        stray += [str(p.relative_to(out)) for p in (out / TEMPORARY_DIR).rglob("*")]
    return stray


def duckdb_available() -> bool:
    """True when the duckdb package is importable here."""
    return importlib.util.find_spec("duckdb") is not None


def readers_ok(out: Path) -> tuple[bool, str]:
    """Read `out/points` with pandas, pyarrow.dataset, dask.dataframe and DuckDB (when installed),
    each with its plain call; every reader must return as many rows as the frames' files hold.

    Returns:
        (all readers agree, "" or what failed). An empty folder (no frame yet) passes.
    """
    points = out / "points"
    files = sorted(points.rglob("*.parquet")) if points.is_dir() else []
    if not files:
        return True, ""
    import dask.dataframe as dd
    import pandas as pd
    import pyarrow.dataset as ds

    expected = sum(pq.read_metadata(f).num_rows for f in files)
    readers = {
        "pandas": lambda: len(pd.read_parquet(points)),
        "pyarrow": lambda: ds.dataset(points).to_table().num_rows,
        "dask": lambda: len(dd.read_parquet(str(points)).compute(scheduler="synchronous")),
    }
    if duckdb_available():
        import duckdb

        # the README's call (a DuckDB relation keeps no result: .df() runs it)
        readers["duckdb"] = lambda: len(duckdb.sql(f"SELECT * FROM read_parquet('{points}/*/*/*.parquet')").df())
    problems = []
    for name, read in readers.items():
        try:
            rows = read()
        except Exception as error:  # noqa: BLE001 - a reader's failure is the finding
            problems.append(f"{name}: {type(error).__name__}: {str(error).splitlines()[0][:120]}")
            continue
        if rows != expected:
            problems.append(f"{name}: {rows} rows, files hold {expected}")
    return not problems, "; ".join(problems)


def summary_matches_disk(out: Path) -> tuple[bool, str]:
    """The last run's summary.json lists with outputs exactly the frames whose Parquet files are
    on disk (done, skipped or replaced ones, and any other whose earlier complete files stay)."""
    try:
        summary = json.loads((out / "summary.json").read_text())
    except (OSError, ValueError) as error:
        return False, f"summary.json: {error}"
    complete = {f["key"] for f in summary["frames"] if f["outputs"]}
    on_disk = len(list((out / "points").rglob("*.parquet")))
    if len(complete) != on_disk:
        return False, f"summary reports {len(complete)} complete frames, {on_disk} on disk"
    return True, ""


def lock_held(out: Path) -> bool:
    """True once a run has created its lock file in `out` (it has passed its checks)."""
    return (out / LOCK_NAME).exists()
