"""cadpu.patches: the balanced partition and the coverings built on it."""

from __future__ import annotations

import math

import numpy as np
import pytest

from cadpu.patches import balanced_cells, keep_owned, overlapping_patches, partitioned_patches, to_count


def _uneven_cloud(n: int, seed: int = 0) -> np.ndarray:
    """(n, 3): dense and sparse blobs, like the objects of a LiDAR scan."""
    rng = np.random.default_rng(seed)
    centres = rng.uniform(-30, 30, size=(8, 3))
    spread = rng.uniform(0.2, 3.0, size=8)
    which = rng.integers(0, 8, n)
    return centres[which] + rng.normal(size=(n, 3)) * spread[which, None]


@pytest.mark.parametrize("n, max_size", [(1000, 192), (192, 192), (193, 192), (5000, 100)])
def test_balanced_cells_are_full_and_near_equal(n: int, max_size: int) -> None:
    cell = balanced_cells(_uneven_cloud(n), max_size)
    size = np.bincount(cell)
    assert len(size) == math.ceil(n / max_size)
    assert size.max() <= max_size and size.max() - size.min() <= 1


def test_balanced_cells_are_spatially_compact() -> None:
    # Two far-apart blobs of 400 points each split into 4 cells: no cell mixes the blobs.
    rng = np.random.default_rng(1)
    points = np.concatenate([rng.normal(size=(400, 3)), rng.normal(size=(400, 3)) + 100.0])
    cell = balanced_cells(points, 200)
    assert set(cell[:400]).isdisjoint(set(cell[400:]))


def test_balanced_cells_split_each_group_along_its_widest_axis() -> None:
    # A 40 x 1 x 1 box of points: every split is along x, so the cells are slabs in x order.
    rng = np.random.default_rng(4)
    points = rng.uniform(0, 1, size=(1000, 3)) * [40.0, 1.0, 1.0]
    cell = balanced_cells(points, 125)
    upper = np.array([points[cell == c, 0].max() for c in range(8)])
    lower = np.array([points[cell == c, 0].min() for c in range(8)])
    assert (np.diff(upper) > 0).all() and (lower[1:] >= upper[:-1]).all()


@pytest.mark.parametrize("points", [np.zeros((700, 3)), np.round(np.random.default_rng(5).normal(size=(3000, 3)), 1)])
def test_balanced_cells_with_many_equal_points(points: np.ndarray) -> None:
    cell = balanced_cells(points, 100)
    size = np.bincount(cell)
    assert len(size) == math.ceil(len(points) / 100) and size.max() - size.min() <= 1


def test_partitioned_patches_own_their_cell_and_add_nearest_context() -> None:
    points = _uneven_cloud(3000, seed=2)
    cover = partitioned_patches(points, patch_size=256, overlap=4 / 3)
    assert cover.num_patches == math.ceil(3000 / 192)
    size = np.bincount(cover.owner)
    for patch in range(cover.num_patches):
        own = cover.point_index[patch, :size[patch]]
        context = cover.point_index[patch, size[patch]:]
        assert (cover.owner[own] == patch).all() and (cover.owner[context] != patch).all()
        assert len(np.unique(cover.point_index[patch])) == 256
        # The context is the outside points nearest the cell's centroid.
        outside = np.flatnonzero(cover.owner != patch)
        centroid = points[own].mean(axis=0)
        distance = np.linalg.norm(points[outside] - centroid, axis=1)
        nearest = outside[np.argsort(distance)[:len(context)]]
        assert set(context) == set(nearest)


def test_partitioned_patches_without_overlap_are_disjoint() -> None:
    cover = partitioned_patches(_uneven_cloud(1024, seed=3), patch_size=256, overlap=1.0)
    assert cover.num_patches == 4
    assert np.array_equal(np.sort(cover.point_index.ravel()), np.arange(1024))


def test_partitioned_patches_reject_bad_arguments() -> None:
    with pytest.raises(ValueError, match="at least 256"):
        partitioned_patches(_uneven_cloud(100), 256)
    with pytest.raises(ValueError, match="overlap"):
        partitioned_patches(_uneven_cloud(1000), 256, overlap=0.5)


@pytest.mark.parametrize("copies", [300, 700])
def test_a_cover_ends_when_more_than_a_patch_of_points_share_one_position(copies: int) -> None:
    # repeated "no return" points: every nearest-neighbour query from them returned the same 256
    # copies, so the cover looped for ever
    points = np.random.default_rng(0).normal(size=(1000 + copies, 3))
    points[:copies] = 0.0
    cover = overlapping_patches(points, patch_size=256)
    assert np.array_equal(np.unique(cover.point_index), np.arange(len(points)))
    assert cover.point_index.shape[1] == 256 and np.isfinite(cover.normalized).all()


