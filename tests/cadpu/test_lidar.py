"""Tests of the simulated HDL-64E and of ring recovery from KITTI point order (cadpu.lidar)."""

from __future__ import annotations

import numpy as np
import pytest

from cadpu.lidar import (HDL64E, MOUNT_HEIGHT, LidarModel, SceneCaster, hdl64e_elevations, keep_rings, mount_pose,
                         recover_rings, simulate_scan, surface_reflectance)
from cadpu.street import BUILDING, ROAD, Scene, make_street
from cadpu.shapes import box


@pytest.fixture(scope="module")
def scene() -> Scene:
    return make_street(1, length_m=60.0, slope=0.03)


@pytest.fixture(scope="module")
def caster(scene: Scene) -> SceneCaster:
    return SceneCaster(scene)


@pytest.fixture(scope="module")
def scan(caster: SceneCaster, scene: Scene):
    return simulate_scan(caster, mount_pose(scene, 5.0), seed=4)


def _elevation_deg(points: np.ndarray) -> np.ndarray:
    return np.degrees(np.arctan2(points[:, 2], np.hypot(points[:, 0], points[:, 1])))


def test_elevations_span_the_hdl64e_field_of_view_in_two_blocks() -> None:
    elevation = hdl64e_elevations()
    assert elevation.shape == (64,)
    assert elevation[0] == pytest.approx(2.0) and elevation[-1] == pytest.approx(-24.8)
    assert np.all(np.diff(elevation) < 0)
    assert np.allclose(np.diff(elevation[:32]), -(2.0 + 8.33) / 31)  # upper block, 1/3 degree apart
    assert np.diff(elevation[31:33])[0] == pytest.approx(-0.5)  # gap between the blocks


def test_scan_has_documented_types_and_all_64_rings(scan) -> None:
    assert scan.points.dtype == np.float32 and scan.points.shape[1] == 4
    assert scan.ring.dtype == np.int16 and scan.labels.dtype == np.int32
    assert len(scan.ring) == len(scan.labels) == len(scan.points)
    assert np.array_equal(np.unique(scan.ring), np.arange(64))
    assert 80_000 < len(scan.points) <= 64 * HDL64E.azimuth_steps


def test_point_elevations_lie_in_the_field_of_view_and_match_their_ring(scan) -> None:
    elevation = _elevation_deg(scan.points.astype(np.float64))
    assert elevation.min() >= -24.8 - 1e-3 and elevation.max() <= 2.0 + 1e-3
    assert np.allclose(elevation, hdl64e_elevations()[scan.ring], atol=1e-3)


def test_points_are_in_kitti_order(scan) -> None:
    assert np.all(np.diff(scan.ring) >= 0)  # ring after ring, top laser first
    azimuth = np.arctan2(scan.points[:, 1], scan.points[:, 0])
    for ring in (0, 20, 63):
        a = azimuth[scan.ring == ring]
        # counter-clockwise from just above 0 through +-180 to just below 0
        unwrapped = np.where(a < 0, a + 2 * np.pi, a)
        assert a[0] >= 0 and np.all(np.diff(unwrapped) > 0)


def test_ground_under_the_sensor_is_mount_height_below(scan) -> None:
    near = (np.hypot(scan.points[:, 0], scan.points[:, 1]) < 12.0) & (scan.labels == ROAD)
    assert near.sum() > 1000
    z = scan.points[near, 2]
    assert np.median(z) == pytest.approx(-MOUNT_HEIGHT, abs=0.01)
    assert np.all(np.abs(z + MOUNT_HEIGHT) < 0.1)  # range noise of 2 cm, at most ~5 sigma


def test_points_land_on_the_scene_surfaces_in_the_world(scene: Scene, scan) -> None:
    pose = mount_pose(scene, 5.0)
    world = scan.points[:, :3].astype(np.float64) @ pose[:3, :3].T + pose[:3, 3]
    road = world[scan.labels == ROAD]
    assert np.abs(road[:, 2] - scene.slope * road[:, 0]).max() < 0.12


