"""Fixtures shared by the test packages: one simulated street and a scan of it (its true ring of
every point known), used by the simulator's tests (tests/cadpu/synthetic) and the ring tests
(tests/stages)."""

from __future__ import annotations

import signal
from collections.abc import Iterator

import pytest

from cadpu.synthetic.lidar import ScanResult, SceneCaster, mount_pose, simulate_scan
from cadpu.synthetic.street import Scene, make_street


#: The SIGINT and SIGTERM handlers this test process started with.
STARTING_HANDLERS = {number: signal.getsignal(number) for number in (signal.SIGINT, signal.SIGTERM)}


@pytest.fixture(autouse=True)
def starting_signal_handlers() -> Iterator[None]:
    """After each test, the SIGINT and SIGTERM handlers the process started with are put back
    where the test (or a fixture it set up) left others. The tests of a worker process share
    them: in two fresh-clone CI runs of three, tests that check a run gives its caller's handlers
    back, or that a signal stops it, failed after something earlier in the same process left
    SIGINT ignored (which, a per-test check did not catch). Those tests' own checks are unchanged."""
    yield
    for number, handler in STARTING_HANDLERS.items():
        if handler is not None and signal.getsignal(number) is not handler:
            signal.signal(number, handler)


@pytest.fixture(scope="session")
def street_scene() -> Scene:
    """A 60 m street with a 3% slope (seed 1)."""
    return make_street(1, length_m=60.0, slope=0.03)


@pytest.fixture(scope="session")
def street_caster(street_scene: Scene) -> SceneCaster:
    """`street_scene` loaded for ray casting."""
    return SceneCaster(street_scene)


@pytest.fixture(scope="session")
def street_scan(street_caster: SceneCaster, street_scene: Scene) -> ScanResult:
    """One simulated HDL-64E scan of `street_scene`, 5 m along it (seed 4)."""
    return simulate_scan(street_caster, mount_pose(street_scene, 5.0), seed=4)
