"""What the Open3D start-up hook (`kitti_pu_open3d.pth`, installed by setup.py) adds to every
interpreter start.

    python bench/startup.py [--runs 40]

Runs this interpreter, isolated and without site (`-I -S`), processing one folder with
`site.addsitedir` as start-up processes site-packages: once an empty folder, once a folder holding
the installed `.pth`, interleaved. Prints the median wall time of each, the median of the paired
differences (the hook's cost), and for scale the median of a whole `python -c pass` here.
"""

from __future__ import annotations

import argparse
import shutil
import site
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

PTH_NAME = "kitti_pu_open3d.pth"
ADD_SITE = "import site, sys; site.addsitedir(sys.argv[1])"


def installed_pth() -> Path:
    """The hook installed in this interpreter's site-packages (SystemExit when absent)."""
    for folder in site.getsitepackages():
        if Path(folder, PTH_NAME).is_file():
            return Path(folder, PTH_NAME)
    raise SystemExit(f"{PTH_NAME} is not installed here: pip install -e . first")


def wall(command: list[str]) -> float:
    """Seconds one run of `command` takes."""
    started = time.perf_counter()
    subprocess.run(command, check=True)
    return time.perf_counter() - started


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--runs", type=int, default=40)
    args = parser.parse_args()
    pth = installed_pth()
    with tempfile.TemporaryDirectory() as tmp:
        empty, hooked = Path(tmp, "empty"), Path(tmp, "hooked")
        empty.mkdir()
        hooked.mkdir()
        shutil.copy(pth, hooked / PTH_NAME)
        base = [sys.executable, "-I", "-S", "-c", ADD_SITE]
        without, with_hook, plain = [], [], []
        for _ in range(args.runs):
            without.append(wall([*base, str(empty)]))
            with_hook.append(wall([*base, str(hooked)]))
            plain.append(wall([sys.executable, "-c", "pass"]))
    paired = [b - a for a, b in zip(without, with_hook)]
    print(f"hook: {pth}")
    print(f"{args.runs} interleaved runs, medians (ms):")
    print(f"  -I -S + addsitedir(empty folder): {1e3 * statistics.median(without):.2f}")
    print(f"  -I -S + addsitedir(the hook)    : {1e3 * statistics.median(with_hook):.2f}")
    print(f"  the hook's cost (paired)        : {1e3 * statistics.median(paired):.2f}")
    print(f"  python -c pass (for scale)      : {1e3 * statistics.median(plain):.2f}")


if __name__ == "__main__":
    main()
