"""The compiled scan-geometry loops give what their plain numpy definitions give (exactly, but for
placed_rows, whose azimuth comes from x and y instead of trigonometry)."""

from __future__ import annotations

import numpy as np
import pytest

from stages.range_image import group_medians, ring_rows
from stages.ring_kernels import (fill_round, in_elevation_order, nearest_in_cells, placed_rows, ranges_and_sines,
                                 rings_above)


def _nearest_by_sort(cell: np.ndarray, distance: np.ndarray, usable: np.ndarray, cells: int) -> np.ndarray:
    order = np.lexsort((distance[usable], cell))
    first = np.concatenate([[True], cell[order][1:] != cell[order][:-1]])
    index = np.full(cells, -1, dtype=np.int64)
    index[cell[order][first]] = usable[order][first]
    return index


def test_nearest_in_cells_keeps_the_nearest_and_the_first_of_equal_ones() -> None:
    rng = np.random.default_rng(0)
    n, cells = 5000, 700
    distance = np.round(rng.uniform(0, 5, n), 1)  # many exact ties
    usable = np.flatnonzero(distance > 0)
    cell = rng.integers(0, cells, len(usable))
    got = nearest_in_cells(cell, distance, usable, cells)
    assert np.array_equal(got, _nearest_by_sort(cell, distance, usable, cells))
    assert (got == -1).any()  # some cells stay empty


def test_group_medians_match_numpy_median_and_leave_empty_groups_nan() -> None:
    rng = np.random.default_rng(1)
    group = rng.integers(0, 40, 3001)
    group[group == 7] = 8  # group 7 empty
    values = rng.normal(size=len(group))
    got = group_medians(group, values, 41)
    expected = np.array([np.median(values[group == g]) if (group == g).any() else np.nan for g in range(41)])
    assert np.array_equal(got, expected, equal_nan=True)
    assert np.isnan(got[7]) and np.isnan(got[40])


def _fill_round_by_search(row: np.ndarray, reach: int | None) -> np.ndarray:
    known = np.flatnonzero(np.isfinite(row))
    if len(known) == 0 or len(known) == len(row):
        return row
    cells = np.arange(len(row))
    after = np.searchsorted(known, cells) % len(known)
    next_cell, previous_cell = known[after], known[after - 1]
    to_previous = (cells - previous_cell) % len(row)
    to_next = (next_cell - cells) % len(row)
    filled = np.where(to_previous <= to_next, row[previous_cell], row[next_cell])
    if reach is not None:
        filled[np.minimum(to_previous, to_next) > reach] = np.nan
    return filled


@pytest.mark.parametrize("reach", [None, 0, 1, 3])
def test_fill_round_takes_the_nearest_filled_cell_round_the_circle(reach: int | None) -> None:
    rng = np.random.default_rng(2)
    table = rng.normal(size=(9, 50))
    table[rng.uniform(size=table.shape) < 0.6] = np.nan
    table[3] = np.nan  # a row with no value
    table[4, :] = 1.0  # a full row
    table[5] = np.nan
    table[5, 10] = 2.5  # a single value
    table[6] = np.nan
    table[6, [0, 49]] = [1.0, 2.0]  # values at both ends (the wrap)
    got = fill_round(table, -1 if reach is None else reach)
    expected = np.stack([_fill_round_by_search(row, reach) for row in table])
    assert np.array_equal(got, expected, equal_nan=True)


