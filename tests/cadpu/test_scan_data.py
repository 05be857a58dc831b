import numpy as np
import pytest

from cadpu.scan_data import (INPUT_POINTS, TRUTH_POINTS, covering_sample, street_scan_patches,
                              thinned_scan_pairs, thinned_scan_patches)


def _ringed_wall(rings: int = 32, per_ring: int = 160) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A vertical wall at x = 10 m scanned by `rings` horizontal lines 5 cm apart (ring 0 on top)."""
    ring = np.repeat(np.arange(rings), per_ring)
    y = np.tile(np.linspace(-2.0, 2.0, per_ring), rings)
    z = 1.0 - 0.05 * ring
    points = np.stack([np.full(len(y), 10.0), y, z], axis=1)
    normals = np.tile([-1.0, 0.0, 0.0], (len(y), 1))
    return points, ring, normals


def test_input_keeps_one_ring_in_four_and_truth_holds_the_rings_between() -> None:
    points, ring, normals = _ringed_wall()
    rng = np.random.default_rng(0)
    inputs, truth, truth_normals = thinned_scan_patches(points, ring, normals, offset=1, count=3, rng=rng)
    assert inputs.shape == (3, INPUT_POINTS, 3) and truth.shape == (3, TRUTH_POINTS, 3)
    np.testing.assert_allclose(np.abs(truth_normals[..., 0]), 1.0)
    # Input heights are 4 ring spacings apart; the truth also holds the three rings in between.
    for patch_in, patch_truth in zip(inputs, truth):
        input_levels = np.unique(np.round(patch_in[:, 2], 4))
        truth_levels = np.unique(np.round(patch_truth[:, 2], 4))
        ring_gap = np.diff(input_levels)
        assert np.allclose(ring_gap, ring_gap[0], atol=2e-4)
        assert np.allclose(np.diff(truth_levels), ring_gap[0] / 4, atol=2e-4)
        assert set(input_levels) <= set(truth_levels)
    assert np.abs(np.linalg.norm(inputs, axis=2).max(axis=1) - 1).max() < 1e-5


def test_too_few_points_give_no_patches() -> None:
    points, ring, normals = _ringed_wall(rings=4, per_ring=100)
    inputs, truth, _ = thinned_scan_patches(points, ring, normals, 0, 5, np.random.default_rng(0))
    assert inputs.shape == (0, INPUT_POINTS, 3) and truth.shape == (0, TRUTH_POINTS, 3)


def test_street_scan_patches_are_deterministic() -> None:
    first = street_scan_patches(3, scans=1, patches_per_scan=4)
    again = street_scan_patches(3, scans=1, patches_per_scan=4)
    assert first[0].shape == (4, INPUT_POINTS, 3)
    for a, b in zip(first, again):
        np.testing.assert_array_equal(a, b)
    # the truth is denser than the input: its nearest-neighbour spacing is smaller
    from scipy.spatial import cKDTree

    spacing_in = cKDTree(first[0][0]).query(first[0][0], k=2)[0][:, 1].mean()
    unique_truth = np.unique(first[1][0], axis=0)
    spacing_truth = cKDTree(unique_truth).query(unique_truth, k=2)[0][:, 1].mean()
    assert spacing_truth < spacing_in


def test_vertical_scale_squashes_patches_and_keeps_normals_normal() -> None:
    points, ring, _ = _ringed_wall()
    # Tilt the wall (z rises with x) so its normal has a vertical part that the scaling changes.
    points[:, 0] += 0.5 * points[:, 2]
    normals = np.tile(np.array([-1.0, 0.0, 0.5]) / np.linalg.norm([-1.0, 0.0, 0.5]), (len(points), 1))
    scale = 0.2
    inputs, truth, truth_normals = thinned_scan_patches(points, ring, normals, 0, 2, np.random.default_rng(1),
                                                        vertical_scale=scale)
    unscaled, _, _ = thinned_scan_patches(points, ring, normals, 0, 2, np.random.default_rng(1))
    # Squashed rows sit closer together: a patch spans more of them.
    rows = lambda patches: np.mean([len(np.unique(np.round(p[:, 2], 3))) for p in patches])  # noqa: E731
    assert rows(inputs) > rows(unscaled)
    np.testing.assert_allclose(np.linalg.norm(truth_normals, axis=2), 1.0, atol=1e-5)
    # Normals stay perpendicular to the (scaled, normalised) surface: zero dot product with
    # directions within it, e.g. between truth points of one patch.
    for patch, normal in zip(truth, truth_normals):
        along = patch[1:] - patch[:1]
        np.testing.assert_allclose(np.einsum("ij,j->i", along, normal[0]), 0.0, atol=1e-4)


def test_covering_sample_keeps_every_point_of_a_small_region() -> None:
    rng = np.random.default_rng(0)
    region = np.arange(100, 1100, 2)  # 500 indices
    picked = covering_sample(region, TRUTH_POINTS, rng)
    assert picked.shape == (TRUTH_POINTS,)
    assert set(picked) == set(region)  # none left out, however the repeats fall
    counts = np.bincount(picked - 100)[::2]
    assert counts.min() >= 2 and counts.max() <= 3  # 1,024 = 2 * 500 + 24: each once, then repeats


def test_covering_sample_of_a_large_region_has_no_repeats() -> None:
    region = np.arange(5000)
    picked = covering_sample(region, TRUTH_POINTS, np.random.default_rng(1))
    assert len(np.unique(picked)) == TRUTH_POINTS


def test_covering_sample_of_nothing_is_an_error() -> None:
    with pytest.raises(ValueError, match="no indices"):
        covering_sample(np.array([], dtype=np.int64), TRUTH_POINTS, np.random.default_rng(0))


def test_frames_put_the_truth_back_in_the_sensor_frame_and_name_the_rings_between() -> None:
    points, ring, normals = _ringed_wall()
    inputs, truth, _, frames = thinned_scan_pairs(points, ring, normals, 1, 3, np.random.default_rng(2), 0.15)
    ring_height = {r: 1.0 - 0.05 * r for r in range(32)}
    for p in range(len(inputs)):
        tiled = truth[p] * frames.scale[p] + frames.centroid[p]
        metres = tiled / np.array([1.0, 1.0, frames.vertical_scale[p]])
        assert np.allclose(metres[:, 0], 10.0, atol=1e-4)  # on the wall, in metres
        between = frames.truth_ring[p] >= 0
        heights = np.round(metres[:, 2], 3)
        # the truth's points of rings 1, 5, 9, ... (the input's) are marked -1, the others are placed
        input_heights = {round(ring_height[r], 3) for r in range(1, 32, 4)}
        assert all((h in input_heights) != b for h, b in zip(heights, between))
        # each place names one ring, whose elevation is that ring's as seen from the origin
        elevations = frames.ring_elevations[p]
        for place in np.unique(frames.truth_ring[p][between]):
            on_ring = metres[frames.truth_ring[p] == place]
            assert np.ptp(on_ring[:, 2]) < 1e-4
            seen = np.arcsin(on_ring[:, 2] / np.linalg.norm(on_ring, axis=1))
            assert abs(np.median(seen) - elevations[place]) < 1e-6
        listed = elevations[np.isfinite(elevations)]
        assert np.all(np.diff(listed) > 0) and len(listed) == len(np.unique(frames.truth_ring[p][between]))


def test_the_pairs_without_frames_are_the_pairs_with_them() -> None:
    points, ring, normals = _ringed_wall()
    plain = thinned_scan_patches(points, ring, normals, 2, 2, np.random.default_rng(5))
    framed = thinned_scan_pairs(points, ring, normals, 2, 2, np.random.default_rng(5))
    for a, b in zip(plain, framed[:3]):
        np.testing.assert_array_equal(a, b)
