"""stages.tile: patches cover every non-ground point, owners hold their points, patches are
normalised to the unit sphere, and too-small frames pass through with a note."""

from __future__ import annotations

import math

import numpy as np
import pytest
from pydantic import ValidationError

from stages import tile
from stages.frame import Frame


def _street_points(n: int, seed: int = 0) -> np.ndarray:
    """(n, 4) float32: an uneven mix of dense and sparse clusters, like a LiDAR scan's objects."""
    rng = np.random.default_rng(seed)
    centres = rng.uniform(-30, 30, size=(12, 3))
    spread = rng.uniform(0.2, 3.0, size=12)
    which = rng.integers(0, 12, n)
    xyz = centres[which] + rng.normal(size=(n, 3)) * spread[which, None]
    return np.column_stack([xyz, rng.uniform(0, 1, n)]).astype(np.float32)


def _frame(points: np.ndarray, ground: np.ndarray | None = None) -> Frame:
    return Frame(points=points, dataset="bin", sequence="t", index=3, ground=ground)


@pytest.mark.parametrize("method", tile.TILING_METHODS)
def test_tile_points_cover_every_point_by_its_owner(method: str) -> None:
    xyz = _street_points(5000)[:, :3]
    tiling = tile.tile_points(xyz, patch_size=256, overlap=1.0, seed=0, method=method, vertical_scale=1.0)
    p = tiling.num_patches
    assert tiling.point_index.shape == (p, 256) and tiling.owner.shape == (5000,)
    assert p >= math.ceil(5000 / 256)
    assert tiling.owner.min() >= 0 and tiling.owner.max() < p
    # Every point is inside the patch that owns it.
    assert (tiling.point_index[tiling.owner] == np.arange(5000)[:, None]).any(axis=1).all()
    # Patches are nearest-neighbour sets: no repeated point within a patch.
    assert all(len(np.unique(row)) == 256 for row in tiling.point_index)


@pytest.mark.parametrize("method", tile.TILING_METHODS)
def test_tile_points_normalise_to_unit_sphere_and_invert(method: str) -> None:
    xyz = _street_points(3000, seed=1)[:, :3].astype(np.float64)
    tiling = tile.tile_points(xyz, patch_size=256, overlap=1.0, seed=0, method=method, vertical_scale=1.0)
    assert tiling.normalized.dtype == np.float32 and tiling.normalized.shape == (tiling.num_patches, 256, 3)
    radius = np.linalg.norm(tiling.normalized, axis=2)
    assert radius.max() <= 1 + 1e-5
    assert np.allclose(radius.max(axis=1), 1.0, atol=1e-5)  # scale is the farthest point
    assert np.allclose(tiling.normalized.mean(axis=1), 0.0, atol=1e-5)
    restored = tiling.normalized * tiling.scale[:, None, None] + tiling.centroid[:, None, :]
    assert np.allclose(restored, xyz[tiling.point_index], atol=1e-4 * tiling.scale.max())


@pytest.mark.parametrize("method", tile.TILING_METHODS)
def test_more_overlap_gives_more_patches(method: str) -> None:
    xyz = _street_points(4000, seed=2)[:, :3]
    assert (tile.tile_points(xyz, 256, 2.0, 0, method, vertical_scale=1.0).num_patches
            > tile.tile_points(xyz, 256, 1.0, 0, method, vertical_scale=1.0).num_patches >= math.ceil(4000 / 256))


def test_partition_needs_fewer_patches_than_fps_on_uneven_density() -> None:
    xyz = _street_points(6000, seed=6)[:, :3]
    partition = tile.tile_points(xyz, 256, 4 / 3, 0, "partition", vertical_scale=1.0)
    assert partition.num_patches == math.ceil(6000 / 192)
    assert partition.num_patches < tile.tile_points(xyz, 256, 1.0, 0, "fps", vertical_scale=1.0).num_patches