def test_rings_above_counts_higher_rows_in_falling_and_other_columns() -> None:
    rng = np.random.default_rng(3)
    rows, width = 12, 30
    table = np.sort(rng.normal(size=(rows, width)), axis=0)[::-1].copy()  # falling columns
    table[:, 5] = rng.normal(size=rows)  # a column out of order
    table[4, 6] = np.nan  # a column with a hole
    table[3:6, 7] = table[3, 7]  # equal neighbours still fall
    column = rng.integers(0, width, 4000)
    elevation = rng.normal(size=len(column))
    elevation[:width] = table[rows // 2, np.arange(width)]  # exactly on a row
    column[:width] = np.arange(width)
    got = rings_above(table, column, elevation)
    assert np.array_equal(got, (table[:, column] > elevation).sum(axis=0))


@pytest.mark.parametrize("rings", [np.array([0, 0, 1, 3, 3, 3, 7]), np.array([5, -2, 5, 9]),
                                   np.array([70_000, 3, 3]), np.zeros(0, np.int64)])
def test_ring_rows_match_unique(rings: np.ndarray) -> None:
    ids, rows = ring_rows(rings)
    expected_ids, expected_rows = np.unique(rings, return_inverse=True)
    assert np.array_equal(ids, expected_ids) and np.array_equal(rows, expected_rows)
    assert rows.dtype == np.int64


def test_ranges_and_sines_match_numpy_bit_for_bit() -> None:
    rng = np.random.default_rng(4)
    xyz = rng.normal(scale=20.0, size=(5000, 3))
    xyz[0] = 0.0  # the origin: sine 0
    distance, sine = ranges_and_sines(xyz)
    assert np.array_equal(distance, np.linalg.norm(xyz, axis=1))
    assert np.array_equal(sine, np.clip(xyz[:, 2] / np.maximum(np.linalg.norm(xyz, axis=1), 1e-12), -1.0, 1.0))


def test_in_elevation_order_is_a_stable_sort_of_each_column_by_falling_elevation() -> None:
    rng = np.random.default_rng(5)
    rows, width = 16, 40
    elevation = np.sort(rng.normal(size=(rows, width)), axis=0)[::-1].copy()  # falling columns
    elevation[:, 5] = rng.normal(size=rows)  # a column out of order
    elevation[[4, 5], 6] = elevation[[5, 4], 6]  # two neighbours crossed
    elevation[3, 7] = np.nan  # a column with a hole
    elevation[[2, 9], 8] = np.nan
    elevation[:, 9] = np.round(rng.normal(size=rows))  # ties out of order
    elevation[3:6, 10] = elevation[3, 10]  # equal neighbours in order
    elevation[:, 11] = np.nan
    ranges = rng.uniform(1.0, 50.0, size=(rows, width))
    ranges[rng.uniform(size=ranges.shape) < 0.1] = np.nan
    ranges = np.asfortranarray(ranges)  # a layout whose transpose is contiguous: still copied
    before = ranges.copy()
    got_elevation, got_ranges = in_elevation_order(elevation, ranges)
    order = np.argsort(-elevation, axis=0, kind="stable")
    assert np.array_equal(got_elevation, np.take_along_axis(elevation, order, 0), equal_nan=True)
    assert np.array_equal(got_ranges, np.take_along_axis(ranges, order, 0), equal_nan=True)
    assert np.array_equal(ranges, before, equal_nan=True)  # the input is not changed


def test_placed_rows_puts_points_on_their_ring_at_their_azimuth_and_range() -> None:
    rng = np.random.default_rng(3)
    q = 20_000
    xyz = rng.uniform(-60, 60, (q, 3)).astype(np.float32)
    xyz[0, :2] = 0.0  # on the vertical axis: no azimuth of its own
    distance = np.linalg.norm(xyz.astype(np.float64), axis=1)
    top = rng.uniform(-0.3, 0.05, q)
    span = rng.uniform(0.001, 0.01, q)
    step = rng.integers(1, 4, q).astype(np.float64)
    between = rng.random(q) < 0.9
    between[0] = True
    got = placed_rows(xyz, between, distance, top, span, step, 4)
    elevation = top - span * step / 4
    azimuth = np.arctan2(xyz[:, 1].astype(np.float64), xyz[:, 0])
    expected = np.stack([np.cos(elevation) * distance * np.cos(azimuth), np.cos(elevation) * distance * np.sin(azimuth),
                         np.sin(elevation) * distance], axis=1).astype(np.float32)
    assert np.array_equal(got[~between], xyz[~between])
    # the azimuth from x / rho and y / rho: the trigonometric form's point to float32 rounding
    deviation = np.abs(got - expected).max(axis=1) / distance
    assert deviation[between].max() <= 1e-6
    assert np.allclose(np.linalg.norm(got[between].astype(np.float64), axis=1), distance[between], rtol=1e-6)
