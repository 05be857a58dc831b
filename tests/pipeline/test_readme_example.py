"""The README's Python blocks: every one runs verbatim on data the test makes (an odometry base for
`/data/kitti/odometry`, `000000.bin` and an output folder `OUT` in the working folder), and the
library example (the whole chain for one scan, on `pipeline.chain.Chain`) gives the same points
as `kitti-pu run` on the same scan."""

from __future__ import annotations

import re
from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq
import pytest
import torch

from pipeline.config import PipelineConfig, load_config
from pipeline.runner import run_pipeline

README = Path(__file__).resolve().parents[2] / "README.md"
#: Where the README's example looks for the data; the test puts its own odometry base there instead.
README_DATA = "/data/kitti/odometry"


def python_blocks() -> list[str]:
    """Every ```python block of the README, in order."""
    return re.findall(r"```python\n(.*?)```", README.read_text(), flags=re.S)


def chain_example() -> str:
    """The README's Python block that runs `Chain().run`."""
    matching = [block for block in python_blocks() if "Chain().run(" in block]
    assert len(matching) == 1, "the README has one example of Chain().run"
    return matching[0]


def _sorted_xyz(xyz: np.ndarray) -> np.ndarray:
    return xyz[np.lexsort(xyz.T[::-1])]


@pytest.fixture
def one_thread() -> Iterator[None]:
    """torch on one thread, as the run's worker: the same sums in the same order."""
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


def _odometry_base(root: Path, scan: np.ndarray) -> Path:
    """ROOT/odometry with sequence 00 holding `scan` as 000000.bin, calib.txt and times.txt."""
    base = root / "odometry"
    folder = base / "sequences" / "00"
    (folder / "velodyne").mkdir(parents=True)
    scan.astype(np.float32).tofile(folder / "velodyne" / "000000.bin")
    projection = " ".join(["1"] + ["0"] * 11)
    (folder / "calib.txt").write_text("\n".join([f"P{i}: {projection}" for i in range(4)]
                                                + ["Tr: 0 -1 0 0 0 0 -1 -0.08 1 0 0 -0.27"]) + "\n")
    (folder / "times.txt").write_text("0.0\n")
    return base


def test_every_python_block_of_the_readme_runs_verbatim(template_scans: list[np.ndarray], tmp_path: Path,
                                                        monkeypatch: pytest.MonkeyPatch,
                                                        make_config: Callable[..., PipelineConfig]) -> None:
    base = _odometry_base(tmp_path, template_scans[0])
    template_scans[0].tofile(tmp_path / "000000.bin")
    summary = run_pipeline(make_config(base, tmp_path / "OUT", output__formats="parquet,ply,kitti"), progress=False)
    assert summary.count("done") == 1
    monkeypatch.chdir(tmp_path)
    blocks = python_blocks()
    assert len(blocks) >= 5
    for number, block in enumerate(blocks, 1):
        namespace: dict[str, object] = {}
        try:
            exec(block.replace(README_DATA, str(base)), namespace)  # noqa: S102 - the README's own code
        except Exception as error:
            pytest.fail(f"README Python block {number} failed: {type(error).__name__}: {error}\n{block}")


def test_the_readme_chain_example_writes_what_kitti_pu_run_writes(template_scans: list[np.ndarray], tmp_path: Path,
                                                                  monkeypatch: pytest.MonkeyPatch,
                                                                  one_thread: None) -> None:
    base = _odometry_base(tmp_path, template_scans[0])

    monkeypatch.chdir(tmp_path)
    namespace: dict[str, object] = {}
    exec(chain_example().replace(README_DATA, str(base)), namespace)  # noqa: S102 - the README's own code
    frame = namespace["frame"]
    example = pq.read_table(tmp_path / "kitti-pu-out" / "points" / "odometry" / "00" / "000000.parquet")

    config = load_config(overrides={"input.path": str(base), "output.dir": str(tmp_path / "run"),
                                    "dask.n_workers": 1, "dask.torch_threads": 1})
    summary = run_pipeline(config, progress=False)
    assert summary.count("done") == 1
    written = pq.read_table(summary.frames[0].outputs["parquet"])
    assert written.num_rows == example.num_rows == len(frame.cloud) > len(template_scans[0])
    as_xyz = [np.column_stack([table[c].to_numpy() for c in "xyz"]) for table in (example, written)]
    np.testing.assert_array_equal(_sorted_xyz(as_xyz[0]), _sorted_xyz(as_xyz[1]))
    np.testing.assert_array_equal(_sorted_xyz(frame.cloud.xyz), _sorted_xyz(as_xyz[1]))
