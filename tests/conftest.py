"""Fixtures shared by the test packages: one simulated street and a scan of it (its true ring of
every point known), used by the simulator's tests (tests/cadpu/synthetic) and the ring tests
(tests/stages)."""

from __future__ import annotations

import pytest

from cadpu.synthetic.lidar import ScanResult, SceneCaster, mount_pose, simulate_scan
from cadpu.synthetic.street import Scene, make_street


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
