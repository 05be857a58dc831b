"""stages.ring_snap: generated points move onto the virtual rings between a scan's real rings,
keep their azimuth and range, and points outside the rings are flagged; scans whose point order
shows no rings are recognised."""

from __future__ import annotations

import numpy as np
import pytest

from stages import ring_snap

#: Elevations of the synthetic scan's rings, degrees, top ring first (stored first, as in KITTI).
RING_ELEVATIONS = np.array([2.0, 0.4, -1.2, -2.8, -4.4, -6.0])
RATIO = 4


def _ring_scan(elevations_deg: np.ndarray = RING_ELEVATIONS, per_ring: int = 720, distance: float = 10.0,
               seed: int = 0) -> np.ndarray:
    """(R * per_ring, 4) scan in KITTI order: ring by ring from the top, within a ring azimuth from
    just above 0 counter-clockwise round to just below 0, every return `distance` metres away."""
    rng = np.random.default_rng(seed)
    rings = []
    for elevation in np.radians(elevations_deg):
        azimuth = np.sort(rng.uniform(0.001, 2 * np.pi - 0.001, per_ring))
        azimuth = np.angle(np.exp(1j * azimuth))  # (-pi, pi]: 0+ .. pi, then -pi .. 0-
        horizontal = distance * np.cos(elevation)
        rings.append(np.column_stack([horizontal * np.cos(azimuth), horizontal * np.sin(azimuth),
                                      np.full(per_ring, distance * np.sin(elevation)), np.zeros(per_ring)]))
    return np.concatenate(rings).astype(np.float32)