def test_range_noise_is_about_two_centimetres(scene: Scene, caster: SceneCaster) -> None:
    pose = mount_pose(scene, 5.0)
    quiet = simulate_scan(caster, pose, seed=4, model=LidarModel(range_noise=0.0))
    noisy = simulate_scan(caster, pose, seed=4)
    assert np.array_equal(quiet.ring, noisy.ring)
    difference = np.linalg.norm(noisy.points[:, :3], axis=1) - np.linalg.norm(quiet.points[:, :3], axis=1)
    assert np.std(difference) == pytest.approx(0.02, rel=0.1)


def test_same_seed_same_scan(scene: Scene, caster: SceneCaster, scan) -> None:
    again = simulate_scan(scene, mount_pose(scene, 5.0), seed=4)  # a plain Scene works too
    assert np.array_equal(again.points, scan.points) and np.array_equal(again.labels, scan.labels)
    other = simulate_scan(caster, mount_pose(scene, 5.0), seed=5)
    assert not np.array_equal(other.points[:100], scan.points[:100])


def test_rays_that_miss_or_reach_too_far_are_dropped() -> None:
    wall = box((1.0, 10.0, 10.0), (20.0, 0.0, 0.0))  # one wall 20 m ahead, filling about 28 degrees
    scene = Scene(wall.vertices, wall.triangles, np.full(len(wall.triangles), BUILDING, np.int32))
    scan = simulate_scan(scene, np.eye(4), seed=0)
    assert 0 < len(scan.points) < 0.1 * 64 * HDL64E.azimuth_steps
    assert np.all(scan.points[:, 0] > 19.0)
    short = simulate_scan(scene, np.eye(4), seed=0, model=LidarModel(max_range=15.0))
    assert len(short.points) == 0 and short.points.shape == (0, 4)


def test_reflectance_is_in_unit_range_and_weaker_at_grazing_incidence(scan) -> None:
    assert scan.points[:, 3].min() >= 0.0 and scan.points[:, 3].max() <= 1.0
    labels = np.full(2, BUILDING)
    head_on, grazing = surface_reflectance(labels, np.array([1.0, 0.05]), np.random.default_rng(0), noise=0.0)
    assert head_on > 2 * grazing > 0


def test_recover_rings_gives_back_the_simulated_rings_exactly(scan) -> None:
    rings = recover_rings(scan.points)
    assert rings.dtype == np.int64
    assert np.array_equal(rings, scan.ring)


def test_recover_rings_on_another_pose_and_seed(scene: Scene, caster: SceneCaster) -> None:
    scan = simulate_scan(caster, mount_pose(scene, 30.0, y=1.7, yaw=np.pi), seed=9)
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
    # a scan that starts with a point jittered just below 0
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


def test_keep_rings_keeps_every_fourth_ring(scan) -> None:
    kept = keep_rings(scan.points, scan.ring, every=4)
    kept_rings = keep_rings(scan.ring, scan.ring, every=4)
    assert len(kept) == len(kept_rings)
    assert np.array_equal(np.unique(kept_rings), np.arange(0, 64, 4))
    assert len(np.unique(kept_rings)) == 16
    shifted = keep_rings(scan.ring, scan.ring, every=4, offset=2)
    assert np.array_equal(np.unique(shifted), np.arange(2, 64, 4))
    # the kept points are still in KITTI order: their rings come back from the order alone
    assert np.array_equal(recover_rings(kept) * 4, kept_rings)


def test_keep_rings_rejects_bad_arguments(scan) -> None:
    with pytest.raises(ValueError, match="offset"):
        keep_rings(scan.points, scan.ring, every=4, offset=4)
    with pytest.raises(ValueError, match="ring ids"):
        keep_rings(scan.points, scan.ring[:-1])


def test_mount_pose_sits_above_the_road_and_pitches_with_it() -> None:
    scene = make_street(0, length_m=20.0, slope=0.05)
    pose = mount_pose(scene, 4.0, y=-1.0)
    assert np.allclose(pose[:3, :3] @ pose[:3, :3].T, np.eye(3))
    assert pose[:3, 0] @ np.array([1.0, 0.0, 0.05]) / np.linalg.norm([1.0, 0.0, 0.05]) == pytest.approx(1.0)
    # the road point straight below the sensor (along its -z axis) is on the road plane
    below = pose[:3, 3] - MOUNT_HEIGHT * pose[:3, 2]
    assert below[2] == pytest.approx(0.05 * below[0]) and below[1] == pytest.approx(-1.0)
    with pytest.raises(ValueError, match="pose"):
        simulate_scan(scene, np.eye(3))
