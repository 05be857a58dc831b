"""Tests of ring recovery from KITTI point order and ring thinning (stages.rings), on simulated
scans (`street_scan` and friends: tests/conftest.py) whose true rings are known."""

from __future__ import annotations

import numpy as np
import pytest

from cadpu.synthetic.lidar import SceneCaster, mount_pose, simulate_scan
from cadpu.synthetic.street import Scene
from stages.rings import keep_rings, recover_rings


def test_recover_rings_gives_back_the_simulated_rings_exactly(street_scan) -> None:
    rings = recover_rings(street_scan.points)
    assert rings.dtype == np.int64
    assert np.array_equal(rings, street_scan.ring)


def test_recover_rings_on_another_pose_and_seed(street_scene: Scene, street_caster: SceneCaster) -> None:
    scan = simulate_scan(street_caster, mount_pose(street_scene, 30.0, y=1.7, yaw=np.pi), seed=9)
    assert np.array_equal(recover_rings(scan.points), scan.ring)


def _ring_points(azimuth_deg: np.ndarray, ring_count: int = 1) -> np.ndarray:
    azimuth = np.radians(np.tile(azimuth_deg, ring_count))
    return np.stack([np.cos(azimuth), np.sin(azimuth), np.zeros_like(azimuth)], axis=1) * 10.0


def test_recover_rings_ignores_jitter_at_zero_and_at_the_rear_seam() -> None:
    # one ring: starts at 0.1, jitters back across 0 right after its start, and crosses the
    # -180/+180 seam with jitter: still one ring
    ring = np.concatenate([[0.1, -0.05, 0.2], np.arange(1.0, 179.9, 1.0), [179.95, -179.95, 179.9, -179.8],
                           np.arange(-179.0, -0.5, 1.0), [-0.3]])
    assert np.all(recover_rings(_ring_points(ring)) == 0)
    # a street_scan that starts with a point jittered just below 0
    assert np.all(recover_rings(_ring_points(np.concatenate([[-0.05], ring[1:]]))) == 0)
    # three such rings in a row give three rings, each whole
    three = recover_rings(_ring_points(ring, 3))
    assert np.array_equal(three, np.repeat([0, 1, 2], len(ring)))


def test_recover_rings_splits_rings_with_returns_on_one_side_only() -> None:
    left_only = np.arange(10.0, 170.0, 1.0)  # e.g. a top laser that sees a facade on the left only
    rings = recover_rings(_ring_points(left_only, 4))
    assert np.array_equal(rings, np.repeat(np.arange(4), len(left_only)))


def test_recover_rings_accepts_extra_columns_and_empty_input() -> None:
    points = np.c_[_ring_points(np.arange(0.0, 360.0, 2.0) - 180.0 + 0.5), np.ones(180)]
    assert recover_rings(points).shape == (180,)
    assert recover_rings(np.zeros((0, 4))).shape == (0,)
    with pytest.raises(ValueError, match="recover_rings"):
        recover_rings(np.zeros(5))


@pytest.mark.parametrize("bad", [np.nan, np.inf])
def test_recover_rings_refuses_a_point_without_an_azimuth(street_scan, bad: float) -> None:
    # a NaN made every later point ring 0's, silently (a review)
    points = street_scan.points.copy()
    points[100, 1] = bad
    with pytest.raises(ValueError, match="rings: 1 point with NaN or infinite x or y \\(the first at index 100\\)"):
        recover_rings(points)


def test_keep_rings_keeps_every_fourth_ring(street_scan) -> None:
    kept = keep_rings(street_scan.points, street_scan.ring, ratio=4)
    kept_rings = keep_rings(street_scan.ring, street_scan.ring, ratio=4)
    assert len(kept) == len(kept_rings)
    assert np.array_equal(np.unique(kept_rings), np.arange(0, 64, 4))
    assert len(np.unique(kept_rings)) == 16
    shifted = keep_rings(street_scan.ring, street_scan.ring, ratio=4, offset=2)
    assert np.array_equal(np.unique(shifted), np.arange(2, 64, 4))
    # the kept points are still in KITTI order: their rings come back from the order alone
    assert np.array_equal(recover_rings(kept) * 4, kept_rings)


def test_keep_rings_rejects_bad_arguments(street_scan) -> None:
    with pytest.raises(ValueError, match="offset"):
        keep_rings(street_scan.points, street_scan.ring, ratio=4, offset=4)
    with pytest.raises(ValueError, match="ring ids"):
        keep_rings(street_scan.points, street_scan.ring[:-1])
    with pytest.raises(ValueError, match="whole numbers"):  # 2.5 kept rings 0, 5, 10, ... (a library user's trial)
        keep_rings(street_scan.points, street_scan.ring, ratio=2.5)
