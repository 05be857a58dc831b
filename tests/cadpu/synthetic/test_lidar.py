"""Tests of the simulated HDL-64E (cadpu.synthetic.lidar)."""

from __future__ import annotations

import numpy as np
import pytest

from cadpu.synthetic.lidar import (HDL64E, MOUNT_HEIGHT, LidarModel, SceneCaster, hdl64e_elevations, mount_pose,
                                   simulate_scan, surface_reflectance)
from cadpu.synthetic.street import BUILDING, ROAD, Scene, make_street
from cadpu.synthetic.shapes import box


def _elevation_deg(points: np.ndarray) -> np.ndarray:
    return np.degrees(np.arctan2(points[:, 2], np.hypot(points[:, 0], points[:, 1])))


def test_elevations_span_the_hdl64e_field_of_view_in_two_blocks() -> None:
    elevation = hdl64e_elevations()
    assert elevation.shape == (64,)
    assert elevation[0] == pytest.approx(2.0) and elevation[-1] == pytest.approx(-24.8)
    assert np.all(np.diff(elevation) < 0)
    assert np.allclose(np.diff(elevation[:32]), -(2.0 + 8.33) / 31)  # upper block, 1/3 degree apart
    assert np.diff(elevation[31:33])[0] == pytest.approx(-0.5)  # gap between the blocks


def test_scan_has_documented_types_and_all_64_rings(street_scan) -> None:
    assert street_scan.points.dtype == np.float32 and street_scan.points.shape[1] == 4
    assert street_scan.ring.dtype == np.int16 and street_scan.labels.dtype == np.int32
    assert len(street_scan.ring) == len(street_scan.labels) == len(street_scan.points)
    assert np.array_equal(np.unique(street_scan.ring), np.arange(64))
    assert 80_000 < len(street_scan.points) <= 64 * HDL64E.azimuth_steps * (1 + 2 * HDL64E.second_return_share)


def test_clean_point_elevations_lie_in_the_field_of_view_and_match_their_ring(
        street_scene: Scene, street_caster: SceneCaster) -> None:
    scan = simulate_scan(street_caster, mount_pose(street_scene, 5.0), seed=4, model=LidarModel.clean())
    elevation = _elevation_deg(scan.points.astype(np.float64))
    assert elevation.min() >= -24.8 - 1e-3 and elevation.max() <= 2.0 + 1e-3
    assert np.allclose(elevation, hdl64e_elevations()[scan.ring], atol=1e-3)


def test_points_are_in_kitti_order(street_scene: Scene, street_caster: SceneCaster, street_scan) -> None:
    assert np.all(np.diff(street_scan.ring) >= 0)  # ring after ring, top laser first
    # a sensor that stands still: azimuths strictly increase (a moving one's jitter near the car)
    scan = simulate_scan(street_caster, mount_pose(street_scene, 5.0), seed=4, model=LidarModel.clean())
    azimuth = np.arctan2(scan.points[:, 1], scan.points[:, 0])
    for ring in (0, 20, 63):
        a = azimuth[scan.ring == ring]
        # counter-clockwise from just above 0 through +-180 to just below 0
        unwrapped = np.where(a < 0, a + 2 * np.pi, a)
        assert a[0] >= 0 and np.all(np.diff(unwrapped) > 0)


def test_ground_under_the_sensor_is_mount_height_below(street_scan) -> None:
    near = (np.hypot(street_scan.points[:, 0], street_scan.points[:, 1]) < 12.0) & (street_scan.labels == ROAD)
    assert near.sum() > 1000
    z = street_scan.points[near, 2]
    assert np.median(z) == pytest.approx(-MOUNT_HEIGHT, abs=0.01)
    assert np.all(np.abs(z + MOUNT_HEIGHT) < 0.1)  # range noise of about 1 cm, at most ~5 sigma


def test_points_land_on_the_scene_surfaces_in_the_world(street_scene: Scene, street_scan) -> None:
    pose = mount_pose(street_scene, 5.0)
    world = street_scan.points[:, :3].astype(np.float64) @ pose[:3, :3].T + pose[:3, 3]
    road = world[street_scan.labels == ROAD]
    assert np.abs(road[:, 2] - street_scene.slope * road[:, 0]).max() < 0.12


def test_clean_range_noise_is_about_two_centimetres(street_scene: Scene, street_caster: SceneCaster) -> None:
    pose = mount_pose(street_scene, 5.0)
    quiet = simulate_scan(street_caster, pose, seed=4, model=LidarModel.clean(range_noise=0.0))
    noisy = simulate_scan(street_caster, pose, seed=4, model=LidarModel.clean())
    assert np.array_equal(quiet.ring, noisy.ring)
    difference = np.linalg.norm(noisy.points[:, :3], axis=1) - np.linalg.norm(quiet.points[:, :3], axis=1)
    assert np.std(difference) == pytest.approx(0.02, rel=0.1)


def test_same_seed_same_scan(street_scene: Scene, street_caster: SceneCaster, street_scan) -> None:
    again = simulate_scan(street_scene, mount_pose(street_scene, 5.0), seed=4)  # a plain Scene works too
    assert np.array_equal(again.points, street_scan.points) and np.array_equal(again.labels, street_scan.labels)
    other = simulate_scan(street_caster, mount_pose(street_scene, 5.0), seed=5)
    assert not np.array_equal(other.points[:100], street_scan.points[:100])


def test_rays_that_miss_or_reach_too_far_are_dropped() -> None:
    wall = box((1.0, 10.0, 10.0), (20.0, 0.0, 0.0))  # one wall 20 m ahead, filling about 28 degrees
    scene = Scene(wall.vertices, wall.triangles, np.full(len(wall.triangles), BUILDING, np.int32))
    scan = simulate_scan(scene, np.eye(4), seed=0)
    assert 0 < len(scan.points) < 0.1 * 64 * HDL64E.azimuth_steps
    assert np.all(scan.points[:, 0] > 19.0)
    short = simulate_scan(scene, np.eye(4), seed=0, model=LidarModel(max_range=15.0))
    assert len(short.points) == 0 and short.points.shape == (0, 4)


def test_reflectance_is_in_unit_range_and_weaker_at_grazing_incidence(street_scan) -> None:
    assert street_scan.points[:, 3].min() >= 0.0 and street_scan.points[:, 3].max() <= 1.0
    labels = np.full(2, BUILDING)
    head_on, grazing = surface_reflectance(labels, np.array([1.0, 0.05]), np.random.default_rng(0), noise=0.0)
    assert head_on > 2 * grazing > 0


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
