"""The Dask task functions (pipeline.tasks), called in process: how a stage's failure travels
down a frame's chain of tasks."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from pipeline import tasks
from stages import load
from stages.errors import InputError, StageError


def _bin_ref(path: Path) -> load.FrameRef:
    refs = load.discover(path.parent, kind="bin")
    return next(ref for ref in refs if ref.source == str(path))


def test_a_bad_scan_is_returned_as_its_error_and_passed_down_the_chain(tmp_path: Path) -> None:
    truncated = tmp_path / "000000.bin"
    truncated.write_bytes(b"\0" * 1001)
    error = tasks.load_task(_bin_ref(truncated), 1_000_000)
    assert isinstance(error, InputError)
    assert error.stage == "load" and error.source == str(truncated) and "multiple of 16" in error.reason
    # later stages hand the same error on without running
    assert tasks.ground_task(error, "patchwork", {}) is error
    assert tasks.tile_task(error, 256, 1.0, 0, "partition", 0.15) is error
    assert tasks.write_task(error, str(tmp_path / "out"), ("parquet",), {}) is error
    assert not (tmp_path / "out").exists()


def test_an_unexpected_exception_is_raised_naming_stage_and_frame(tmp_path: Path) -> None:
    scan = tmp_path / "000000.bin"
    np.zeros((200, 4), np.float32).tofile(scan)
    frame = tasks.load_task(_bin_ref(scan), 1_000_000)
    with pytest.raises(StageError, match=r"^\[ground\] .*000000\.bin: ValueError: .*no-such-method") as raised:
        tasks.ground_task(frame, "no-such-method", {})
    assert not isinstance(raised.value, InputError) and raised.value.stage == "ground"