def _rows(rings: int = 32, per_ring: int = 100, ring_gap: float = 0.25, spacing: float = 0.025) -> np.ndarray:
    """(rings * per_ring, 3) a wall sampled as a spinning LiDAR does: rows along x, far apart in z."""
    x, z = np.meshgrid(np.arange(per_ring) * spacing, np.arange(rings) * ring_gap)
    return np.column_stack([x.ravel(), np.full(x.size, 10.0), z.ravel()])


@pytest.mark.parametrize("method", tile.TILING_METHODS)
def test_vertical_scale_tiles_squashed_points_and_records_it(method: str) -> None:
    xyz = _rows()
    tiling = tile.tile_points(xyz, 256, 1.0, 0, method, vertical_scale=0.1)
    assert np.array_equal(tiling.axis_scale, [1.0, 1.0, 0.1])
    restored = tiling.normalized * tiling.scale[:, None, None] + tiling.centroid[:, None, :]
    assert np.allclose(restored, xyz[tiling.point_index] * [1.0, 1.0, 0.1], atol=1e-4 * tiling.scale.max())
    # Squashed, a patch of 256 points spans more rows (and less of each row) than unscaled.
    rows_per_patch = lambda t: np.mean([len(np.unique(xyz[row, 2])) for row in t.point_index])  # noqa: E731
    assert rows_per_patch(tiling) > 2 * rows_per_patch(tile.tile_points(xyz, 256, 1.0, 0, method, vertical_scale=1.0))


@pytest.mark.parametrize("scale", [0.0, -1.0, float("nan")])
def test_vertical_scale_must_be_positive(scale: float) -> None:
    with pytest.raises(ValueError, match="vertical_scale must be > 0"):
        tile.tile_points(_rows(), vertical_scale=scale)


@pytest.mark.parametrize("scale", [float("inf"), 1e305])
def test_options_refuse_a_vertical_scale_that_overflows(scale: float) -> None:
    # accepted as a setting (gt=0 alone), then every frame failed as if its scan were bad (a review)
    with pytest.raises(ValidationError, match="vertical_scale"):
        tile.Options(vertical_scale=scale)
    from pipeline.config import ConfigError, load_config

    with pytest.raises(ConfigError, match="vertical_scale"):
        load_config(overrides={"tile.vertical_scale": scale})


def test_unknown_method_is_named() -> None:
    with pytest.raises(ValueError, match="unknown method 'grid'"):
        tile.tile_points(_street_points(300)[:, :3], method="grid")


@pytest.mark.parametrize("method", tile.TILING_METHODS)
def test_tiling_is_deterministic_for_a_seed(method: str) -> None:
    xyz = _street_points(2000, seed=3)[:, :3]
    first, second = tile.tile_points(xyz, 256, 1.0, 5, method, vertical_scale=1.0), tile.tile_points(xyz, 256, 1.0, 5, method, vertical_scale=1.0)
    assert np.array_equal(first.point_index, second.point_index)
    assert np.array_equal(first.owner, second.owner)


def test_run_tiles_only_the_non_ground_points() -> None:
    points = _street_points(4000, seed=4)
    ground = np.zeros(4000, dtype=bool)
    ground[::3] = True
    points[ground, :3] = 1000.0  # far away: a patch reaching a ground point would show it
    frame = tile.run(_frame(points, ground), tile.Options(vertical_scale=1.0))
    objects = points[~ground, :3]
    tiling = frame.tiling
    assert tiling is not None and tiling.owner.shape == (len(objects),)
    assert tiling.point_index.max() < len(objects)
    restored = tiling.normalized * tiling.scale[:, None, None] + tiling.centroid[:, None, :]
    assert np.abs(restored).max() < 500  # no ground point in any patch
    assert frame.points is points and frame.notes == ()


def test_run_without_ground_mask_tiles_every_point_and_says_so() -> None:
    frame = tile.run(_frame(_street_points(1000, seed=5)))
    assert frame.tiling is not None and frame.tiling.owner.shape == (1000,)
    assert frame.notes == ("tile: no ground labels (stages.ground has not run): every point tiled as an object",)


