"""Compiled loops of the scan geometry (range image, ring tables, ring snapping), with Numba.

Each function here computes exactly what the numpy expression it replaced computed (same cells,
same rows, same values chosen; no floating-point arithmetic is reordered), only without the
sorts and (rings x points) temporaries: together they took about two thirds of the
stitch + snap + fill time of a KITTI frame (docs/results.md, "Speed of the output cloud stages").
The trigonometry stays in numpy, in the callers, so the floating-point results do not change.

- `nearest_in_cells`: per range-image cell, the nearest return (was a lexsort by cell and range).
- `group_medians`: the median of each group of values (was a lexsort by group and value).
- `fill_round`: per row, each empty cell takes the value of the nearest filled one, round the
  circle (was a searchsorted per row).
- `rings_above`: how many rows of a point's azimuth column of a ring table lie above it (was an
  (R, Q) comparison); a binary search in columns whose elevations fall monotonically.
"""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True, nogil=True)
def nearest_in_cells(cell: np.ndarray, distance: np.ndarray, usable: np.ndarray,
                     cells: int) -> np.ndarray:  # pragma: no cover - compiled
    """(cells,) int64: for each cell, the entry of `usable` (point indices, ascending) whose point
    lies in it (`cell`, (len(usable),) int64 cell of each usable point) with the smallest
    `distance` ((N,) float64, by point index); the first such point on ties; -1 for an empty cell."""
    index = np.full(cells, -1, np.int64)
    for k in range(len(usable)):
        point = usable[k]
        c = cell[k]
        held = index[c]
        if held < 0 or distance[point] < distance[held]:
            index[c] = point
    return index


@njit(cache=True, nogil=True)
def group_medians(group: np.ndarray, values: np.ndarray, groups: int) -> np.ndarray:  # pragma: no cover
    """(groups,) float64 median of the (P,) `values` in each group id of `group` (P,) int64 in
    [0, groups): the mean of the two middle values in sorted order (the middle one for an odd
    count); NaN for an empty group."""
    counts = np.zeros(groups, np.int64)
    for g in group:
        counts[g] += 1
    starts = np.zeros(groups + 1, np.int64)
    for g in range(groups):
        starts[g + 1] = starts[g] + counts[g]
    placed = starts[:-1].copy()
    by_group = np.empty(len(values), np.float64)
    for k in range(len(values)):
        g = group[k]
        by_group[placed[g]] = values[k]
        placed[g] += 1
    medians = np.full(groups, np.nan)
    for g in range(groups):
        count = counts[g]
        if count == 0:
            continue
        part = np.sort(by_group[starts[g]:starts[g + 1]])
        medians[g] = 0.5 * (part[(count - 1) // 2] + part[count // 2])
    return medians


@njit(cache=True, nogil=True)
def fill_round(table: np.ndarray, reach: int) -> np.ndarray:  # pragma: no cover - compiled
    """(R, W) float64 copy of `table` whose NaN cells take, row by row, the value of the nearest
    finite cell round the circle (the previous one on ties); cells more than `reach` cells from
    every finite one stay NaN (reach < 0: no limit). A row with no finite cell stays NaN."""
    rows, width = table.shape
    out = table.copy()
    previous = np.empty(width, np.int64)  # distance back to the nearest finite cell (itself: 0)
    following = np.empty(width, np.int64)
    for r in range(rows):
        row = table[r]
        last = -1
        for c in range(width):
            if np.isfinite(row[c]):
                last = c
        if last < 0:
            continue
        for c in range(width):  # the previous finite cell, circularly, starting from the row's last one
            if np.isfinite(row[c]):
                last = c
            previous[c] = (c - last) % width
        first = -1
        for c in range(width):
            if np.isfinite(row[c]):
                first = c
                break
        nxt = first + width  # the next finite cell after the row's end, unrolled
        for c in range(width - 1, -1, -1):
            if np.isfinite(row[c]):
                nxt = c
            following[c] = nxt - c
        for c in range(width):
            back, ahead = previous[c], following[c]
            if back == 0:
                continue
            if reach >= 0 and min(back, ahead) > reach:
                out[r, c] = np.nan
            elif back <= ahead:
                out[r, c] = row[(c - back) % width]
            else:
                out[r, c] = row[(c + ahead) % width]
    return out


@njit(cache=True, nogil=True)
def rings_above(table: np.ndarray, column: np.ndarray, elevation: np.ndarray) -> np.ndarray:  # pragma: no cover
    """(Q,) int64: for each point, how many rows r of the (R, W) `table` hold
    table[r, column[q]] > elevation[q] (NaN cells never do).

    In a column whose values never rise from row to row (no NaN), those rows are a prefix and a
    binary search finds its end; any other column is counted row by row."""
    rows, width = table.shape
    falling = np.ones(width, np.bool_)
    for c in range(width):
        for r in range(rows):
            if not (table[r, c] == table[r, c]):  # NaN
                falling[c] = False
                break
            if r > 0 and not (table[r - 1, c] >= table[r, c]):
                falling[c] = False
                break
    by_column = np.ascontiguousarray(table.T)
    above = np.empty(len(column), np.int64)
    for q in range(len(column)):
        values = by_column[column[q]]
        e = elevation[q]
        if falling[column[q]]:
            low, high = 0, rows  # values[:low] > e, values[high:] <= e
            while low < high:
                middle = (low + high) // 2
                if values[middle] > e:
                    low = middle + 1
                else:
                    high = middle
            above[q] = low
        else:
            count = 0
            for r in range(rows):
                if values[r] > e:
                    count += 1
            above[q] = count
    return above
