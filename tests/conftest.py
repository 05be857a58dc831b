"""Fixtures shared by the test packages: one simulated street and a scan of it (its true ring of
every point known), used by the simulator's tests (tests/cadpu/synthetic) and the ring tests
(tests/stages)."""

from __future__ import annotations

import signal
from collections.abc import Iterator

import pytest

from cadpu.synthetic.lidar import ScanResult, SceneCaster, mount_pose, simulate_scan
from cadpu.synthetic.street import Scene, make_street


# A process started in the background by a shell without job control (`cmd &` in a script) has
# SIGINT ignored, and so have the processes it starts: the tests of Ctrl-C then failed, their runs
# never seeing the signal (three tests, in a fresh-clone CI started that way). They need it handled.
if signal.getsignal(signal.SIGINT) is signal.SIG_IGN:
    signal.signal(signal.SIGINT, signal.default_int_handler)
#: The SIGINT and SIGTERM handlers this test process runs its tests with.
STARTING_HANDLERS = {number: signal.getsignal(number) for number in (signal.SIGINT, signal.SIGTERM)}


@pytest.fixture(autouse=True)
def starting_signal_handlers() -> Iterator[None]:
    """After each test, `STARTING_HANDLERS` are put back where the test (or a fixture it set up)
    left others: the tests of a worker process share them."""
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
