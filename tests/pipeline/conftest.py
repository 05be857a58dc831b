"""Shared fixtures of the pipeline tests.

- `weights_file`: an untrained ratio-4 generator saved by `cadpu.weights.save` (with .sha256), so
  the tests never depend on the shipped weights;
- `raw_drive_template`: a 2-frame synthetic KITTI raw drive (`pipeline.synthetic_drive`) whose scans are cut
  to every 16th point (about 8k points, 3.5k of them above the ground) so a frame runs in well
  under a second on one CPU thread;
- `raw_drive` / `bin_folder`: private copies of it (a raw base folder, a folder of .bin files)
  that a test may damage;
- `make_config`: the run configuration every test uses (one single-threaded LocalCluster worker,
  the untrained weights, CPU).
"""

from __future__ import annotations

import shutil
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch

from cadpu import weights
from cadpu.network import Generator
from pipeline.config import PipelineConfig, load_config
from pipeline.synthetic_drive import write_synthetic_drive

DATE = "2011_09_26"
DRIVE = "0001"
DRIVE_NAME = f"{DATE}_drive_{DRIVE}_sync"
#: Keep one point in this many of a simulated HDL-64E scan (125k points -> about 7.8k).
SUBSAMPLE = 16


@pytest.fixture(scope="session")
def weights_file(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """An untrained ratio-4 generator saved with its .sha256, as `cadpu.weights.save` writes it."""
    torch.manual_seed(0)
    path = tmp_path_factory.mktemp("weights") / "untrained_r4.pt"
    weights.save(Generator(ratio=4), path)
    return path


@pytest.fixture(scope="session")
def raw_drive_template(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A KITTI raw base folder holding one 2-frame synthetic drive with small scans (read-only:
    tests that change it take `raw_drive`)."""
    base = tmp_path_factory.mktemp("raw_template")
    drive_dir = write_synthetic_drive(base, n_frames=2, seed=0, date=DATE, drive=DRIVE)
    for scan_file in sorted((drive_dir / "velodyne_points" / "data").glob("*.bin")):
        scan = np.fromfile(scan_file, dtype=np.float32).reshape(-1, 4)
        np.ascontiguousarray(scan[::SUBSAMPLE]).tofile(scan_file)  # keeps the KITTI ring order
    return base


@pytest.fixture()
def raw_drive(raw_drive_template: Path, tmp_path: Path) -> Path:
    """A private copy of the raw base folder (BASE with BASE/DATE/DATE_drive_0001_sync)."""
    return Path(shutil.copytree(raw_drive_template, tmp_path / "kitti_raw"))


@pytest.fixture(scope="session")
def template_scans(raw_drive_template: Path) -> list[np.ndarray]:
    """The template drive's scans, each (N, 4) float32 x, y, z, reflectance in the sensor frame."""
    data = raw_drive_template / DATE / DRIVE_NAME / "velodyne_points" / "data"
    return [np.fromfile(f, dtype=np.float32).reshape(-1, 4) for f in sorted(data.glob("*.bin"))]


@pytest.fixture()
def bin_folder(template_scans: list[np.ndarray], tmp_path: Path) -> Path:
    """A plain folder `scans/` with the template's scans as 000000.bin and 000001.bin."""
    folder = tmp_path / "scans"
    folder.mkdir()
    for index, scan in enumerate(template_scans):
        scan.tofile(folder / f"{index:06d}.bin")
    return folder


@pytest.fixture(scope="session")
def make_config(weights_file: Path) -> Callable[..., PipelineConfig]:
    """Build a validated configuration for `input_path` -> `out_dir` plus dotted-key overrides.

    Every run gets one LocalCluster worker with one thread and one torch thread (two cores are
    shared on the CI machine), the untrained weights, the CPU, every patch upsampled, every
    generated point kept where the network put it (no ring snapping and no ground fill, so a frame
    has r generated points per object point) and no progress bar.
    """

    def build(input_path: Path, out_dir: Path, **overrides: Any) -> PipelineConfig:
        settings: dict[str, Any] = {
            "input.path": str(input_path),
            "output.dir": str(out_dir),
            "upsample.weights": str(weights_file),
            "upsample.device": "cpu",
            # the test scans are sparse (few rings): most patches are wider than the default limit
            "upsample.max_patch_radius": 0,
            "snap.enabled": False,
            "fill.enabled": False,
            "dask.n_workers": 1,
            "dask.threads_per_worker": 1,
            "dask.torch_threads": 1,
        }
        settings.update({key.replace("__", "."): value for key, value in overrides.items()})
        return load_config([], settings)

    return build


def hidden_files(root: Path) -> list[Path]:
    """Every file or folder under `root` whose name starts with '.' (temporary names), but the
    output folder's lock file, which stays (`pipeline.runner.LOCK_NAME`), and the (empty) folder of
    the output's temporaries, `OUT/.tmp`."""
    from pipeline.runner import LOCK_NAME

    return [path for path in Path(root).rglob("*") if path.name.startswith(".") and path.name != LOCK_NAME
            and not (path.name == ".tmp" and path.is_dir() and not any(path.iterdir()))]


@pytest.fixture(scope="session")
def find_hidden() -> Callable[[Path], list[Path]]:
    """`hidden_files` as a fixture (test modules cannot import conftest under importlib mode)."""
    return hidden_files
