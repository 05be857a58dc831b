import numpy as np
import pytest

from cadpu.baseline import midpoint_upsample, upsample_patches


def test_midpoints_stay_on_a_plane_and_count_is_r_times() -> None:
    rng = np.random.default_rng(0)
    plane = np.c_[rng.uniform(-1, 1, (256, 2)), np.zeros(256)]
    out, parents = midpoint_upsample(plane, 4)
    assert out.shape == (1024, 3)
    assert np.abs(out[:, 2]).max() < 1e-9
    assert np.bincount(parents).tolist() == [4] * 256


def test_duplicate_points_are_skipped_as_neighbours() -> None:
    points = np.random.default_rng(0).uniform(size=(200, 3))
    doubled = np.concatenate([points, points])  # every point twice
    out, parents = midpoint_upsample(doubled, 4)
    inserted = out[len(doubled):]
    assert np.linalg.norm(inserted - doubled[parents[len(doubled):]], axis=1).min() > 0  # a third sat on its parent


def test_points_of_the_wrong_shape_are_refused_naming_the_call() -> None:
    with pytest.raises(ValueError, match=r"midpoint_upsample: points must be an \(N, 3\) array, got shape \(50, 4\)"):
        midpoint_upsample(np.zeros((50, 4)), 4)
    points = np.random.default_rng(0).uniform(size=(50, 3))
    points[7, 1] = np.nan  # scipy's "data must be finite", not naming the call, before
    with pytest.raises(ValueError, match="midpoint_upsample: 1 point with NaN or infinite coordinates"):
        midpoint_upsample(points, 4)


def test_patches_are_taken_as_the_network_takes_them() -> None:
    # an empty batch and a single (K, 3) patch failed inside numpy ("need at least one array to stack")
    points, parents = upsample_patches(np.zeros((0, 256, 3), np.float32))
    assert points.shape == (0, 1024, 3) and parents.shape == (0, 1024)
    with pytest.raises(ValueError, match=r"upsample_patches: patches must be \(B, K, 3\), got \(256, 3\)"):
        upsample_patches(np.zeros((256, 3), np.float32))


def test_a_ratio_that_is_not_a_whole_number_is_refused() -> None:
    # 2.5 gave (900, 3) points with (600,) parents
    points = np.random.default_rng(0).normal(size=(300, 3))
    with pytest.raises(ValueError, match="ratio must be a whole number >= 2, got 2.5"):
        midpoint_upsample(points, 2.5)


@pytest.mark.parametrize("ratio", [2.5, 0, -1, 1])
def test_a_bad_ratio_is_refused_for_an_empty_batch_too(ratio: object) -> None:
    # 2.5 raised a bare TypeError, -1 numpy's "negative dimensions", 0 returned (0, 0, 3) (a trial)
    with pytest.raises(ValueError, match=f"upsample_patches: ratio must be a whole number >= 2, got {ratio!r}"):
        upsample_patches(np.zeros((0, 256, 3), np.float32), ratio)


def test_repeated_points_leave_the_tangent_planes_as_the_distinct_points_give_them() -> None:
    # the planes were fitted to neighbourhoods holding the point's own copies: on a sphere of 2,048
    # points each repeated 6 times, the inserted points lay 7 times further off it (a trial)
    rng = np.random.default_rng(0)
    sphere = rng.normal(size=(2048, 3))
    sphere /= np.linalg.norm(sphere, axis=1, keepdims=True)
    once, _ = midpoint_upsample(sphere, 4)
    repeated, _ = midpoint_upsample(np.repeat(sphere, 6, axis=0), 4)
    off = lambda points: np.abs(np.linalg.norm(points, axis=1) - 1.0).mean()  # noqa: E731
    assert off(repeated) < 1.5 * off(once)