@pytest.mark.parametrize("object_points", [0, 1, 255])
def test_too_few_object_points_give_no_tiling_and_a_note(object_points: int) -> None:
    points = _street_points(600, seed=6)
    ground = np.ones(600, dtype=bool)
    ground[:object_points] = False
    frame = tile.run(_frame(points, ground), tile.Options(vertical_scale=1.0))
    assert frame.tiling is None
    said = "1 object point," if object_points == 1 else f"{object_points} object points,"
    assert len(frame.notes) == 1 and said in frame.notes[0]


def test_exactly_one_patch_worth_of_points() -> None:
    frame = tile.run(_frame(_street_points(256, seed=7)))
    assert frame.tiling is not None and frame.tiling.num_patches >= 1
    assert np.array_equal(np.sort(frame.tiling.point_index[0]), np.arange(256))


def test_tile_points_names_the_stage_in_every_refusal() -> None:
    points = np.random.default_rng(0).uniform(-10, 10, size=(600, 4))
    with pytest.raises(ValueError, match=r"tile: xyz must be an \(M, 3\) array .* got shape \(600, 4\)"):
        tile.tile_points(points)
    points[3, 2] = np.nan
    with pytest.raises(ValueError, match="tile: xyz holds 1 point with NaN"):
        tile.tile_points(points[:, :3])
    with pytest.raises(ValueError, match="tile: need at least 256 points, got 100"):
        tile.tile_points(np.zeros((100, 3)))
    with pytest.raises(ValueError, match=r"tile: overlap must be in \[1, 8\], got 0.5"):
        tile.tile_points(np.random.default_rng(1).uniform(-10, 10, size=(600, 3)), overlap=0.5)
    with pytest.raises(ValueError, match=r"tile: overlap must be in \[1, 8\], got 9"):  # accepted, as Options refuses it
        tile.tile_points(np.random.default_rng(1).uniform(-10, 10, size=(600, 3)), overlap=9)
    good = np.random.default_rng(1).uniform(-10, 10, size=(600, 3))
    with pytest.raises(ValueError, match="tile: patch_size must be a whole number of at least 16, got 0"):
        tile.tile_points(good, patch_size=0)  # it read "overlap must be in [1, 0]"
    with pytest.raises(ValueError, match="tile: vertical_scale must be > 0 and at most 1000, got inf"):
        tile.tile_points(good, vertical_scale=float("inf"))  # it blamed the data
    with pytest.raises(ValueError, match=r"tile: a coordinate of 1e\+301 m, beyond 1e\+07 m"):
        tile.tile_points(good / 10.0 * 1e301)  # an IndexError deep in cadpu.patches
    for odd in (good > 0, good.astype(str)):  # tiled as 0/1 and parsed numbers, without a word
        with pytest.raises(ValueError, match=f"tile: xyz must hold real numbers .* got an array of {odd.dtype}"):
            tile.tile_points(odd)


def test_coordinates_no_sensor_gives_are_an_input_error_naming_the_scan() -> None:
    # a bare ValueError that named no file, which the chain takes for a bug of its own (a review)
    from stages import ground, load
    from stages.errors import InputError

    rng = np.random.default_rng(0)
    points = np.column_stack([rng.normal(size=(900, 3)) * [8, 8, 1], rng.uniform(size=900)]).astype(np.float32)
    points[:, 0] += 2e7
    frame = ground.run(load.frame_from_points(points, source="/data/000004.bin", max_range=1e9))
    with pytest.raises(InputError, match=r"\[tile\] /data/000004.bin: a coordinate of 2e\+07 m"):
        tile.run(frame)


def test_a_negative_seed_is_refused_as_a_setting_not_blamed_on_the_scan() -> None:
    from pydantic import ValidationError

    # accepted, then every frame failed with "InputError [tile] ...: expected non-negative integer"
    with pytest.raises(ValidationError, match="greater than or equal to 0"):
        tile.Options(method="fps", seed=-1)
    points = np.random.default_rng(0).normal(size=(600, 3))
    with pytest.raises(ValueError, match="tile: seed must be a whole number of at least 0, got -1"):
        tile.tile_points(points, method="fps", seed=-1)
