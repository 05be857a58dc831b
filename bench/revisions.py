"""Run a benchmark script on a git revision and on the working tree, interleaved, and print both.

Used by the benchmarks' `--compare REF` option (`bench/frames_per_minute.py`, `bench/stitch.py`, `bench/inference.py`,
`bench/crossing_rings.py`):

    python bench/stitch.py --compare main [--runs 3] [the script's own options]

The revision is checked out with `git worktree add --detach` into a temporary folder (removed
afterwards). Each run starts the *working tree's* script twice in a fresh Python process, once
with PYTHONPATH at the working tree and once at the revision's checkout (so the same measuring code
times both versions of the packages; Dask workers inherit PYTHONPATH), alternating which goes
first. The script prints its figures as one JSON line (`emit`); the medians over the runs are
printed side by side with their ratio (working tree / revision: below 1 is faster for times,
above 1 is more for frames per minute), with the machine's load averages before and after,
since timings on a shared machine are only comparable side by side.
"""

from __future__ import annotations

import json
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

#: The working tree: the repository this file is in.
TREE = Path(__file__).resolve().parents[1]
#: Prefix of the line a benchmark prints its figures on (`emit`).
MARK = "BENCH-FIGURES "


def add_arguments(parser) -> None:  # argparse.ArgumentParser
    """The options of a comparable benchmark: --compare REF, --runs N, --json."""
    parser.add_argument("--compare", metavar="REF", default=None,
                        help="also run git revision REF, interleaved with the working tree; print both and the ratio")
    parser.add_argument("--runs", type=int, default=3, help="with --compare: interleaved runs of each side")
    parser.add_argument("--json", action="store_true", help="print the figures as one JSON line (used by --compare)")


def parse_or_compare(parser, script: Path):  # (argparse.ArgumentParser) -> argparse.Namespace | None
    """Parse the command line; with --compare REF, run `script` on REF and on the working tree
    (`compare`) and return None, else return the parsed arguments."""
    args = parser.parse_args()
    if args.compare:
        compare(script, sys.argv[1:], args.compare, args.runs)
        return None
    return args


def emit(figures: dict[str, float]) -> None:
    """Print `figures` (name -> value) as the line `compare` reads."""
    print(MARK + json.dumps(figures), flush=True)


@contextmanager
def checkout(ref: str) -> Iterator[Path]:
    """A temporary detached git worktree of `ref` (removed on exit)."""
    folder = Path(tempfile.mkdtemp(prefix="kitti-pu-ref-"))
    target = folder / "tree"
    done = subprocess.run(["git", "-C", str(TREE), "worktree", "add", "--detach", str(target), ref],
                          capture_output=True, text=True)
    if done.returncode:
        raise SystemExit(f"--compare: cannot check out {ref!r}: {done.stderr.strip()}")
    try:
        yield target
    finally:
        subprocess.run(["git", "-C", str(TREE), "worktree", "remove", "--force", str(target)], capture_output=True)
        subprocess.run(["git", "-C", str(TREE), "worktree", "prune"], capture_output=True)
        shutil.rmtree(folder, ignore_errors=True)


def run_figures(script: Path, args: list[str], root: Path) -> dict[str, float]:
    """Run `script` with `args` and --json in a new process whose packages come from `root`."""
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(root), *filter(None, [os.environ.get("PYTHONPATH")])])}
    done = subprocess.run([sys.executable, str(script), *args, "--json"], env=env, capture_output=True, text=True)
    lines = [line for line in done.stdout.splitlines() if line.startswith(MARK)]
    if done.returncode or not lines:
        raise SystemExit(f"{script.name} with packages from {root} failed (exit {done.returncode}):\n"
                         f"{done.stderr[-3000:]}")
    return json.loads(lines[-1][len(MARK):])


def own_arguments(argv: list[str]) -> list[str]:
    """`argv` without --compare REF, --runs N and --json (what each side is run with)."""
    kept, skip = [], False
    for arg in argv:
        if skip:
            skip = False
        elif arg in ("--compare", "--runs"):
            skip = True
        elif not (arg.startswith("--compare=") or arg.startswith("--runs=") or arg == "--json"):
            kept.append(arg)
    return kept


def compare(script: Path, argv: list[str], ref: str, runs: int) -> None:
    """Run `script` on `ref` and on the working tree, `runs` times each, interleaved; print the
    median of each figure on both sides and their ratio (working tree / ref)."""
    args = own_arguments(argv)
    load_before = os.getloadavg()
    sides: dict[str, list[dict[str, float]]] = {ref: [], "working tree": []}
    with checkout(ref) as ref_root:
        for run in range(runs):
            order = [("working tree", TREE), (ref, ref_root)]
            for side, root in order if run % 2 == 0 else order[::-1]:
                print(f"run {run + 1}/{runs}: {side} ...", file=sys.stderr, flush=True)
                sides[side].append(run_figures(script, args, root))
    load_after = os.getloadavg()
    names = list(dict.fromkeys(name for figures in sides["working tree"] for name in figures))
    medians = {side: {name: statistics.median(f[name] for f in results if name in f) for name in names
                      if any(name in f for f in results)} for side, results in sides.items()}
    print(f"{script.name} {' '.join(args)}: medians of {runs} interleaved runs per side; "
          f"load average (1, 5, 15 min) {_loads(load_before)} before, {_loads(load_after)} after, "
          f"{os.cpu_count()} CPUs")
    print(f"{'figure':<32}{ref:>16}{'working tree':>16}{'ratio':>8}")
    for name in names:
        old, new = medians[ref].get(name, float("nan")), medians["working tree"][name]
        ratio = new / old if old else float("nan")
        print(f"{name:<32}{old:>16.1f}{new:>16.1f}{ratio:>8.2f}")


def _loads(loads: tuple[float, float, float]) -> str:
    return "/".join(f"{value:.1f}" for value in loads)
