"""Put generated points on virtual laser rings between the scan's real rings.

A rotating LiDAR samples a surface along cones of fixed elevation, one per laser. Densifying a scan
r-fold is, for a sensor user, the scan an r-times denser laser column would have taken: its points
lie on r - 1 new cones between every two neighbouring real ones. The network does not know the
sensor (its patches are normalised), so its points scatter in elevation; this module moves each
generated point, at its own azimuth and range, to the elevation of the nearest virtual ring.

The elevation of every ring is read per azimuth column from the scan itself (the returns of that
ring in that column, or in the nearest column that has one), not from a global table: KITTI's
lasers sit off the sensor axis, so a ring's elevation seen from the origin drifts by more than a
ring spacing between near and far returns (docs/results.md, "Scan geometry").

Within a column the real rings are taken in the order of their elevations there, not of their
ring ids (`in_column_order`). Seen from the origin, two rings can cross in a column: KITTI's lasers
fire from above the origin and the car moves during a sweep, so a near return of a lower laser can
sit above a far return of the laser above it (docs/results.md, "Rings that cross"). Taken by ring
id, the elevation intervals of neighbouring ring pairs then overlap: a point lies between several
pairs, and a virtual ring of one pair lies inside another, so snapping a snapped point can move it
again. Taken in elevation order, a column's returns cut its elevation range into gaps that do not
overlap: every point lies in exactly one, between the two returns just above and below its ray
(the returns the range check must compare it with), and the virtual rings of a gap lie inside it,
so snapping is idempotent within a column. (A snapped point is stored in float32, which can move
its azimuth by about 1e-7 rad: one that lay within that of a column's edge can fall into the next
column, whose rings lie a little higher or lower, and a second snap moves it again. A review
found such moves of up to 0.2 mm among 40,000 jittered scan points.) Where the rings do not
cross, the elevation order is the rings' own and nothing changes.

Points above the top ring or below the bottom ring of their column have no virtual ring and are
reported as outside; nothing is extrapolated past the scan's field of view (the rule of the
range-image baseline, `stages.range_image`).

`fits_ring_ranges` then checks a snapped point's range against the two real returns above and
below it in its column (between them on one surface; across a depth edge, near one of them and in
the half of the gap beside it), which removes the points a patch spanning foreground and background
puts in mid-air between the two. `snap_and_check` does both, and hands the points of a ring gap on
one surface to its virtual rings in elevation order, so that bunched copies fill every ring.

Measured effect on the 16-to-64-beam evaluation: `kitti-pu eval-kitti` with the defaults and with
`--set snap.range_tolerance=null` or `--set snap.enabled=false` (docs/quality.md, "What each
setting is worth").

Frames: sensor frame, x forward, y left, z up, metres; azimuth atan2(y, x), elevation
asin(z / range), radians.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .rings import MAX_BACKWARD_SHARE, rings_and_backward_share
from .range_image import (DEFAULT_COLUMNS, DEFAULT_MAX_INCIDENCE_DEG, DEFAULT_NOISE_FLOOR, RangeImage,
                          build_range_image, ring_rows)
from .ring_kernels import (beside_fits, fill_round, gaps_of, in_elevation_order, placed_rows, range_checks,
                           ranges_and_sines, spread_in_cells)
from .frame import looks_transposed
from .wording import counted

#: A point order showing more rings than this is not a ring-by-ring scan (lasers of the largest
#: spinning LiDARs: 128).
MAX_RINGS = 256
#: ... nor one showing fewer (a scan sorted by azimuth shows 2).
MIN_RINGS = 4
#: ... nor is one whose rings average fewer returns than this (a shuffled scan "wraps" every
#: second point).
MIN_POINTS_PER_RING = 50
#: Slack of the half-gap test across depth edges, in gap fractions: a point snapped to the middle
#: virtual ring and stored as float32 may read a little off 1/2 (virtual rings are 1/r apart).
HALF_SLACK = 1e-3
#: Where a ring has no return in a column, its range is borrowed from the nearest return up to
#: this many of the ring's own azimuth steps away (its median return spacing; KITTI: about 0.17
#: degree), so a gap in a ring (a window, the sky) is not bridged.
RANGE_FILL_STEPS = 2.0
#: tan of the steepest incidence joined by `stages.range_image.surface_gap_limit` (its default).
SURFACE_SLOPE = float(np.tan(np.radians(DEFAULT_MAX_INCIDENCE_DEG)))


def scan_rings(points: np.ndarray) -> np.ndarray | None:
    """Ring ids of a scan stored ring by ring (KITTI order), or None when its order shows no rings.

    Args:
        points: (N, 3+) scan in its stored order, sensor frame.

    Returns:
        (N,) int64 ring ids (`stages.rings.recover_rings`), or None when the order yields fewer than
        `MIN_RINGS` rings, more than `MAX_RINGS`, or fewer than `MIN_POINTS_PER_RING` points per
        ring on average, or turns backward at most steps (e.g. a shuffled, azimuth-sorted or
        reversed scan).
    """
    points = _scan_points("scan_rings", points)
    if len(points) == 0:
        return None
    rings, backward = rings_and_backward_share(points)
    count = int(rings.max()) + 1 if len(rings) else 0
    if count < MIN_RINGS or count > MAX_RINGS or len(rings) < MIN_POINTS_PER_RING * count:
        return None
    if backward > MAX_BACKWARD_SHARE:
        return None
    return rings


def _scan_points(function: str, points: np.ndarray) -> np.ndarray:
    """`points` as an (N, 3+) array, or a ValueError naming `function` (a list or one row failed
    inside numpy's indexing)."""
    array = np.asarray(points)
    if array.ndim != 2 or array.shape[1] < 3 or array.dtype.kind not in "fiu":
        raise ValueError(f"{function}: points must be an (N, 3+) array of numbers, x, y, z first, got "
                         f"{array.dtype} of shape {array.shape}")
    if looks_transposed(array.shape):  # read as a handful of points, scan_rings found no rings, silently (a trial)
        raise ValueError(f"{function}: points must be an (N, 3+) array, one row per point, got shape {array.shape}: "
                         "transposed? (give points.T)")
    return array


def no_rings_reason(points: np.ndarray) -> str:
    """Why `scan_rings` finds no rings in `points` (N, 3+), for a frame's note: too few rings in
    an order that is KITTI's (a scan of one or two lasers, a thinned scan), or an order that is
    not (sorted, shuffled or reversed), where the unordered-scans preset is the remedy."""
    points = _scan_points("no_rings_reason", points)
    if len(points) == 0:
        return "the scan has no points to read laser rings from"
    rings, backward = rings_and_backward_share(points)
    count = int(rings.max()) + 1
    if backward <= MAX_BACKWARD_SHARE and count < MIN_RINGS:
        return (f"the point order shows {counted(count, 'laser ring')}, fewer than the {MIN_RINGS} that ring "
                "snapping needs")
    return ("the point order shows no laser rings in KITTI's order (a scan sorted, shuffled or stored in reverse; "
            "for such scans: -c unordered_scans)")


@dataclass(frozen=True)
class RingTables:
    """What a scan's rings hold in every azimuth column, rings ordered top to bottom.

    Rows are rings, so in a column where two rings cross (seen from the origin) they are out of
    elevation order there; the snapping functions take each column in elevation order
    (`in_column_order`).

    Attributes:
        elevation: (R, W) float64 radians: row k is the ring with the k-th highest median
            elevation; a cell holds the elevation of that ring's nearest return in the column, or,
            where the column has none, of the ring's return in the nearest column (round the
            circle) that has one.
        range: (R, W) float64 metres: the range of that return, or of the ring's nearest return
            at most `RANGE_FILL_STEPS` of its median azimuth steps away; NaN where there is none
            (a range, unlike an elevation, is not carried across a gap in the ring).
    """

    elevation: np.ndarray
    range: np.ndarray


def ring_tables(points: np.ndarray, rings: np.ndarray, columns: int = DEFAULT_COLUMNS,
                image: RangeImage | None = None) -> RingTables:
    """Elevation and range of every ring in every azimuth column (see `RingTables`).

    Args:
        points: (N, 3+) scan, sensor frame, metres. rings: (N,) integer ring ids.
        columns: azimuth bins per revolution (bin c covers [-pi + c 2pi/W, -pi + (c+1) 2pi/W)).
        image: the scan's range image with these rings, when already built (else built here).

    Returns:
        The `RingTables`, rows top ring first.
    """
    image = image if image is not None else build_range_image(points, rings, columns)
    columns = image.index.shape[1]
    filled = image.index >= 0
    cell = np.maximum(image.index, 0)
    elevations = fill_round(np.where(filled, image.point_elevation[cell], np.nan), -1)
    reach = _range_fill_reach(filled, np.asarray(rings))
    ranges = fill_round(np.where(filled, image.range[cell], np.nan), reach)
    order = np.argsort(-image.elevation, kind="stable")  # top ring first
    return RingTables(elevation=elevations[order], range=ranges[order])


def in_column_order(tables: RingTables) -> RingTables:
    """The tables with the cells of each azimuth column in elevation order, highest first (both
    tables permuted alike; equal elevations keep their ring order, NaN last). Row k of a column is
    then the return with the k-th highest elevation there, whichever ring it belongs to; in columns
    where no rings cross the tables are unchanged (see the module docstring for why snapping
    needs this order).

    Args:
        tables: (R, W) `RingTables` of a scan, rows by ring.

    Returns:
        (R, W) float64 `RingTables`, each column ordered by elevation.
    """
    elevation, ranges = in_elevation_order(np.asarray(tables.elevation, np.float64),
                                           np.asarray(tables.range, np.float64))
    return RingTables(elevation=elevation, range=ranges)


def _ordered_elevations(table: np.ndarray) -> np.ndarray:
    """(R, W) float64 elevation table with each column in elevation order (`in_column_order`)."""
    table = np.asarray(table, np.float64)
    return in_elevation_order(table, table)[0]


def ring_elevation_table(points: np.ndarray, rings: np.ndarray, columns: int = DEFAULT_COLUMNS) -> np.ndarray:
    """(R, W) elevation of every ring in every azimuth column, radians, top ring first
    (`RingTables.elevation`; arguments as `ring_tables`)."""
    return ring_tables(points, rings, columns).elevation


def _range_fill_reach(filled: np.ndarray, rings: np.ndarray) -> int:
    """`RANGE_FILL_STEPS` of a ring's median azimuth step, in whole columns (at least 1; 0 for no
    points). filled: (R, W) bool, which cells of the range image hold a return. The step is the
    azimuth the scan spans over a ring's median number of returns. The span is the circle less
    its widest stretch of columns no ring reaches: a scan cropped to a field of view (a front 90
    degrees, as KITTI's `velodyne_reduced`) has its returns that much closer together, where
    dividing the whole circle by them had bridged gaps four times as wide."""
    if not len(rings):
        return 0
    reached = filled.any(axis=0)
    covered_columns = len(reached) - _widest_run_round(~reached)
    returns_per_ring = float(np.median(_returns_per_ring(rings)))
    return int(np.ceil(RANGE_FILL_STEPS * covered_columns / max(returns_per_ring, 1.0)))


def _widest_run_round(flags: np.ndarray) -> int:
    """The length of the longest run of True in a (W,) bool array read round a circle."""
    if flags.all():
        return len(flags)
    start = int(np.argmin(flags))  # a False: no run wraps past it once the array starts there
    edges = np.diff(np.concatenate([[0], np.roll(flags, -start).astype(np.int8), [0]]))
    runs = np.flatnonzero(edges == -1) - np.flatnonzero(edges == 1)
    return int(runs.max()) if len(runs) else 0


def _returns_per_ring(rings: np.ndarray) -> np.ndarray:
    """The number of points of each distinct ring id, as `np.unique(rings, return_counts=True)[1]`."""
    ring_ids, row = ring_rows(rings)
    return np.bincount(row, minlength=len(ring_ids))


@dataclass(frozen=True)
class _Located:
    """Where Q points lie among the rings of their azimuth column."""

    distance: np.ndarray  # (Q,) metres
    azimuth: np.ndarray  # (Q,) radians
    elevation: np.ndarray  # (Q,) radians
    column: np.ndarray  # (Q,) int64 azimuth column
    gap: np.ndarray  # (Q,) int64 k: the point lies between rows k - 1 (above) and k (below)
    between: np.ndarray  # (Q,) bool: below the top ring and above the bottom ring of its column
    top: np.ndarray  # (Q,) elevation of the ring above, radians
    span: np.ndarray  # (Q,) elevation of the ring above minus that of the ring below, radians
    position: np.ndarray  # (Q,) where in its gap: 0 on the ring above, 1 on the ring below (0 if span <= 0)


def _locate(xyz: np.ndarray, elevation_table: np.ndarray) -> _Located:
    """Column and ring gap of (Q, 3) points (sensor frame) in an (R, W) top-first elevation table.

    Raises:
        ValueError: `xyz` is not (Q, 3) (the compiled kernels would read past its rows).
    """
    xyz = np.asarray(xyz, dtype=np.float64)
    if xyz.ndim != 2 or xyz.shape[1] != 3:
        raise ValueError(f"ring snapping: points must be (Q, 3) x, y, z, got shape {xyz.shape}")
    distance, sine = ranges_and_sines(xyz)
    azimuth = np.arctan2(xyz[:, 1], xyz[:, 0])
    elevation = np.arcsin(sine)
    column, gap, between, top, span, position = gaps_of(np.asarray(elevation_table, dtype=np.float64), azimuth,
                                                        elevation, distance)
    # a gap next to a ring without an elevation in the column (a NaN row: every return of that ring
    # at the origin) has no span: its points are outside, not moved to NaN (a review)
    between = between & np.isfinite(span) & np.isfinite(position)
    return _Located(distance, azimuth, elevation, column, gap, between, top, span, position)


def _check_table(table: np.ndarray) -> None:
    if table.ndim != 2 or len(table) < 2:
        raise ValueError(f"ring snapping: need an elevation table of at least 2 rings, got shape {table.shape}")


def _check_ratio(ratio: int) -> None:
    if ratio < 2:
        raise ValueError(f"ring snapping: ratio must be >= 2, got {ratio}")


def snap_to_virtual_rings(xyz: np.ndarray, table: np.ndarray, ratio: int) -> tuple[np.ndarray, np.ndarray]:
    """Move points to the elevation of the nearest of the ratio - 1 virtual rings between the two
    real rings they lie between, keeping their azimuth and range.

    Between real rings with elevations e_top > e_bottom in the point's column, the virtual rings
    are at e_top + (e_bottom - e_top) * j / ratio, j = 1 .. ratio - 1; a point on or next to a
    real ring goes to the nearest virtual one (the real ring is already sampled by the scan). The
    two real rings are the returns just above and below the point in its column, the rings of the
    column taken in elevation order (`in_column_order`), so snapping a snapped point moves nothing
    (but at a column's edge, see the module docstring).

    Args:
        xyz: (Q, 3) points, sensor frame, metres.
        table: (R, W) ring elevations per azimuth column, top ring first (`RingTables.elevation`;
            each column is put in elevation order here).
        ratio: virtual ring gaps per real gap (the upsampling ratio r >= 2).

    Returns:
        (Q, 3) float32 snapped points, and (Q,) bool: False for points above the top ring or below
        the bottom ring of their column (returned unmoved; callers drop them).
    """
    _check_ratio(ratio)
    _check_table(table)
    at = _locate(xyz, _ordered_elevations(table))
    return _placed(xyz, at, _nearest_step(at, ratio), ratio), at.between


def snap_and_check(xyz: np.ndarray, tables: RingTables, ratio: int, tolerance: float,
                   across_edges: bool = True, across_within: float = np.inf) -> tuple[np.ndarray, np.ndarray]:
    """Snap points onto virtual rings and keep those whose range fits the real returns around them.

    Each point goes to its nearest virtual ring (`snap_to_virtual_rings`), with one change: in an
    azimuth column's ring gap whose two returns lie on one surface, the points that fit there, when
    there are at least ratio - 1 of them, are handed to the gap's virtual rings in elevation order,
    spread evenly, so that every virtual ring of the gap gets one (points a network grows from
    one parent tend to bunch on one virtual ring and leave the next one empty). Then points are
    kept by `fits_ring_ranges`. What the spreading and the half-gap rule of `fits_ring_ranges`
    gained on simulated streets: docs/results.md.

    Args:
        xyz: (Q, 3) points, sensor frame, metres. tables: the scan's `RingTables`.
        ratio: virtual ring gaps per real gap (r >= 2). tolerance: >= 0, metres.
        across_edges: keep points across depth edges by the half-gap rule (`fits_ring_ranges`).
        across_within: ... only those within this range of the sensor (metres).

    Returns:
        (Q, 3) float32 snapped points (points outside the rings unmoved), and (Q,) bool: True for
        the points to keep; `fits_ring_ranges(snapped, tables, tolerance, across_edges,
        across_within)` gives the same answer.
    """
    _check_tolerance(tolerance)
    _check_ratio(ratio)
    _check_table(tables.elevation)
    tables = in_column_order(tables)
    at = _locate(xyz, tables.elevation)
    step = _nearest_step(at, ratio)
    range_fits, one_surface = _range_fits(at, tables, tolerance)
    step = _spread_steps(at, step, range_fits & one_surface, ratio)
    return _placed(xyz, at, step, ratio), _fits(at, tables, tolerance, step / ratio, across_edges, across_within,
                                                (range_fits, one_surface))


def _nearest_step(at: _Located, ratio: int) -> np.ndarray:
    """(Q,) the nearest virtual ring j in 1 .. ratio - 1 of each located point."""
    return np.clip(np.round(at.position * ratio), 1, ratio - 1)


def _spread_steps(at: _Located, step: np.ndarray, among: np.ndarray, ratio: int) -> np.ndarray:
    """(Q,) virtual rings: in every (column, gap) cell holding at least ratio - 1 of the `among`
    points, those points take rings 1 .. ratio - 1 in elevation order (top first, ties by index),
    spread evenly (rank i of m takes ring 1 + floor((i + 1/2) (ratio - 1) / m)); every other point
    keeps `step`."""
    gaps = int(at.gap.max(initial=0)) + 1
    cells = (int(at.column.max(initial=0)) + 1) * gaps
    return spread_in_cells(np.flatnonzero(among), at.column, at.gap, at.position, np.asarray(step, np.float64),
                           ratio - 1, gaps, cells)


def _placed(xyz: np.ndarray, at: _Located, step: np.ndarray, ratio: int) -> np.ndarray:
    """(Q, 3) float32 points moved to virtual ring `step` of their gap at their azimuth and range;
    points outside the rings unmoved."""
    return placed_rows(np.asarray(xyz, np.float32), at.between, at.distance, at.top, at.span,
                       np.asarray(step, np.float64), ratio)


def fits_ring_ranges(xyz: np.ndarray, tables: RingTables, tolerance: float,
                     across_edges: bool = True, across_within: float = np.inf) -> np.ndarray:
    """Whether each point's range agrees with the two real returns around it in its azimuth column.

    A ray between two neighbouring rings hits the surface those rings sample (neighbours in
    elevation in the point's column, `in_column_order`). When their two
    returns lie on one surface (range difference within `stages.range_image.surface_gap_limit`),
    the point's range must lie between theirs. Across a depth edge the ray hits one of the two
    surfaces, so its range must be near one of theirs, and the point must lie in the half of the
    gap next to that return (where the edge falls in the gap is unknown, so each surface is given
    the half beside it; the middle virtual ring of an even ratio belongs to both). Without
    `across_edges` no point across a depth edge fits: which surface the ray hits there, and where
    the edge falls, is a guess. `tolerance` widens the range tests (range noise).

    Args:
        xyz: (Q, 3) points, sensor frame, metres.
        tables: the scan's `RingTables`.
        tolerance: >= 0, metres.
        across_edges: keep points across depth edges by the half-gap rule above (False: drop them).
        across_within: ... only those within this range of the sensor (metres; beyond it, which
            surface the ray hits is guessed over a gap that widens with range).

    Returns:
        (Q,) bool: True where the range fits; False also outside the rings and where a return
        above or below is missing (`RingTables.range` is NaN).
    """
    _check_tolerance(tolerance)
    _check_table(tables.elevation)
    tables = in_column_order(tables)
    at = _locate(xyz, tables.elevation)
    return _fits(at, tables, tolerance, at.position, across_edges, across_within)


def _range_fits(at: _Located, tables: RingTables, tolerance: float) -> tuple[np.ndarray, np.ndarray]:
    """(Q,) whether each located point's range fits (between the two returns on one surface, near
    either across a depth edge; inside the rings, both returns known), and (Q,) whether its two
    returns lie on one surface (`surface_gap_limit` with its defaults)."""
    return range_checks(np.asarray(tables.range, np.float64), at.column, at.gap, at.between, at.span, at.distance,
                        float(tolerance), SURFACE_SLOPE, DEFAULT_NOISE_FLOOR)


def _fits(at: _Located, tables: RingTables, tolerance: float, position: np.ndarray, across_edges: bool,
          across_within: float, range_fits: tuple[np.ndarray, np.ndarray] | None = None) -> np.ndarray:
    """(Q,) `fits_ring_ranges` of located points lying at `position` (0: ring above, 1: below) in
    their gap; `range_fits`: `_range_fits` of these points when already known."""
    if across_edges and not across_within > 0:
        raise ValueError(f"ring snapping: across_within must be > 0 metres, got {across_within}")
    range_fits, one_surface = range_fits if range_fits is not None else _range_fits(at, tables, tolerance)
    return beside_fits(np.asarray(tables.range, np.float64), at.column, at.gap, at.distance,
                       np.asarray(position, np.float64), range_fits, one_surface, float(tolerance), HALF_SLACK,
                       float(across_within) if across_edges else -np.inf)


def _check_tolerance(tolerance: float) -> None:
    if not tolerance >= 0:
        raise ValueError(f"ring snapping: range tolerance must be >= 0 m, got {tolerance}")
