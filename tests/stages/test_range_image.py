"""Tests of the range-image linear interpolation baseline (stages.range_image)."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import pytest

from cadpu.synthetic.lidar import hdl64e_elevations
from stages.rings import recover_rings
from stages.range_image import build_range_image, interpolate_rings, surface_gap_limit

COLUMNS = 2000
#: Rings 0, 4, 8, ... of the HDL-64E: a 16-beam input.
ELEVATIONS = np.radians(hdl64e_elevations()[::4])


def _directions(azimuth_deg: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Unit directions (R*A, 3), ring id and azimuth of rays on every ring at the given azimuths,
    ring by ring, azimuth increasing from 0 and wrapping through 180 (KITTI order)."""
    azimuth = np.radians(np.sort(np.mod(azimuth_deg, 360.0)))
    azimuth = np.where(azimuth > np.pi, azimuth - 2 * np.pi, azimuth)
    el, az = np.meshgrid(ELEVATIONS, azimuth, indexing="ij")
    directions = np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)], axis=-1).reshape(-1, 3)
    ring = np.repeat(np.arange(len(ELEVATIONS)), len(azimuth))
    return directions, ring, az.reshape(-1)


def _scan(azimuth_deg: np.ndarray, distance: Callable[[np.ndarray], np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """A noise-free 16-ring scan: points (N, 4) at `distance(directions)` along each ray (NaN =
    no return), reflectance 0.5, and their rings."""
    directions, ring, _ = _directions(azimuth_deg)
    r = distance(directions)
    hit = np.isfinite(r)
    points = np.column_stack([directions[hit] * r[hit, None], np.full(int(hit.sum()), 0.5)]).astype(np.float32)
    return points, ring[hit]


def _bin_centres(first_deg: float, last_deg: float) -> np.ndarray:
    """Azimuths (degrees) at the centres of the range image's columns within [first, last]."""
    centres = -180.0 + (np.arange(COLUMNS) + 0.5) * 360.0 / COLUMNS
    return centres[(centres >= first_deg) & (centres <= last_deg)]


def _wall(x: float) -> Callable[[np.ndarray], np.ndarray]:
    """Range along each direction to the vertical plane at x (NaN for rays that miss it)."""
    def distance(directions: np.ndarray) -> np.ndarray:
        with np.errstate(divide="ignore"):
            r = x / directions[:, 0]
        return np.where(r > 0, r, np.nan)
    return distance


def test_inserted_points_of_a_flat_wall_lie_on_the_wall_and_the_count_is_exact() -> None:
    azimuths = _bin_centres(-40.0, 40.0)
    points, rings = _scan(azimuths, _wall(10.0))
    out = interpolate_rings(points, rings, ratio=4, columns=COLUMNS)
    assert np.array_equal(out[: len(points)], points)  # the input is kept, unchanged, first
    inserted = out[len(points):]
    assert len(inserted) == (len(ELEVATIONS) - 1) * len(azimuths) * 3
    assert np.abs(inserted[:, 0] - 10.0).max() < 0.01  # on the plane x = 10
    assert np.allclose(inserted[:, 3], 0.5)  # reflectance interpolated
    # new elevations lie strictly between the neighbouring rings, three per gap
    elevation = np.arcsin(inserted[:, 2] / np.linalg.norm(inserted[:, :3], axis=1))
    assert elevation.max() < ELEVATIONS[0] and elevation.min() > ELEVATIONS[-1]
    assert len(np.unique(np.round(np.degrees(elevation), 3))) == (len(ELEVATIONS) - 1) * 3


def test_a_wall_across_the_seam_behind_the_sensor_is_interpolated_on_the_wall() -> None:
    azimuths = np.concatenate([_bin_centres(150.0, 180.0), _bin_centres(-180.0, -150.0)])
    points, rings = _scan(azimuths, _wall(-12.0))
    inserted = interpolate_rings(points, rings, columns=COLUMNS)[len(points):]
    assert len(inserted) == (len(ELEVATIONS) - 1) * len(azimuths) * 3
    assert np.abs(inserted[:, 0] + 12.0).max() < 0.01


def test_nothing_is_inserted_across_a_depth_edge() -> None:
    edge = np.radians(-8.0)  # rays above hit a wall 20 m ahead, rays below an object 5 m ahead

    def distance(directions: np.ndarray) -> np.ndarray:
        far, near = _wall(20.0)(directions), _wall(5.0)(directions)
        return np.where(directions[:, 2] > np.sin(edge), far, near)

    azimuths = _bin_centres(-30.0, 30.0)
    points, rings = _scan(azimuths, distance)
    inserted = interpolate_rings(points, rings, columns=COLUMNS)[len(points):]
    x = inserted[:, 0]
    assert np.all((np.abs(x - 5.0) < 0.01) | (np.abs(x - 20.0) < 0.02))  # no point in the empty space
    crossing = 1  # one ring gap straddles the edge and gets nothing
    assert len(inserted) == (len(ELEVATIONS) - 1 - crossing) * len(azimuths) * 3


def test_a_column_with_a_single_return_gets_nothing() -> None:
    azimuths = _bin_centres(-10.0, 10.0)
    points, rings = _scan(azimuths, _wall(8.0))
    lonely = np.flatnonzero(rings == 5)[:3]  # drop three returns of ring 5
    keep = np.setdiff1d(np.arange(len(points)), lonely)
    out = interpolate_rings(points[keep], rings[keep], columns=COLUMNS)
    full = interpolate_rings(points, rings, columns=COLUMNS)
    assert len(full) - len(out) == 3 + 3 * 2 * 3  # the points, and the two gaps around each


def test_ring_ids_only_matter_by_their_order() -> None:
    points, rings = _scan(_bin_centres(-20.0, 20.0), _wall(15.0))
    a = interpolate_rings(points, rings, columns=COLUMNS)
    b = interpolate_rings(points, rings * 4 + 100, columns=COLUMNS)
    assert np.array_equal(a, b)
    # and the rings recovered from the KITTI point order are the ones the scan was built with
    assert np.array_equal(recover_rings(points), rings)


def test_range_image_keeps_the_nearest_return_of_a_cell() -> None:
    points = np.array([[10.0, 0.0, 0.0, 0.1], [5.0, 0.0, 0.0, 0.2], [0.0, 7.0, 0.0, 0.3]], dtype=np.float32)
    image = build_range_image(points, np.zeros(3, dtype=np.int64), columns=8)
    assert image.index.shape == (1, 8)
    assert sorted(image.index[image.index >= 0].tolist()) == [1, 2]
    assert image.elevation[0] == pytest.approx(0.0)


def test_factor_one_and_empty_scans_return_the_input() -> None:
    points, rings = _scan(_bin_centres(-5.0, 5.0), _wall(9.0))
    assert np.array_equal(interpolate_rings(points, rings, ratio=1), points)
    empty = interpolate_rings(np.zeros((0, 4), np.float32), np.zeros(0, np.int64))
    assert empty.shape == (0, 4)


def test_gap_limit_grows_with_range_and_ring_spacing() -> None:
    step = np.radians(2.0)
    assert surface_gap_limit(np.array(10.0), step, 75.0, 0.1) == pytest.approx(10 * step * np.tan(np.radians(75)) + 0.1)
    assert surface_gap_limit(np.array(20.0), step) > surface_gap_limit(np.array(10.0), step)
    with pytest.raises(ValueError, match="max_incidence_deg"):
        surface_gap_limit(np.array(1.0), step, 90.0)


@pytest.mark.parametrize("points, rings, message", [
    (np.zeros((5, 3)), np.zeros(5, np.int64), "shape"),
    (np.zeros((5, 4)), np.zeros(4, np.int64), "rings"),
    (np.zeros((5, 4)), np.zeros(5), "integers"),
    (np.full((5, 4), np.nan), np.zeros(5, np.int64), "NaN"),
])
def test_bad_input_is_refused_with_a_clear_message(points: np.ndarray, rings: np.ndarray, message: str) -> None:
    with pytest.raises(ValueError, match=message):
        interpolate_rings(points, rings)


@pytest.mark.parametrize("ratio", [0, 2.5, True])
def test_bad_factor_is_refused(ratio: object) -> None:
    # 2.5 inserted points at 0.4 and 0.8 of each gap (a review)
    with pytest.raises(ValueError, match=f"interpolate_rings: ratio must be a whole number >= 1, got {ratio!r}"):
        interpolate_rings(np.ones((3, 4)), np.zeros(3, np.int64), ratio=ratio)


def test_row_elevation_is_each_rings_median_with_odd_even_and_missing_rings() -> None:
    rng = np.random.default_rng(3)
    elevation_deg = {0: [2.0, 1.0, 3.5], 1: [-1.0, -2.0, -1.5, -4.0], 3: [-8.0]}  # ring 2 has no point
    rings = np.concatenate([np.full(len(v), k) for k, v in elevation_deg.items()])
    el = np.radians(np.concatenate(list(elevation_deg.values())))
    az = rng.uniform(-np.pi, np.pi, len(el))
    distance = rng.uniform(5.0, 30.0, len(el))
    points = np.column_stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)]) * distance[:, None]
    image = build_range_image(points, rings)
    assert list(image.ring_ids) == [0, 1, 3]
    np.testing.assert_allclose(np.degrees(image.elevation), [2.0, -1.75, -8.0], atol=1e-9)


def test_inserted_elevations_follow_each_returns_own_elevation_not_its_rings_median() -> None:
    # ring 0 seen 0.5 degree higher on the left half of the sweep (a laser off the sensor axis)
    azimuth = np.radians(_bin_centres(-90.0, 90.0))
    top = np.where(azimuth >= 0, 1.5, 1.0)
    elevation = np.radians(np.concatenate([top, np.full(len(azimuth), -1.0)]))
    around = np.concatenate([azimuth, azimuth])
    points = np.column_stack([10.0 * np.cos(elevation) * np.cos(around), 10.0 * np.cos(elevation) * np.sin(around),
                              10.0 * np.sin(elevation), np.zeros(len(around))]).astype(np.float32)
    rings = np.repeat([0, 1], len(azimuth))
    inserted = interpolate_rings(points, rings, ratio=4, columns=COLUMNS)[len(points):].astype(np.float64)
    got = np.degrees(np.arcsin(inserted[:, 2] / np.linalg.norm(inserted[:, :3], axis=1))).reshape(-1, 3)
    expected = top[:, None] + (-1.0 - top[:, None]) * np.arange(1, 4)[None, :] / 4
    np.testing.assert_allclose(got, expected, atol=1e-4)