def _spherical(xyz: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    xyz = np.asarray(xyz, dtype=np.float64)
    distance = np.linalg.norm(xyz, axis=1)
    return distance, np.arctan2(xyz[:, 1], xyz[:, 0]), np.degrees(np.arcsin(xyz[:, 2] / distance))


def _points_at(elevation_deg: np.ndarray, seed: int = 1) -> np.ndarray:
    rng = np.random.default_rng(seed)
    azimuth = rng.uniform(-np.pi, np.pi, len(elevation_deg))
    distance = rng.uniform(3.0, 40.0, len(elevation_deg))
    elevation = np.radians(elevation_deg)
    return np.column_stack([distance * np.cos(elevation) * np.cos(azimuth),
                            distance * np.cos(elevation) * np.sin(azimuth), distance * np.sin(elevation)])


def test_scan_rings_reads_the_rings_of_a_ring_ordered_scan() -> None:
    rings = ring_snap.scan_rings(_ring_scan())
    assert rings is not None
    assert np.array_equal(np.bincount(rings), np.full(len(RING_ELEVATIONS), 720))


def test_scan_rings_refuses_a_transposed_scan() -> None:
    # a (4, N) scan read as 4 points of N columns: None, as for a scan without rings (a library
    # user's trial), where ground.segment says "transposed?"
    with pytest.raises(ValueError, match=r"scan_rings: points must be an \(N, 3\+\) array, one row per point, got "
                                         r"shape \(4, \d+\): transposed\? \(give points.T\)"):
        ring_snap.scan_rings(_ring_scan().T)


@pytest.mark.parametrize("reorder", ["shuffle", "azimuth", "azimuth from -180", "reversed"])
def test_scan_rings_refuses_an_order_without_rings(reorder: str) -> None:
    scan = _ring_scan()
    azimuth = np.arctan2(scan[:, 1], scan[:, 0])
    if reorder == "shuffle":
        scan = scan[np.random.default_rng(0).permutation(len(scan))]
    elif reorder == "azimuth":  # one sweep round the sensor: a single "ring"
        scan = scan[np.argsort(azimuth % (2 * np.pi), kind="stable")]
    elif reorder == "azimuth from -180":  # the sweep from behind the sensor reads as 2 "rings"
        scan = scan[np.argsort(azimuth, kind="stable")]
    else:  # backwards, bottom ring first; with three 25-degree gaps a ring (where nothing returns),
        # as a real scan has, the backward sweep reads as a dozen odd "rings"
        degrees = np.degrees(azimuth)
        gaps = ((degrees > 10) & (degrees < 35)) | ((degrees > 100) & (degrees < 125)) | ((degrees > -120) & (degrees < -95))
        scan = scan[~gaps][::-1]
    assert ring_snap.scan_rings(scan) is None


def test_elevation_table_holds_each_rings_elevation_in_every_column() -> None:
    scan = _ring_scan(per_ring=300)  # fewer returns than columns: most columns are filled from neighbours
    table = ring_snap.ring_elevation_table(scan, ring_snap.scan_rings(scan), columns=2000)
    assert table.shape == (len(RING_ELEVATIONS), 2000)
    assert np.allclose(np.degrees(table), RING_ELEVATIONS[:, None], atol=1e-4)


def test_points_between_rings_move_to_the_nearest_virtual_ring_keeping_azimuth_and_range() -> None:
    scan = _ring_scan()
    table = ring_snap.ring_elevation_table(scan, ring_snap.scan_rings(scan))
    elevation = np.random.default_rng(2).uniform(RING_ELEVATIONS[-1] + 1e-3, RING_ELEVATIONS[0] - 1e-3, 2000)
    points = _points_at(elevation)
    snapped, inside = ring_snap.snap_to_virtual_rings(points, table, RATIO)
    assert inside.all()
    before, after = _spherical(points), _spherical(snapped)
    assert np.allclose(after[0], before[0], rtol=1e-5)  # range kept
    assert np.allclose(np.angle(np.exp(1j * (after[1] - before[1]))), 0.0, atol=1e-5)  # azimuth kept
    virtual = (RING_ELEVATIONS[:-1, None] + np.diff(RING_ELEVATIONS)[:, None] * np.arange(1, RATIO) / RATIO).ravel()
    nearest_virtual = np.abs(after[2][:, None] - virtual[None]).min(axis=1)
    assert nearest_virtual.max() < 1e-3  # degrees: on a virtual ring
    # and on the virtual ring of its own gap nearest to where it was
    gap = np.searchsorted(-RING_ELEVATIONS, -elevation) - 1
    step = np.clip(np.round((RING_ELEVATIONS[gap] - elevation) / 1.6 * RATIO), 1, RATIO - 1)
    assert np.allclose(after[2], RING_ELEVATIONS[gap] - 1.6 * step / RATIO, atol=1e-3)


def test_points_outside_the_rings_are_flagged_and_left_unmoved() -> None:
    scan = _ring_scan()
    table = ring_snap.ring_elevation_table(scan, ring_snap.scan_rings(scan))
    points = _points_at(np.array([5.0, 2.5, -6.5, -20.0, 1.0]))
    snapped, inside = ring_snap.snap_to_virtual_rings(points, table, RATIO)
    assert inside.tolist() == [False, False, False, False, True]
    assert np.allclose(snapped[:4], points[:4], atol=1e-5)


def test_ratio_two_puts_points_on_the_middle_ring() -> None:
    scan = _ring_scan()
    table = ring_snap.ring_elevation_table(scan, ring_snap.scan_rings(scan))
    snapped, inside = ring_snap.snap_to_virtual_rings(_points_at(np.array([1.9, 0.3, -5.9])), table, 2)
    assert inside.all()
    assert np.allclose(_spherical(snapped)[2], [1.2, -0.4, -5.2], atol=1e-4)


def test_bad_arguments_are_refused() -> None:
    scan = _ring_scan()
    table = ring_snap.ring_elevation_table(scan, ring_snap.scan_rings(scan))
    with pytest.raises(ValueError, match="ratio"):
        ring_snap.snap_to_virtual_rings(np.zeros((1, 3)), table, 1)
    with pytest.raises(ValueError, match="at least 2 rings"):
        ring_snap.snap_to_virtual_rings(np.zeros((1, 3)), table[:1], 4)


def _point(elevation_deg: float, azimuth: float, distance: float) -> np.ndarray:
    """(3,) point at this elevation (degrees), azimuth (radians) and range (metres)."""
    elevation = np.radians(elevation_deg)
    return distance * np.array([np.cos(elevation) * np.cos(azimuth), np.cos(elevation) * np.sin(azimuth),
                                np.sin(elevation)])


def _tables(scan: np.ndarray) -> ring_snap.RingTables:
    return ring_snap.ring_tables(scan, ring_snap.scan_rings(scan))


def test_range_table_holds_each_rings_range() -> None:
    tables = _tables(_ring_scan(distance=12.0))
    assert tables.range.shape == tables.elevation.shape
    finite = np.isfinite(tables.range)
    assert finite.mean() > 0.95 and np.allclose(tables.range[finite], 12.0, atol=1e-4)


def test_on_one_surface_a_point_fits_only_between_the_two_ranges() -> None:
    tables = _tables(_ring_scan(distance=10.0))
    points = np.stack([_point(1.2, 0.3, 10.03), _point(1.2, 0.3, 9.96), _point(1.2, 0.3, 10.2),
                       _point(1.2, 0.3, 9.5)])
    assert ring_snap.fits_ring_ranges(points, tables, 0.05).tolist() == [True, True, False, False]


def test_across_a_depth_edge_a_point_fits_only_near_one_of_the_two_surfaces() -> None:
    tables = _tables(_wall_and_background())
    between = -2.0  # between ring 2 (-1.2 degrees) and ring 3 (-2.8)
    points = np.stack([_point(between, 1.0, 10.02), _point(between, 1.0, 19.97), _point(between, 1.0, 15.0),
                       _point(between, 1.0, 10.5)])
    assert ring_snap.fits_ring_ranges(points, tables, 0.05).tolist() == [True, True, False, False]


def test_no_fit_where_a_ring_has_no_return_or_outside_the_rings() -> None:
    scan = _ring_scan(distance=10.0)
    rings = ring_snap.scan_rings(scan)
    azimuth = np.arctan2(scan[:, 1], scan[:, 0])
    scan = scan[~((rings == 1) & (azimuth > 0.0) & (azimuth < 0.5))]  # a window in ring 1
    tables = _tables(scan)
    points = np.stack([_point(1.2, 0.25, 10.0), _point(1.2, 2.0, 10.0), _point(3.0, 2.0, 10.0),
                       _point(-7.0, 2.0, 10.0)])
    assert ring_snap.fits_ring_ranges(points, tables, 0.05).tolist() == [False, True, False, False]


def test_a_negative_range_tolerance_is_refused() -> None:
    with pytest.raises(ValueError, match="tolerance"):
        ring_snap.fits_ring_ranges(np.zeros((1, 3)), _tables(_ring_scan()), -0.1)


def _wall_and_background() -> np.ndarray:
    """Rings 0-2 hit a wall 10 m away, rings 3-5 the background 20 m away."""
    return np.concatenate([_ring_scan(RING_ELEVATIONS[:3], distance=10.0),
                           _ring_scan(RING_ELEVATIONS[3:], distance=20.0, seed=1)])


def test_across_a_depth_edge_a_point_fits_only_in_the_half_of_the_gap_beside_its_surface() -> None:
    tables = _tables(_wall_and_background())
    upper, lower = -1.6, -2.4  # a quarter and three quarters of the way from ring 2 (-1.2) to ring 3 (-2.8)
    points = np.stack([_point(upper, 1.0, 10.0), _point(lower, 1.0, 10.0), _point(upper, 1.0, 20.0),
                       _point(lower, 1.0, 20.0)])
    assert ring_snap.fits_ring_ranges(points, tables, 0.05).tolist() == [True, False, False, True]


def test_without_the_half_gap_rule_nothing_across_a_depth_edge_fits() -> None:
    tables = _tables(_wall_and_background())
    upper, lower = -1.6, -2.4
    across = np.stack([_point(upper, 1.0, 10.0), _point(lower, 1.0, 20.0)])  # kept by the half-gap rule
    assert ring_snap.fits_ring_ranges(across, tables, 0.05).tolist() == [True, True]
    assert ring_snap.fits_ring_ranges(across, tables, 0.05, across_edges=False).tolist() == [False, False]
    on_wall = np.stack([_point(0.0, 1.0, 10.0)])  # between rings 1 and 2, both on the wall
    assert ring_snap.fits_ring_ranges(on_wall, tables, 0.05, across_edges=False).tolist() == [True]
    snapped, keep = ring_snap.snap_and_check(np.concatenate([across, on_wall]), tables, RATIO, 0.05, across_edges=False)
    assert keep.tolist() == [False, False, True]


def test_the_half_gap_rule_keeps_points_across_a_depth_edge_only_within_its_range_limit() -> None:
    tables = _tables(_wall_and_background())
    upper, lower = -1.6, -2.4
    across = np.stack([_point(upper, 1.0, 10.0), _point(lower, 1.0, 20.0)])  # the wall's and the background's
    on_wall = np.stack([_point(0.0, 1.0, 10.0)])  # one surface: the limit does not apply
    points = np.concatenate([across, on_wall])
    assert ring_snap.fits_ring_ranges(points, tables, 0.05, across_within=15.0).tolist() == [True, False, True]
    assert ring_snap.fits_ring_ranges(points, tables, 0.05, across_within=25.0).tolist() == [True, True, True]
    assert ring_snap.fits_ring_ranges(points, tables, 0.05, across_edges=False, across_within=25.0).tolist() == \
        [False, False, True]
    _, keep = ring_snap.snap_and_check(points, tables, RATIO, 0.05, across_within=15.0)
    assert keep.tolist() == [True, False, True]
    for bad in (0.0, -1.0, float("nan")):  # would drop every point across an edge, as "drop" does
        with pytest.raises(ValueError, match="across_within must be > 0 metres"):
            ring_snap.fits_ring_ranges(points, tables, 0.05, across_within=bad)


def test_snap_and_check_spreads_a_bunched_gap_over_its_virtual_rings() -> None:
    tables = _tables(_ring_scan(distance=10.0))  # one surface everywhere
    azimuth = 0.5  # one column; between ring 1 (0.4 degrees) and ring 2 (-1.2)
    bunched = np.stack([_point(e, azimuth, 10.0) for e in (0.05, 0.0, -0.05)])  # all nearest to ring j = 1 (0.0)
    snapped, keep = ring_snap.snap_and_check(bunched, tables, RATIO, 0.05)
    assert keep.all()
    assert np.allclose(_spherical(snapped)[2], [0.0, -0.4, -0.8], atol=1e-4)  # rings 1, 2, 3 in elevation order
    # fewer points than virtual rings: each goes to its nearest
    snapped, _ = ring_snap.snap_and_check(bunched[:2], tables, RATIO, 0.05)
    assert np.allclose(_spherical(snapped)[2], [0.0, 0.0], atol=1e-4)
    # across a depth edge the points are not spread (each surface keeps its own half)
    edge = _tables(_wall_and_background())
    near_wall = np.stack([_point(e, azimuth, 10.0) for e in (-1.3, -1.35, -1.4)])
    snapped, keep = ring_snap.snap_and_check(near_wall, edge, RATIO, 0.05)
    assert keep.all() and np.allclose(_spherical(snapped)[2], -1.6, atol=1e-4)


def test_snap_and_check_keeps_what_fits_after_snapping_on_virtual_rings() -> None:
    tables = _tables(_wall_and_background())
    rng = np.random.default_rng(3)
    count = 4000  # enough that many column gaps hold 3 or more points and are spread
    points = np.stack([_point(e, a, d) for e, a, d in zip(rng.uniform(-7.0, 3.0, count),
                                                          rng.uniform(-0.3, 0.3, count),
                                                          rng.choice([10.01, 15.0, 19.98, 25.0], count))])
    snapped, keep = ring_snap.snap_and_check(points, tables, RATIO, 0.05)
    nearest, inside = ring_snap.snap_to_virtual_rings(points, tables.elevation, RATIO)
    assert np.array_equal(keep, inside & ring_snap.fits_ring_ranges(snapped, tables, 0.05))
    assert 0 < keep.sum() < inside.sum()
    again, _ = ring_snap.snap_to_virtual_rings(snapped[keep], tables.elevation, RATIO)
    assert np.abs(again - snapped[keep]).max() < 1e-4  # kept points lie on virtual rings
    moved = np.abs(snapped[keep] - nearest[keep]).max(axis=1) > 1e-4
    assert 0 < moved.sum() < keep.sum()  # some were spread to another ring, most kept their nearest
    assert np.array_equal(snapped[~inside], points[~inside].astype(np.float32))


def _crossing_scan(crossed: float = -0.7, window: tuple[float, float] = (0.8, 1.2)) -> np.ndarray:
    """`_ring_scan` (every return 10 m away) whose ring 3 (-2.8 degrees) returns at `crossed`
    degrees in the azimuth window (radians): there it lies above ring 2 (-1.2), seen from the
    origin, as a near return of a lower laser can lie above a far one of the laser above."""
    scan = _ring_scan(distance=10.0)
    rings = ring_snap.scan_rings(scan)
    azimuth = np.arctan2(scan[:, 1], scan[:, 0])
    moved = (rings == 3) & (azimuth > window[0]) & (azimuth < window[1])
    elevation = np.radians(crossed)
    scan[moved, 0] = 10.0 * np.cos(elevation) * np.cos(azimuth[moved])
    scan[moved, 1] = 10.0 * np.cos(elevation) * np.sin(azimuth[moved])
    scan[moved, 2] = 10.0 * np.sin(elevation)
    return scan


def test_where_two_rings_cross_the_gaps_follow_the_elevations_and_snapping_is_idempotent() -> None:
    scan = _crossing_scan()
    tables = _tables(scan)
    rng = np.random.default_rng(4)
    count = 3000
    azimuth = rng.uniform(0.85, 1.15, count)  # inside the window, where ring 3 lies above ring 2
    elevation = rng.uniform(-5.9, 1.9, count)
    points = np.stack([_point(e, a, 10.0) for e, a in zip(elevation, azimuth)])
    column = np.floor((azimuth + np.pi) / (2 * np.pi) * tables.elevation.shape[1]).astype(np.int64)
    assert (np.diff(tables.elevation[:, column], axis=0) > 0).any(axis=0).all()  # the rings cross there
    # the gaps between the returns in elevation order, and their virtual rings
    column_rings = np.array([2.0, 0.4, -0.7, -1.2, -4.4, -6.0])
    virtual = (column_rings[:-1, None] + np.diff(column_rings)[:, None] * np.arange(1, RATIO) / RATIO).ravel()
    snapped, inside = ring_snap.snap_to_virtual_rings(points, tables.elevation, RATIO)
    assert inside.all()
    after = _spherical(snapped)[2]
    # each point on the virtual ring nearest to it in its own gap of the ordered column
    gap = np.searchsorted(-column_rings, -elevation) - 1
    top, span = column_rings[gap], column_rings[gap] - column_rings[gap + 1]
    step = np.clip(np.round((top - elevation) / span * RATIO), 1, RATIO - 1)
    assert np.allclose(after, top - span * step / RATIO, atol=1e-3)
    assert np.abs(after[:, None] - virtual[None]).min(axis=1).max() < 1e-3
    again, _ = ring_snap.snap_to_virtual_rings(snapped, tables.elevation, RATIO)
    assert np.abs(again - snapped).max() < 1e-4  # snapping a snapped point moves nothing
    # the same with the range check and spreading, which compare with the returns around the point
    checked, keep = ring_snap.snap_and_check(points, tables, RATIO, 0.05)
    assert keep.all()  # one surface, 10 m away everywhere
    assert ring_snap.fits_ring_ranges(checked, tables, 0.05).all()
    again, keep_again = ring_snap.snap_and_check(checked, tables, RATIO, 0.05)
    assert keep_again.all() and np.abs(again - checked).max() < 1e-4


def test_in_column_order_orders_crossing_columns_and_leaves_the_others_as_they_are() -> None:
    tables = _tables(_crossing_scan())
    ordered = ring_snap.in_column_order(tables)
    crossing = (np.diff(tables.elevation, axis=0) > 0).any(axis=0)
    assert 0 < crossing.sum() < len(crossing) // 10
    assert (np.diff(ordered.elevation, axis=0) <= 0).all()
    assert np.array_equal(ordered.elevation[:, ~crossing], tables.elevation[:, ~crossing])
    assert np.array_equal(ordered.range[:, ~crossing], tables.range[:, ~crossing], equal_nan=True)
    # in the crossing columns rings 2 and 3 swap, each keeping its own range
    assert np.array_equal(ordered.elevation[:, crossing], tables.elevation[[0, 1, 3, 2, 4, 5]][:, crossing])
    assert np.array_equal(ordered.range[:, crossing], tables.range[[0, 1, 3, 2, 4, 5]][:, crossing], equal_nan=True)


def _cropped_ring_scan(per_ring: int, degrees: float) -> np.ndarray:
    """A ring scan of `per_ring` returns a ring spread evenly over the front `degrees` only (a
    field-of-view crop, as KITTI's velodyne_reduced), each ring in KITTI's order: counter-clockwise
    from just above 0 to degrees / 2, then from -degrees / 2 to just below 0."""
    azimuth = np.radians(np.linspace(-degrees / 2, degrees / 2, per_ring, endpoint=False) + 0.01)
    azimuth = np.concatenate([azimuth[azimuth > 0], azimuth[azimuth <= 0]])
    rings = []
    for elevation in np.radians(RING_ELEVATIONS):
        horizontal = 10.0 * np.cos(elevation)
        rings.append(np.column_stack([horizontal * np.cos(azimuth), horizontal * np.sin(azimuth),
                                      np.full(per_ring, 10.0 * np.sin(elevation)), np.zeros(per_ring)]))
    return np.concatenate(rings).astype(np.float32)


def test_a_range_is_borrowed_over_two_azimuth_steps_of_a_cropped_scan_not_of_the_circle() -> None:
    # the reach was 2 x (columns / returns a ring), right only for a ring round the whole circle: on a
    # scan cropped to 90 degrees it bridged gaps four times as wide (a review)
    scan = _cropped_ring_scan(per_ring=250, degrees=90.0)  # 2 of the 2,000 columns between returns
    azimuth = np.degrees(np.arctan2(scan[:, 1], scan[:, 0]))
    gap = (azimuth > 19.0) & (azimuth < 23.0)  # 11 returns a ring gone: 24 columns without a return
    holed = scan[~gap]
    assert np.array_equal(np.bincount(ring_snap.scan_rings(holed)), np.full(len(RING_ELEVATIONS), 239))
    tables = ring_snap.ring_tables(holed, ring_snap.scan_rings(holed))
    columns = tables.range.shape[1]
    middle = int((np.radians(21.0) + np.pi) / (2 * np.pi) * columns)  # about 11 columns from a return
    assert np.isnan(tables.range[:, middle]).all()  # reach 5 columns (17 before): not bridged
    whole = ring_snap.ring_tables(scan, ring_snap.scan_rings(scan))
    assert np.isfinite(whole.range[:, middle]).all()  # at most 2 columns from one: borrowed


def test_tables_of_a_scan_without_points_are_empty() -> None:
    # the median of no ring's returns made the reach NaN, and the int of it raised (a review)
    tables = ring_snap.ring_tables(np.zeros((0, 4), np.float32), np.zeros(0, np.int64))
    assert tables.range.shape[0] == tables.elevation.shape[0] == 0


def test_points_of_two_columns_are_refused_not_read_past() -> None:
    scan = _ring_scan()
    tables = ring_snap.ring_tables(scan, ring_snap.scan_rings(scan))
    flat = np.array([[10.0, 0.0], [0.0, 10.0], [5.0, 5.0]])
    # the compiled kernels read the next row's x as z, and past the array for the last (a new-user trial)
    with pytest.raises(ValueError, match=r"points must be \(Q, 3\) x, y, z, got shape \(3, 2\)"):
        ring_snap.snap_to_virtual_rings(flat, tables.elevation, 4)
    with pytest.raises(ValueError, match=r"points must be \(Q, 3\)"):
        ring_snap.fits_ring_ranges(flat, tables, 0.05)


def test_a_gap_beside_a_ring_without_an_elevation_leaves_its_points_outside_not_at_nan() -> None:
    # a ring whose every return lay at the origin has a NaN row; a point below the last real ring
    # was taken to lie in the gap next to it and moved to NaN, which the writer then refused
    from stages.ring_snap import snap_to_virtual_rings

    point = np.array([[10.0, 0.0, 10 * np.sin(-0.05)]])
    table = np.array([[0.1] * 8, [0.0] * 8, [np.nan] * 8])
    snapped, between = snap_to_virtual_rings(point, table, 4)
    assert np.isfinite(snapped).all() and not between[0]
    np.testing.assert_allclose(snapped, point, rtol=0, atol=1e-6)


def test_why_no_rings_are_found_names_too_few_rings_apart_from_another_order(street_scan) -> None:
    # two rings in KITTI's order were told their order was "sorted, shuffled or stored in reverse"
    # and pointed at the unordered-scans preset (a library user's trial)
    two = street_scan.points[np.isin(street_scan.ring, [10, 40])]
    assert ring_snap.scan_rings(two) is None
    assert ring_snap.no_rings_reason(two) == ("the point order shows 2 laser rings, fewer than the 4 that ring "
                                             "snapping needs")
    shuffled = street_scan.points[np.random.default_rng(0).permutation(len(street_scan.points))]
    assert "no laser rings in KITTI's order" in ring_snap.no_rings_reason(shuffled)
    assert "-c unordered_scans" in ring_snap.no_rings_reason(shuffled)


@pytest.mark.parametrize("points", [np.ones(300), np.ones((300, 2)), np.array([["a", "b", "c"]] * 300)])
def test_scan_rings_refuses_what_is_not_an_array_of_points_by_name(points) -> None:
    # a single row failed inside numpy's indexing (a library user's trial)
    with pytest.raises(ValueError, match=r"scan_rings: points must be an \(N, 3\+\) array of numbers"):
        ring_snap.scan_rings(points)


def test_scan_rings_reads_a_list_as_its_array(street_scan) -> None:
    rings = ring_snap.scan_rings(street_scan.points.tolist())  # a TypeError before
    assert rings is not None and np.array_equal(rings, ring_snap.scan_rings(street_scan.points))
