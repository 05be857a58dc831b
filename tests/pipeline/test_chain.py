"""The chain of a frame's journey (pipeline.chain), run in process: its steps, how a stage's failure
travels down them, timings and the frame's report."""

from __future__ import annotations

import functools
import inspect
from pathlib import Path

import numpy as np
import pytest

from pipeline.chain import Chain, Step, report
from pipeline.config import PipelineConfig, load_config
from pipeline.summary import STAGES
from stages import fill, ground, load, snap, stitch, tile, upsample, write
from stages.errors import InputError, StageError


def _bin_ref(path: Path) -> load.FrameRef:
    refs = load.discover(path.parent, kind="bin")
    return next(ref for ref in refs if ref.source == str(path))


def test_the_chain_has_one_step_per_stage_in_order() -> None:
    assert [step.name for step in Chain().steps] == list(STAGES)
    assert [step.name for step in Chain(writes=False).steps] == list(STAGES[:-1])


def test_a_bad_scan_is_returned_as_its_error_and_passed_down_the_chain(tmp_path: Path) -> None:
    truncated = tmp_path / "000000.bin"
    truncated.write_bytes(b"\0" * 1001)
    config = load_config(overrides={"output.dir": str(tmp_path / "out")})
    steps = Chain(config).steps
    error = steps[0](_bin_ref(truncated))
    assert isinstance(error, InputError)
    assert error.stage == "load" and error.source == str(truncated) and "multiple of 16" in error.reason
    for step in steps[1:]:  # later stages hand the same error on without running
        assert step(error) is error
    assert report(error) is error
    assert not (tmp_path / "out").exists()
    with pytest.raises(InputError, match="multiple of 16"):
        Chain(config).run(_bin_ref(truncated))


def test_an_unexpected_exception_is_raised_naming_stage_and_frame(tmp_path: Path) -> None:
    scan = tmp_path / "000000.bin"
    np.full((200, 4), 5.0, np.float32).tofile(scan)  # not zeros: load drops returns at the sensor
    frame = Chain().steps[0](_bin_ref(scan))

    def broken(_: object) -> None:
        raise ValueError("no-such-method")

    with pytest.raises(StageError, match=r"^\[ground\] .*000000\.bin: ValueError: .*no-such-method") as raised:
        Step("ground", broken)(frame)
    assert not isinstance(raised.value, InputError) and raised.value.stage == "ground"
    assert isinstance(raised.value.__cause__, ValueError)


def test_each_step_times_its_stage_and_the_report_counts_the_cloud(tmp_path: Path) -> None:
    rng = np.random.default_rng(0)
    scan = tmp_path / "000007.bin"
    np.column_stack([rng.normal(size=(600, 3)) * [10, 10, 1], rng.uniform(size=600)]).astype(np.float32).tofile(scan)
    config = load_config(overrides={"output.dir": str(tmp_path / "out"), "output.formats": ["parquet"]})
    frame = Chain(config, metadata={"config_hash": "x"}).run(_bin_ref(scan))
    assert list(frame.timings) == list(STAGES) and all(seconds >= 0 for seconds in frame.timings.values())
    done = report(frame)
    assert done.status == "done" and done.index == 7 and done.points_in == 600
    assert done.points_out == len(frame.cloud) and done.generated == int(frame.cloud.generated.sum())
    assert Path(done.outputs["parquet"]).is_file() and set(done.timings) == set(STAGES)


STAGE_OPTIONS = {"input": load.Options, "ground": ground.Options, "tile": tile.Options,
                 "upsample": upsample.Options, "stitch": stitch.Options, "snap": snap.Options,
                 "fill": fill.Options, "output": write.Options}


@pytest.mark.parametrize("section", sorted(STAGE_OPTIONS))
def test_the_pipeline_defaults_are_the_stage_defaults(section: str) -> None:
    """A section of the default configuration equals its stage's Options(), and every keyword of the
    stage's plain functions that is also an option defaults to the option's value."""
    options = STAGE_OPTIONS[section]
    default = getattr(PipelineConfig(), section)
    assert {k: getattr(default, k) for k in options.model_fields} == options().model_dump()
    module = inspect.getmodule(options)
    for _, function in inspect.getmembers(module, inspect.isfunction):
        if function.__module__ != module.__name__:
            continue
        for name, parameter in inspect.signature(function).parameters.items():
            if name in options.model_fields and parameter.default is not inspect.Parameter.empty:
                expected = options.model_fields[name].get_default(call_default_factory=True)
                if isinstance(expected, dict):  # ground's params: a dict here, the method's dataclass there
                    continue
                given = tuple(parameter.default) if isinstance(expected, list) else parameter.default
                expected = tuple(expected) if isinstance(expected, list) else expected
                assert given == expected, f"{module.__name__}.{function.__name__}({name}=...)"
        if "options" in inspect.signature(function).parameters:
            assert inspect.signature(function).parameters["options"].default == options()


def test_a_step_is_a_stage_bound_to_its_section_of_the_config() -> None:
    config = load_config(overrides={"tile.vertical_scale": 0.5, "snap.range_tolerance": 0.1})
    steps = {step.name: step.function for step in Chain(config).steps}
    assert isinstance(steps["tile"], functools.partial) and steps["tile"].keywords["options"] is config.tile
    assert steps["snap"].keywords["options"].range_tolerance == 0.1


def test_a_frame_failing_after_load_reports_the_points_it_read() -> None:
    import pickle

    from pipeline.runner import _failed_report
    from stages.errors import StageError

    # a frame failing at write (a full disk) reported 0 points in, though load had read them (an
    # operator's trial)
    def full_disk(frame: object) -> object:
        raise StageError("write", "OUT/points/bin/s/000000.parquet", "cannot write (No space left on device)")

    frame = load.frame_from_points(np.random.default_rng(0).uniform(1, 20, size=(700, 4)).astype(np.float32))
    error = Step("write", full_disk)(frame)
    assert isinstance(error, StageError) and error.points_in == len(frame.points)
    carried = pickle.loads(pickle.dumps(error))  # as a Dask worker hands it back
    assert carried.points_in == len(frame.points) and str(carried) == str(error)
    ref = load.FrameRef(dataset="bin", sequence="s", index=0, source="s/000000.bin")
    assert _failed_report(ref, carried).points_in == len(frame.points)