def test_keep_owned_names_rows_that_are_not_of_the_patches_it_is_given() -> None:
    points = np.random.default_rng(0).normal(size=(2048, 3))
    cover = partitioned_patches(points, 256, 1.0)
    upsampled = np.repeat(cover.normalized, 4, axis=1)
    parents = np.tile(np.repeat(np.arange(256), 4), (len(upsampled), 1))
    # numpy's "shape mismatch" IndexError before, for a subset given without patches=
    with pytest.raises(ValueError, match=r"for the S = \d+ patches they are of \(all of the cover; pass patches="):
        keep_owned(cover, upsampled[:3], parents[:3])
    kept, source = keep_owned(cover, upsampled[:3], parents[:3], patches=np.arange(3))
    assert len(kept) == len(source) > 0
    # a parent beyond the patch's slots was numpy's IndexError, and -1 wrapped to the last slot
    for wrong in (300, -1):
        bad = parents.copy()
        bad[0, 5] = wrong
        with pytest.raises(ValueError, match="parents must be slots 0 to 255"):
            keep_owned(cover, upsampled, bad)


def test_keep_owned_takes_any_float_coordinates_and_names_what_it_refuses() -> None:
    points = np.random.default_rng(0).normal(size=(2048, 3))
    cover = partitioned_patches(points, 256, 1.0)
    upsampled = np.repeat(cover.normalized, 4, axis=1).astype(np.float32)
    parents = np.tile(np.repeat(np.arange(256), 4), (len(upsampled), 1))
    expected, _ = keep_owned(cover, upsampled, parents)
    # big-endian and float16 coordinates, which the upsampler takes, failed inside numba
    for kind in (">f4", np.float16):
        kept, _ = keep_owned(cover, upsampled.astype(kind), parents)
        np.testing.assert_allclose(kept, expected, atol=1e-2 if kind is np.float16 else 0)
    nan = upsampled.copy()
    nan[1, 7, 0] = np.nan
    cases = [((upsampled, parents.astype(float)), "parents must be whole numbers"),  # numpy's IndexError
             ((upsampled, parents, np.array([1.0])), "patches must be whole numbers"),
             ((upsampled[:1], parents[:1], np.array([99])), "patches must be indices 0 to 7"),  # numpy's IndexError
             ((nan, parents), "upsampled holds 1 non-finite values"),  # mapped back as NaN points before
             ((upsampled.astype(int), parents), "upsampled must be floating-point")]
    for arguments, message in cases:
        with pytest.raises(ValueError, match=message):
            keep_owned(cover, *arguments)


def test_to_count_drops_one_of_the_closest_pair_and_adds_into_the_widest_gap() -> None:
    grid = np.array([[x, y, 0.0] for x in range(4) for y in range(4)], dtype=np.float64)
    crowded = np.vstack([grid, [[0.05, 0.0, 0.0]]])  # a point beside the grid's first
    source = np.arange(len(crowded))
    points, kept_source = to_count(crowded, source, 16, np.zeros((0, 3)), np.zeros(0, np.int64), crowded)
    assert len(points) == 16
    assert len(set(kept_source) & {0, 16}) == 1  # one of the pair, not both
    # added: the spare that fills the widest gap on the input's own scale; one near a lone input
    # point, whose gaps are wide in metres, does not go first (a review found a lone point given 9
    # copies instead of 4), and one far from its source never goes
    origin = np.vstack([grid, [[50.0, 0.0, 0.0]]])
    kept = np.vstack([grid + [0.25, 0.25, 0.0], [[50.25, 0.25, 0.0]]])
    spare = np.array([[49.8, -0.2, 0.0], [1.0, 1.3, 0.0], [9.0, 9.0, 0.0]])
    wide = to_count(kept, np.arange(17), 18, spare, np.array([16, 5, 0]), origin)
    assert np.array_equal(wide[0][-1], spare[1]) and wide[1][-1] == 5
    assert np.array_equal(wide[0][:17], kept)
    with pytest.raises(ValueError, match="to_count: 20 points asked, 17 kept and 2 spare near their sources"):
        to_count(kept, np.arange(17), 20, spare, np.array([16, 5, 0]), origin)


def test_to_count_drops_past_the_close_pairs_when_it_must() -> None:
    points = np.random.default_rng(1).normal(size=(50, 3))
    kept, source = to_count(points, np.arange(50), 10, np.zeros((0, 3)), np.zeros(0, np.int64), points)
    assert len(kept) == 10 and len(np.unique(source)) == 10
    assert np.array_equal(kept, points[source])


@pytest.mark.parametrize("height", [1e6, 1.0])
def test_a_stray_points_patch_owns_only_it(height: float) -> None:
    # the patch of a point far from all others spans the gap, so widely normalised that the copies
    # of the others in it came out hundreds of units off; it owned those covered by no other patch,
    # and, a point only a little apart, those nearer to it than to another seed (a review)
    rng = np.random.default_rng(2)
    plane = np.c_[rng.uniform(size=(700, 2)), np.zeros(700)]
    points = np.vstack([plane, [[0.5, 0.5, height]]])
    for seed in range(6):
        cover = overlapping_patches(points, patch_size=256, seed=seed, stray_seeds=True)
        with_stray = np.flatnonzero(cover.point_index[:, 0] == 700)
        assert len(with_stray) == 1
        assert cover.owner[700] == with_stray[0]
        assert with_stray[0] not in set(cover.owner[:700])
        assert (cover.owner >= 0).all()
    # the pipeline's fps tiling keeps its covers (its output would change)
    plain = overlapping_patches(points, patch_size=256, seed=0)
    assert np.array_equal(plain.point_index, overlapping_patches(points, patch_size=256, seed=0,
                                                                 stray_seeds=False).point_index)
