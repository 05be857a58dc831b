"""Tests of the measured sensor effects of the simulated HDL-64E (cadpu.synthetic.lidar): the two
blocks' elevations and heights, range noise growing with range, dropouts, second returns, and the
clean sensor kept bit for bit."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from cadpu.synthetic.lidar import (HDL64E, HDL64E_RANGE_BIASED, KITTI_BLOCK_OFFSETS_M, KITTI_ELEVATIONS_DEG,
                                   KITTI_RANGE_BIAS_M, MOUNT_HEIGHT, LidarModel, SceneCaster, in_shadow, mount_pose,
                                   simulate_scan)
from cadpu.synthetic.shapes import box
from cadpu.synthetic.street import ROAD, Scene, make_street
from stages.rings import recover_rings

SMALL = dict(azimuth_steps=360, max_range=40.0)


#: What the simulator of commit 38c710c (before LidarModel.clean existed) made of the call below:
#: its point count, points per ring, points per class, and sums over the points (x, y, z,
#: reflectance; the same weighted by each point's row, so the order counts too; the normals).
#: Sums, not a digest of the bytes: the float32 coordinates differ in their last bits from CPU to
#: CPU (the digest of one machine, an Intel one, failed on an AMD one whose output equals that
#: commit's there bit for bit), while a change of the sensor moves a sum by 1e-4 of it or more.
OLD_CLEAN_SCAN = {
    "points": 22110,
    "per ring": [304, 304, 301, 296, 298, 296, 297, 298, 301, 308, 308, 311, 311, 311, 312, 328, 332, 336]
                + [360] * 16 + [358] + [360] * 29,
    "per class": {0: 8242, 1: 1203, 2: 5844, 3: 5368, 4: 109, 5: 1242, 6: 102},
    "sums": [-12252.127627477188, 20255.321751784766, -23080.859988927616, 5226.767190859653],
    "row-weighted means": [-2879.1230910455106, 8857.807782718506, -14654.646583823062, 2440.4018368809284],
    "normal sums": [415.181611748897, 1812.062368426156, 11368.281886866145],
}


def test_clean_sensor_gives_the_scan_of_the_code_before_the_measured_effects() -> None:
    scene = make_street(3, length_m=30.0, slope=0.01)
    scan = simulate_scan(scene, mount_pose(scene, 4.0), seed=11, model=LidarModel.clean(**SMALL))
    points, rows = scan.points.astype(np.float64), np.arange(len(scan.points))
    assert len(points) == OLD_CLEAN_SCAN["points"]
    assert np.bincount(scan.ring).tolist() == OLD_CLEAN_SCAN["per ring"]
    assert dict(zip(*(values.tolist() for values in np.unique(scan.labels, return_counts=True)))) == \
        OLD_CLEAN_SCAN["per class"]
    np.testing.assert_allclose(points.sum(0), OLD_CLEAN_SCAN["sums"], rtol=1e-5)
    np.testing.assert_allclose((rows[:, None] * points).sum(0) / len(points), OLD_CLEAN_SCAN["row-weighted means"],
                               rtol=1e-5)
    np.testing.assert_allclose(scan.normals.astype(np.float64).sum(0), OLD_CLEAN_SCAN["normal sums"], rtol=1e-5)
    assert LidarModel.clean().is_clean and not HDL64E.is_clean


def test_measured_elevations_have_the_two_blocks_spacings_and_irregularity() -> None:
    upper, lower = -np.diff(KITTI_ELEVATIONS_DEG[:32]), -np.diff(KITTI_ELEVATIONS_DEG[32:])
    assert HDL64E.beams == 64 and np.array_equal(HDL64E.elevations_deg, KITTI_ELEVATIONS_DEG)
    assert 0.31 < upper.mean() < 0.37 and 0.46 < lower.mean() < 0.54  # about 1/3 and 1/2 degree
    assert np.all(upper > 0) and np.all(lower > 0) and upper.std() > 0.02  # ordered, irregular
    assert 0.3 < KITTI_ELEVATIONS_DEG[31] - KITTI_ELEVATIONS_DEG[32] < 0.45  # the gap between the blocks
    assert KITTI_BLOCK_OFFSETS_M[0] > KITTI_BLOCK_OFFSETS_M[1]


def test_each_ring_of_a_still_sensor_lies_on_its_lasers_cone(street_scene: Scene, street_caster: SceneCaster) -> None:
    still = dataclasses.replace(HDL64E, ego_speed=0.0)
    scan = simulate_scan(street_caster, mount_pose(street_scene, 5.0), seed=4, model=still)
    xyz = scan.points[:, :3].astype(np.float64)
    rho = np.hypot(xyz[:, 0], xyz[:, 1])
    h = np.asarray(HDL64E.vertical_offsets_m)[scan.ring]
    elevation = np.degrees(np.arctan2(xyz[:, 2] - h, rho))
    # range noise moves a point along its ray only
    assert np.allclose(elevation, KITTI_ELEVATIONS_DEG[scan.ring], atol=2e-3)
    seen_from_origin = np.degrees(np.arctan2(xyz[:, 2], rho))
    near = (scan.ring == 0) & (rho < 10)
    assert np.all(seen_from_origin[near] > KITTI_ELEVATIONS_DEG[0] + 0.5)  # 20 cm up: steeper when near


def test_a_moving_sensor_stores_its_scan_de_skewed_to_the_forward_azimuth() -> None:
    slab = box((400.0, 400.0, 1.0), (0.0, 0.0, -MOUNT_HEIGHT - 0.5))  # flat ground 1.73 m below
    ground = Scene(slab.vertices, slab.triangles, np.full(len(slab.triangles), ROAD, np.int32))
    quiet = dict(range_noise=0.0, range_noise_quadratic=0.0, dropout=0.0, dropout_growth=0.0, ego_shadow=())
    moving = simulate_scan(ground, np.eye(4), seed=1, model=dataclasses.replace(HDL64E, **quiet))
    still = simulate_scan(ground, np.eye(4), seed=1, model=dataclasses.replace(HDL64E, ego_speed=0.0, **quiet))
    assert np.allclose(moving.points[:, 2], -MOUNT_HEIGHT, atol=1e-4)  # still on the ground
    azimuth = np.degrees(np.arctan2(moving.points[:, 1], moving.points[:, 0]))
    rho = np.hypot(moving.points[:, 0], moving.points[:, 1])
    bottom = moving.ring == 63
    # behind the car the sweep starts (+180) with the sensor 0.5 * v * T back and ends (-180) as far ahead
    early, late = bottom & (azimuth > 170), bottom & (azimuth < -170)
    travel = HDL64E.ego_speed * HDL64E.sweep_period
    assert np.median(rho[early]) - np.median(rho[late]) == pytest.approx(travel * 175 / 180, rel=0.05)
    ahead = bottom & (np.abs(azimuth) < 2)  # fired as the sensor faced forward: where a still sensor's are
    assert np.median(rho[ahead]) == pytest.approx(np.median(np.hypot(*still.points[still.ring == 63, :2].T)), abs=0.01)
    # the upper rings see no ground; every ring that does is recovered from the order
    assert np.array_equal(recover_rings(moving.points), moving.ring - moving.ring.min())


def test_range_noise_follows_its_parameters(street_scene: Scene, street_caster: SceneCaster) -> None:
    pose = mount_pose(street_scene, 5.0)
    quiet = simulate_scan(street_caster, pose, seed=4, model=dataclasses.replace(
        HDL64E, range_noise=0.0, range_noise_quadratic=0.0))
    noisy = simulate_scan(street_caster, pose, seed=4)
    assert np.array_equal(quiet.ring, noisy.ring)  # dropouts and second returns draw the same
    origin = np.zeros((len(quiet.ring), 3))
    origin[:, 2] = np.asarray(HDL64E.vertical_offsets_m)[quiet.ring]
    r_quiet = np.linalg.norm(quiet.points[:, :3] - origin, axis=1)
    difference = np.linalg.norm(noisy.points[:, :3] - origin, axis=1) - r_quiet
    sigma = HDL64E.range_noise + HDL64E.range_noise_quadratic * r_quiet ** 2
    assert np.std(difference / sigma) == pytest.approx(1.0, rel=0.05)
    far = r_quiet > 40
    assert np.std(difference[far]) > 1.5 * np.std(difference[r_quiet < 10])


def test_dropouts_remove_points_in_order_and_keep_all_rings(street_scene: Scene, street_caster: SceneCaster) -> None:
    pose = mount_pose(street_scene, 30.0, y=1.7, yaw=np.pi)
    base = dataclasses.replace(HDL64E, range_noise=0.0, range_noise_quadratic=0.0, second_return_share=0.0,
                               dropout=0.0, dropout_growth=0.0)
    full = simulate_scan(street_caster, pose, seed=9, model=base)
    holey = simulate_scan(street_caster, pose, seed=9, model=dataclasses.replace(base, dropout=0.3))
    assert len(holey.points) / len(full.points) == pytest.approx(0.7, abs=0.01)
    # the kept points are a subsequence of the full scan: same order, nothing moved
    rows = {row.tobytes(): i for i, row in enumerate(full.points[:, :3])}  # (reflectance noise differs)
    index = np.array([rows[row.tobytes()] for row in holey.points[:, :3]])
    assert np.all(np.diff(index) > 0)
    rings = recover_rings(holey.points)
    assert rings.max() + 1 == 64 and np.array_equal(rings, holey.ring)


def test_dropouts_grow_with_range(street_scene: Scene, street_caster: SceneCaster) -> None:
    pose = mount_pose(street_scene, 5.0)
    base = dataclasses.replace(HDL64E, second_return_share=0.0, dropout=0.0, dropout_growth=0.0)
    full = simulate_scan(street_caster, pose, seed=4, model=base)
    lossy = simulate_scan(street_caster, pose, seed=4, model=dataclasses.replace(base, dropout_growth=0.01,
                                                                                 dropout_start=10.0))
    r_full, r_lossy = (np.linalg.norm(s.points[:, :3], axis=1) for s in (full, lossy))
    near = np.sum(r_lossy < 9) / np.sum(r_full < 9)
    mid = np.sum((r_lossy > 25) & (r_lossy < 35)) / np.sum((r_full > 25) & (r_full < 35))
    far = np.sum(r_lossy > 45) / np.sum(r_full > 45)  # no growth beyond dropout_end (40 m)
    assert near == pytest.approx(1.0, abs=0.005) and mid == pytest.approx(1 - 0.01 * 20, abs=0.04)
    assert far == pytest.approx(1 - 0.01 * 30, abs=0.07) and np.sum(r_full > 45) > 300  # 3 binomial sd


def test_second_returns_follow_their_firing_half_a_step_later(street_scan) -> None:
    azimuth = np.degrees(np.arctan2(street_scan.points[:, 1], street_scan.points[:, 0]))
    same_ring = street_scan.ring[1:] == street_scan.ring[:-1]
    step = np.mod(np.diff(azimuth) + 180, 360)[same_ring] - 180
    firing = 360 / HDL64E.azimuth_steps
    half = np.mean(np.abs(step - firing / 2) < 0.05 * firing)
    share = HDL64E.second_return_share  # each second return makes two half steps: before and after it
    assert half == pytest.approx(2 * share / (1 + share), rel=0.15)
    assert np.array_equal(recover_rings(street_scan.points), street_scan.ring)


def test_the_car_hides_the_ground_behind_it_from_the_lowest_lasers(street_scan) -> None:
    azimuth = np.mod(np.degrees(np.arctan2(street_scan.points[:, 1], street_scan.points[:, 0])), 360)
    behind = (azimuth > 175) & (azimuth < 190)
    assert not np.any(behind & (street_scan.ring >= 52))  # below -19.3 degrees there (KITTI_EGO_SHADOW)
    assert np.sum(behind & (street_scan.ring >= 40) & (street_scan.ring < 52)) > 12 * 50
    counts = np.bincount(street_scan.ring, minlength=64)
    assert counts[63] < 0.75 * counts[40]
    assert not np.any(in_shadow(HDL64E.ego_shadow, np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0]])))
    assert np.all(in_shadow(HDL64E.ego_shadow, np.array([[-0.9, 0.0, -0.45], [0.9, 0.0, -0.45]])))  # -26.6 deg


def test_a_model_needs_one_offset_per_laser() -> None:
    with pytest.raises(ValueError, match="vertical offsets"):
        LidarModel(elevations_deg=np.linspace(2, -24, 16))
    assert LidarModel.clean(elevations_deg=np.linspace(2, -24, 16), vertical_offsets_m=np.zeros(16)).beams == 16


def test_range_biases_move_each_lasers_returns_along_its_beams(street_scene: Scene, street_caster: SceneCaster) -> None:
    pose = mount_pose(street_scene, 5.0)
    plain = simulate_scan(street_caster, pose, seed=2, model=dataclasses.replace(HDL64E, **SMALL))
    biased = simulate_scan(street_caster, pose, seed=2, model=dataclasses.replace(HDL64E_RANGE_BIASED, **SMALL))
    assert np.array_equal(plain.ring, biased.ring) and np.array_equal(plain.labels, biased.labels)
    shift = biased.points[:, :3].astype(np.float64) - plain.points[:, :3]
    expected = KITTI_RANGE_BIAS_M[plain.ring]
    assert np.allclose(np.linalg.norm(shift, axis=1), np.abs(expected), atol=1e-5)
    beam = plain.points[:, :3] / np.linalg.norm(plain.points[:, :3], axis=1, keepdims=True)
    along = np.einsum("ij,ij->i", shift, beam)  # along the beam (the lasers sit within 21 cm of the origin)
    assert np.allclose(along, expected, atol=2e-3)
    assert not HDL64E_RANGE_BIASED.is_clean and HDL64E.range_bias_m is None
    with pytest.raises(ValueError, match="range biases"):
        LidarModel(range_bias_m=np.zeros(16))
