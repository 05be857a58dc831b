"""Install time and size of kitti-pu with and without its extras, each in a fresh venv.

    python bench/install.py [--rounds 2] [--spec . --spec ".[open3d]" ...]

For every round and every spec (interleaved), in a temporary folder: `python3 -m venv`, then
`pip install -q -e "ROOT<spec>"` of this checkout, timed; then the venv's size (`du -sm`) and its
package count (`pip list`). Run it twice and quote the second run: the first fills pip's cache
(wheels from the index), which the figures are meant to leave out. Prints one line per install
and the median seconds per spec.
"""

from __future__ import annotations

import argparse
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def install(spec: str) -> tuple[float, int, int]:
    """(seconds, MB, packages) of one editable install of ROOT + `spec` into a fresh venv."""
    with tempfile.TemporaryDirectory() as tmp:
        venv = Path(tmp, "venv")
        subprocess.run([sys.executable, "-m", "venv", str(venv)], check=True)
        pip = str(venv / "bin" / "pip")
        started = time.perf_counter()
        subprocess.run([pip, "install", "-q", "-e", f"{ROOT}{spec.lstrip('.')}"], check=True,
                       stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        seconds = time.perf_counter() - started
        size = int(subprocess.run(["du", "-sm", str(venv)], check=True, capture_output=True,
                                  text=True).stdout.split()[0])
        listed = subprocess.run([pip, "list", "--format=freeze"], check=True, capture_output=True, text=True)
        return seconds, size, len(listed.stdout.splitlines())


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--rounds", type=int, default=2)
    parser.add_argument("--spec", action="append", help='e.g. "." or ".[open3d]" (default both)')
    args = parser.parse_args()
    specs = args.spec or [".", ".[open3d]"]
    seconds: dict[str, list[float]] = {spec: [] for spec in specs}
    for round_ in range(1, args.rounds + 1):
        for spec in specs:
            took, size, packages = install(spec)
            seconds[spec].append(took)
            print(f"round {round_}  pip install -e {spec!r:14} {took:6.1f} s  {size:5d} MB  {packages:4d} packages",
                  flush=True)
    for spec, values in seconds.items():
        print(f"median {spec!r:14} {statistics.median(values):6.1f} s over {len(values)}")


if __name__ == "__main__":
    main()
