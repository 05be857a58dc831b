"""Fixtures shared by the test packages: one simulated street and a scan of it (its true ring of
every point known), used by the simulator's tests (tests/cadpu/synthetic) and the ring tests
(tests/stages)."""

from __future__ import annotations

import signal
from collections.abc import Iterator

import pytest

from cadpu.synthetic.lidar import ScanResult, SceneCaster, mount_pose, simulate_scan
from cadpu.synthetic.street import Scene, make_street


@pytest.fixture(autouse=True)
def own_signal_handlers() -> Iterator[None]:
    """Each test starts with the SIGINT and SIGTERM handlers the one before it found: the tests of a
    worker process share them, and tests that check a run gives its caller's handlers back (or that
    a signal stops it) failed, in two fresh-clone CI runs of three, after an earlier test of the same
    process left SIGINT ignored (which one was not found; the tests' own checks are unchanged)."""
    before = {number: signal.getsignal(number) for number in (signal.SIGINT, signal.SIGTERM)}
    yield
    for number, handler in before.items():
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
