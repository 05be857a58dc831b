"""Compiled loops of the scan geometry (range image, ring tables, ring snapping), with Numba.

Each function here computes exactly what the numpy expression it replaced computed (same cells,
same rows, same values chosen; no floating-point arithmetic is reordered), only without the
sorts and (rings x points) temporaries: together they took about two thirds of the
stitch + snap + fill time of a KITTI frame (docs/results.md, "Speed of the output cloud stages").
The trigonometry stays in numpy, in the callers, so the floating-point results do not change.

- `ranges_and_sines`: range and elevation sine of each point (was `np.linalg.norm` and three temporaries).
- `nearest_in_cells`: per range-image cell, the nearest return (was a lexsort by cell and range).
- `fill_round`: per row, each empty cell takes the value of the nearest filled one, round the
  circle (was a searchsorted per row).
- `in_elevation_order`: a ring table's cells ordered by elevation within each azimuth column
  (was a stable argsort of every column).
- `rings_above`, `gaps_of`: how many rows of a point's azimuth column of a ring table lie above
  it (was an (R, Q) comparison; a binary search in columns whose elevations fall monotonically),
  and the ring gap that makes.
- `range_checks`, `beside_fits`: the range check of `stages.ring_snap`, point by point (was a
  dozen (Q,) temporaries).
- `spread_in_cells`: the spreading of `stages.ring_snap` over the virtual rings of a ring gap
  (was a float argsort of all points).
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
def _by_column(table: np.ndarray) -> tuple:  # pragma: no cover - compiled
    """(W, R) copy of an (R, W) table, column by column, and (W,) whether each column's values
    never rise from row to row (and hold no NaN)."""
    rows, width = table.shape
    by_column = np.ascontiguousarray(table.T)
    falling = np.ones(width, np.bool_)
    for c in range(width):
        for r in range(rows):
            if not (by_column[c, r] == by_column[c, r]):  # NaN
                falling[c] = False
                break
            if r > 0 and not (by_column[c, r - 1] >= by_column[c, r]):
                falling[c] = False
                break
    return by_column, falling


@njit(cache=True, nogil=True)
def in_elevation_order(elevation: np.ndarray, ranges: np.ndarray) -> tuple:  # pragma: no cover - compiled
    """(R, W) float64 copies of the (R, W) `elevation` and `ranges` tables with the cells of each
    column reordered by elevation, highest first: the permutation
    `np.argsort(-elevation, axis=0, kind="stable")` applied to both (equal elevations keep their
    row order, NaN goes last). A column already in that order is copied as it is."""
    rows, width = elevation.shape
    values, far = elevation.copy(), ranges.copy()
    falling = np.ones(width, np.bool_)  # row by row, so that memory is read in order
    for r in range(rows):
        for c in range(width):
            if not (values[r, c] == values[r, c]) or (r > 0 and not (values[r - 1, c] >= values[r, c])):
                falling[c] = False  # a NaN, or a rise
    for c in range(width):
        if falling[c]:
            continue
        for i in range(1, rows):  # insertion sort, stable: a column holds a few dozen rings
            e, d = values[i, c], far[i, c]
            j = i - 1
            # e goes before values[j] when it is higher, or values[j] is NaN and e is not
            while j >= 0 and (e > values[j, c] or (values[j, c] != values[j, c] and e == e)):
                values[j + 1, c], far[j + 1, c] = values[j, c], far[j, c]
                j -= 1
            values[j + 1, c], far[j + 1, c] = e, d
    return values, far


@njit(cache=True, nogil=True)
def _count_above(values: np.ndarray, falling: bool, e: float) -> int:  # pragma: no cover - compiled
    """How many of `values` are > e (NaN never is): a binary search when they never rise."""
    rows = len(values)
    if falling:
        low, high = 0, rows  # values[:low] > e, values[high:] <= e
        while low < high:
            middle = (low + high) // 2
            if values[middle] > e:
                low = middle + 1
            else:
                high = middle
        return low
    count = 0
    for r in range(rows):
        count += values[r] > e
    return count


@njit(cache=True, nogil=True)
def rings_above(table: np.ndarray, column: np.ndarray, elevation: np.ndarray) -> np.ndarray:  # pragma: no cover
    """(Q,) int64: for each point, how many rows r of the (R, W) `table` hold
    table[r, column[q]] > elevation[q] (NaN cells never do).

    In a column whose values never rise from row to row (no NaN), those rows are a prefix and a
    binary search finds its end; any other column is counted row by row."""
    by_column, falling = _by_column(table)
    above = np.empty(len(column), np.int64)
    for q in range(len(column)):
        above[q] = _count_above(by_column[column[q]], falling[column[q]], elevation[q])
    return above


@njit(cache=True, nogil=True)
def gaps_of(table: np.ndarray, azimuth: np.ndarray, elevation: np.ndarray,
            distance: np.ndarray) -> tuple:  # pragma: no cover - compiled
    """Where (Q,) points at `azimuth`, `elevation` (radians) and `distance` (metres) lie among the
    rings of an (R, W) top-first elevation `table`: their azimuth column (int64, bin c covers
    [-pi + c 2pi/W, -pi + (c+1) 2pi/W)), gap k (between rows k - 1 and k, int64, clipped to
    1 .. R - 1; k = `rings_above`), between (inside the rings and off the origin), the elevation
    of the ring above (top), top minus that of the ring below (span), and the position in the gap,
    (top - elevation) / span (0 where span is not positive)."""
    rows, columns = table.shape
    by_column, falling = _by_column(table)
    count = len(azimuth)
    column = np.empty(count, np.int64)
    gap = np.empty(count, np.int64)
    between = np.empty(count, np.bool_)
    top = np.empty(count, np.float64)
    span = np.empty(count, np.float64)
    position = np.empty(count, np.float64)
    for q in range(count):
        c = np.int64(np.floor((azimuth[q] + np.pi) / (2 * np.pi) * columns))
        if c < 0 or c >= columns:
            c %= columns
        column[q] = c
        values = by_column[c]
        above = _count_above(values, falling[c], elevation[q])
        between[q] = above > 0 and above < rows and distance[q] > 0
        k = min(max(above, 1), rows - 1)
        gap[q] = k
        top[q] = values[k - 1]
        span[q] = top[q] - values[k]
        position[q] = (top[q] - elevation[q]) / span[q] if span[q] > 0 else 0.0
    return column, gap, between, top, span, position


@njit(cache=True, nogil=True)
def range_checks(ranges: np.ndarray, column: np.ndarray, gap: np.ndarray, between: np.ndarray, span: np.ndarray,
                 distance: np.ndarray, tolerance: float, slope: float, floor: float) -> tuple:  # pragma: no cover
    """`ring_snap._range_fits` point by point: (Q,) whether each range fits the two real returns of
    its gap ((R, W) `ranges`, NaN where none), and (Q,) whether those lie on one surface (their
    difference within nearer * |span| * slope + floor, `range_image.surface_gap_limit`)."""
    count = len(column)
    fits = np.empty(count, np.bool_)
    one_surface = np.empty(count, np.bool_)
    for q in range(count):
        upper, lower = ranges[gap[q] - 1, column[q]], ranges[gap[q], column[q]]
        nearer, farther = np.fmin(upper, lower), np.fmax(upper, lower)
        one = farther - nearer <= nearer * abs(span[q]) * slope + floor
        one_surface[q] = one
        d = distance[q]
        if one:
            inside = d >= nearer - tolerance and d <= farther + tolerance
        else:
            inside = abs(d - upper) <= tolerance or abs(d - lower) <= tolerance
        known = np.isfinite(upper) and np.isfinite(lower)
        fits[q] = between[q] and known and inside
    return fits, one_surface


@njit(cache=True, nogil=True)
def beside_fits(ranges: np.ndarray, column: np.ndarray, gap: np.ndarray, distance: np.ndarray,
                position: np.ndarray, fits: np.ndarray, one_surface: np.ndarray, tolerance: float,
                slack: float, across_within: float) -> np.ndarray:  # pragma: no cover - compiled
    """`ring_snap._fits` point by point: (Q,) `fits` and, across a depth edge, at a range up to
    `across_within` (metres; -inf: never) near the return of the half of the gap the point lies in
    (`position` up to 1/2 + slack: the upper half; from 1/2 - slack: the lower half)."""
    kept = np.empty(len(column), np.bool_)
    for q in range(len(column)):
        if not fits[q]:
            kept[q] = False
        elif one_surface[q]:
            kept[q] = True
        elif not distance[q] <= across_within:
            kept[q] = False
        else:
            upper, lower = ranges[gap[q] - 1, column[q]], ranges[gap[q], column[q]]
            d = distance[q]
            kept[q] = ((abs(d - upper) <= tolerance and position[q] <= 0.5 + slack)
                       or (abs(d - lower) <= tolerance and position[q] >= 0.5 - slack))
    return kept


@njit(cache=True, nogil=True)
def spread_in_cells(chosen: np.ndarray, column: np.ndarray, gap: np.ndarray, position: np.ndarray,
                    step: np.ndarray, rings: int, gaps: int, cells: int) -> np.ndarray:  # pragma: no cover
    """`ring_snap._spread_steps`: (Q,) copy of `step` where, in every (column, gap) cell (cell id
    column * gaps + gap, below `cells`) holding at least `rings` of the `chosen` points ((P,)
    ascending indices), rank i of m (by position clipped to [0, 1], ties by index) takes ring
    1 + floor((i + 1/2) rings / m)."""
    cell = np.empty(len(chosen), np.int64)
    for k in range(len(chosen)):
        cell[k] = column[chosen[k]] * gaps + gap[chosen[k]]
    counts = np.zeros(cells + 1, np.int64)
    for c in cell:
        counts[c + 1] += 1
    for c in range(cells):
        counts[c + 1] += counts[c]
    placed = counts[:-1].copy()
    order = np.empty(len(chosen), np.int64)  # into chosen: by cell, stable
    for k in range(len(chosen)):
        order[placed[cell[k]]] = k
        placed[cell[k]] += 1
    key = np.empty(len(chosen), np.float64)  # the order within a cell
    for k in range(len(chosen)):
        key[k] = min(max(position[chosen[k]], 0.0), 1.0)
    spread = step.copy()
    for c in range(cells):
        start, end = counts[c], counts[c + 1]
        members = end - start
        if members == 0:
            continue
        for i in range(start + 1, end):  # insertion sort by key, stable (cells hold a few points)
            k = order[i]
            j = i - 1
            while j >= start and key[order[j]] > key[k]:
                order[j + 1] = order[j]
                j -= 1
            order[j + 1] = k
        if members < rings:
            continue
        for i in range(members):
            spread[chosen[order[start + i]]] = 1 + np.floor((i + 0.5) * rings / members)
    return spread


@njit(cache=True, nogil=True)
def placed_rows(xyz: np.ndarray, between: np.ndarray, distance: np.ndarray, top: np.ndarray, span: np.ndarray,
                step: np.ndarray, ratio: int) -> np.ndarray:  # pragma: no cover - compiled
    """(Q, 3) float32: the rows of (Q, 3) float32 `xyz` where not `between`, else the point at
    that distance and azimuth on virtual ring `step` of its gap, at elevation
    e = top - span * step / ratio (x = cos e d cos a, y = cos e d sin a, z = sin e d).

    The azimuth's cosine and sine are the point's own x / rho and y / rho (rho = hypot(x, y)), not
    the trigonometry of atan2(y, x): the same values up to rounding, without two trigonometric
    calls per point (docs/results.md, "Snap: the azimuth from x and y")."""
    out = np.empty((len(xyz), 3), np.float32)
    for q in range(len(xyz)):
        if between[q]:
            x, y = np.float64(xyz[q, 0]), np.float64(xyz[q, 1])
            elevation = top[q] - span[q] * step[q] / ratio
            horizontal = np.cos(elevation) * distance[q]
            rho = np.sqrt(x * x + y * y)
            cos_azimuth, sin_azimuth = (x / rho, y / rho) if rho > 0 else (1.0, 0.0)
            out[q, 0] = horizontal * cos_azimuth
            out[q, 1] = horizontal * sin_azimuth
            out[q, 2] = np.sin(elevation) * distance[q]
        else:
            out[q, 0], out[q, 1], out[q, 2] = xyz[q, 0], xyz[q, 1], xyz[q, 2]
    return out


@njit(cache=True, nogil=True)
def ranges_and_sines(xyz: np.ndarray) -> tuple:  # pragma: no cover - compiled
    """(Q,) float64 distance sqrt(x^2 + y^2 + z^2) of (Q, 3) float64 points (summed in that order,
    as `np.linalg.norm(xyz, axis=1)`), and (Q,) z / max(distance, 1e-12) clipped to [-1, 1] (the
    sine of the elevation)."""
    count = len(xyz)
    distance = np.empty(count, np.float64)
    sine = np.empty(count, np.float64)
    for q in range(count):
        x, y, z = xyz[q, 0], xyz[q, 1], xyz[q, 2]
        d = np.sqrt(x * x + y * y + z * z)
        distance[q] = d
        sine[q] = min(max(z / max(d, 1e-12), -1.0), 1.0)
    return distance, sine
