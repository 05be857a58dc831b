"""bench/faults.py's core runs in CI: one kill -9 of `kitti-pu run` at a random moment and two
concurrent runs, each rerun and checked against an uninterrupted run (`--quick`: no loopback
cluster, no tmpfs, no change of configuration)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

SCRIPT = Path(__file__).resolve().parents[2] / "bench" / "faults.py"


def test_the_fault_script_passes_its_quick_trials_and_prints_the_table(tmp_path: Path) -> None:
    work = tmp_path / "faults"
    result = subprocess.run([sys.executable, str(SCRIPT), "--trials", "1", "--quick", "--out", str(work)],
                            capture_output=True, text=True, timeout=300, cwd=tmp_path,
                            env={**os.environ, "PYTHONUNBUFFERED": "1"})
    assert result.returncode == 0, result.stdout + result.stderr[-3000:]
    lines = result.stdout.splitlines()
    assert "| trial | fault | moment (s) | faulted exit | rerun exit | identical | readers OK | note |" in lines
    rows = [line for line in lines if line.startswith(("| 1 |", "| 2 |"))]
    assert [row.split(" | ")[1] for row in rows] == ["kill -9 main", "two concurrent runs"]
    assert all(" | yes | yes | " in row for row in rows), rows
    assert lines[-1] == "2 trials: 2 passed, 0 failed, 0 skipped"
    assert not list(work.glob("trials/*/.tmp/*")), "the reruns left temporaries"
