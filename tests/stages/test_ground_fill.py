"""stages.ground_fill: points between neighbouring ground returns lie on the line joining them, on
the virtual rings, and nothing bridges a kerb, a non-ground return or a missing return."""

from __future__ import annotations

import numpy as np
import pytest

from stages.range_image import DEFAULT_COLUMNS, build_range_image
from stages.ground_fill import fill_ground

RATIO = 4
SENSOR_HEIGHT = 1.73
#: Ring elevations, degrees, top ring first: all of them see the ground (flat at -SENSOR_HEIGHT).
RING_ELEVATIONS = np.array([-8.0, -9.5, -11.0, -12.5, -14.0])
#: One return per azimuth column, at the column centres of the first COLUMNS_USED columns.
COLUMNS_USED = 300


def _ground_scan(heights: tuple[float, ...] | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(R * COLUMNS_USED, 4) scan of flat ground ring by ring (reflectance = ring id / 10), and its
    ring ids; `heights` gives each ring's ground height instead of -SENSOR_HEIGHT."""
    heights = heights or (-SENSOR_HEIGHT,) * len(RING_ELEVATIONS)
    azimuth = -np.pi + (np.arange(COLUMNS_USED) + 0.5) * 2 * np.pi / DEFAULT_COLUMNS
    scan, rings = [], []
    for ring, (elevation, height) in enumerate(zip(np.radians(RING_ELEVATIONS), heights)):
        planar = height / np.tan(elevation)  # where the ray meets the plane z = height
        scan.append(np.column_stack([planar * np.cos(azimuth), planar * np.sin(azimuth),
                                     np.full(COLUMNS_USED, height), np.full(COLUMNS_USED, ring / 10)]))
        rings.append(np.full(COLUMNS_USED, ring))
    return np.concatenate(scan).astype(np.float32), np.concatenate(rings)


def _fill(points: np.ndarray, rings: np.ndarray, ground: np.ndarray | None = None, **kwargs: float):
    ground = np.ones(len(points), dtype=bool) if ground is None else ground
    return fill_ground(points, ground, build_range_image(points, rings), RATIO, **kwargs)


def test_flat_ground_is_filled_on_the_ground_at_the_virtual_ring_elevations() -> None:
    points, rings = _ground_scan()
    filled = _fill(points, rings)
    pairs = (len(RING_ELEVATIONS) - 1) * COLUMNS_USED
    assert len(filled) == pairs * (RATIO - 1)
    np.testing.assert_allclose(filled.xyz[:, 2], -SENSOR_HEIGHT, atol=1e-5)  # on the plane, not off it
    planar = np.hypot(filled.xyz[:, 0], filled.xyz[:, 1]).astype(np.float64)
    elevation = np.degrees(np.arctan2(filled.xyz[:, 2], planar))
    step = np.diff(RING_ELEVATIONS)[0]
    virtual = RING_ELEVATIONS[:-1, None] + step * np.arange(1, RATIO)[None, :] / RATIO
    expected = np.repeat(virtual, COLUMNS_USED, axis=0).reshape(-1)  # pairs in (ring, column) order
    np.testing.assert_allclose(elevation, expected, atol=1e-3)
    # each point's azimuth is its pair's column, its parent the upper return, its reflectance between the two
    upper_ring = rings[filled.parent]
    assert np.array_equal(upper_ring, np.repeat(np.arange(len(RING_ELEVATIONS) - 1), COLUMNS_USED * (RATIO - 1)))
    np.testing.assert_allclose(np.arctan2(filled.xyz[:, 1], filled.xyz[:, 0]),
                               np.arctan2(points[filled.parent, 1], points[filled.parent, 0]), atol=1e-5)
    assert np.all((filled.reflectance > upper_ring / 10) & (filled.reflectance < (upper_ring + 1) / 10))


def test_a_kerb_between_two_rings_is_not_bridged() -> None:
    heights = (-SENSOR_HEIGHT + 0.15,) + (-SENSOR_HEIGHT,) * (len(RING_ELEVATIONS) - 1)  # top ring on the pavement
    points, rings = _ground_scan(heights)
    filled = _fill(points, rings)
    assert len(filled) == (len(RING_ELEVATIONS) - 2) * COLUMNS_USED * (RATIO - 1)
    assert not np.any(rings[filled.parent] == 0)
    # a gentler slope setting refuses nothing more on the flat part; a steep one bridges the kerb
    assert len(_fill(points, rings, max_slope_deg=1.0)) == len(filled)
    assert len(_fill(points, rings, max_slope_deg=89.0)) == (len(RING_ELEVATIONS) - 1) * COLUMNS_USED * (RATIO - 1)


def test_only_pairs_of_ground_returns_with_both_returns_present_are_joined() -> None:
    points, rings = _ground_scan()
    ground = np.ones(len(points), dtype=bool)
    object_columns = np.flatnonzero(rings == 2)[:100]  # ring 2, first 100 columns: not ground
    ground[object_columns] = False
    present = np.ones(len(points), dtype=bool)
    present[np.flatnonzero(rings == 4)[-50:]] = False  # ring 4, last 50 columns: no return
    filled = _fill(points[present], rings[present], ground[present])
    # ring 2's object columns lose both their pairs (with ring 1 and with ring 3), ring 4's gaps one each
    assert len(filled) == ((len(RING_ELEVATIONS) - 1) * COLUMNS_USED - 2 * 100 - 50) * (RATIO - 1)


def test_factor_one_fills_nothing() -> None:
    points, rings = _ground_scan()
    filled = fill_ground(points, np.ones(len(points), dtype=bool), build_range_image(points, rings), 1)
    assert len(filled) == 0 and filled.xyz.shape == (0, 3)


@pytest.mark.parametrize("kwargs, message", [
    ({"ground": np.ones(3, dtype=bool)}, "ground must be"),
    ({"ratio": 0}, "ratio must be"),
    ({"ratio": 2.5}, "ratio must be a whole number"),  # xyz and parents of different lengths before
    ({"max_slope_deg": 90.0}, "max_slope_deg"),
])
def test_bad_arguments_are_refused(kwargs: dict, message: str) -> None:
    points, rings = _ground_scan()
    arguments = {"ground": np.ones(len(points), dtype=bool), "ratio": RATIO, **kwargs}
    with pytest.raises(ValueError, match=message):
        fill_ground(points, image=build_range_image(points, rings), **arguments)


def test_points_or_an_image_of_another_scan_are_refused_by_name() -> None:
    points, rings = _ground_scan()
    image = build_range_image(points, rings)
    ground = np.ones(len(points), dtype=bool)
    with pytest.raises(ValueError, match=r"fill_ground: points must be \(N, 4\)"):
        fill_ground(points[:, :3], ground, image, RATIO)  # an IndexError inside before
    with pytest.raises(ValueError, match=rf"range image is of a scan of {len(points)} points, not of these 100"):
        fill_ground(points[:100], ground[:100], image, RATIO)
    with pytest.raises(ValueError, match=r"range image: points must be \(N, 3\) x, y, z, got shape"):
        build_range_image(points[:, :2].copy(), rings)  # accepted before
    with pytest.raises(ValueError, match=rf"range image: {len(points)} points but rings has shape"):
        build_range_image(points, rings[:-1])  # an IndexError inside before


def test_what_scan_rings_returns_for_no_rings_and_non_finite_points_are_refused_by_name() -> None:
    # the README's own flow passes scan_rings' None on: "rings has shape ()" and an AttributeError
    # before; a NaN reflectance was copied into the fill points (a library user's trial)
    points, rings = _ground_scan()
    ground = np.ones(len(points), dtype=bool)
    with pytest.raises(ValueError, match=r"range image: rings is None: the scan's point order shows no laser rings"):
        build_range_image(points, None)
    with pytest.raises(ValueError, match=r"fill_ground: image must be the scan's RangeImage .*got NoneType"):
        fill_ground(points, ground, None, RATIO)
    damaged = points.copy()
    damaged[5, 3] = np.nan
    with pytest.raises(ValueError, match=r"fill_ground: points hold 1 point with NaN or infinite values"):
        fill_ground(damaged, ground, build_range_image(points, rings), RATIO)


def test_each_point_takes_the_azimuth_between_its_two_returns() -> None:
    points, rings = _ground_scan()
    # each ring's returns a tenth of a column further round than the ring above, as a real scan's are
    column = 2 * np.pi / DEFAULT_COLUMNS
    azimuth = np.arctan2(points[:, 1], points[:, 0]) + rings * 0.1 * column
    planar = np.hypot(points[:, 0], points[:, 1])
    points[:, 0], points[:, 1] = planar * np.cos(azimuth), planar * np.sin(azimuth)
    filled = _fill(points, rings)
    upper = filled.parent
    lower = upper + COLUMNS_USED  # the same column of the ring below
    point_planar = np.hypot(filled.xyz[:, 0], filled.xyz[:, 1]).astype(np.float64)
    along = (point_planar - planar[upper]) / (planar[lower] - planar[upper])  # u: 0 at the upper return
    assert np.all((along > 0) & (along < 1))
    expected = azimuth[upper] + (azimuth[lower] - azimuth[upper]) * along
    np.testing.assert_allclose(np.arctan2(filled.xyz[:, 1], filled.xyz[:, 0]), expected, atol=2e-6)
