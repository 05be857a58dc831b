"""The default ground method of `stages.ground`: zone-based local plane fitting (Patchwork family).

Pure numpy, vectorised over all bins of the concentric zone model: the points are sorted once by
(bin, height), after which every per-bin quantity is a `np.bincount` or a lookup, and the plane
fit of all bins is one batched 3x3 `np.linalg.eigh`.

Assumptions: points in the sensor frame (x forward, y left, z up, metres), sensor roughly level
and above the ground it drives on (KITTI: 1.73 m, estimated from each scan). Ground is what a
vehicle could drive or walk on: road, parking, sidewalks and kerbs, terrain. Low obstacles and
points below the road surface (multi-path reflections) are not ground.

Per scan:
1. bins: rings of horizontal range (zones of equal-width rings, coarser far away) times sectors of
   azimuth; points outside [min_range, max_range) are never ground;
2. per bin, the lowest-point representative (LPR): the median height of its `lpr_points` lowest
   points (a median, so a few reflections below the road do not drag it down);
3. sensor height: minus the median LPR of the well-filled bins of the innermost zone;
4. seeds: points within [-seed_margin_below, +seed_margin] of the LPR; then `iterations` rounds of
   PCA plane fitting per bin (batched covariances, one `eigh`), each keeping the points within
   `distance_threshold` of the plane. A far bin crossed by a single laser ring holds a line,
   which fixes no plane: its plane is turned about the line to continue the inner ground (step 5);
5. ground likelihood, ring by ring from the sensor outwards: a bin is ground when it has enough
   points, its plane is upright (normal z >= `uprightness`) and its height at the fitted
   centroid is within `max_step` of the ground plane of the inner bin at the same azimuth
   extrapolated there (or of the sensor-height plane while no inner ground was found). Ramps and
   slopes continue the inner plane; kerbs (15-20 cm) are a step below `max_step`; car roofs and
   walls are neither upright nor continuous;
5b. ground is continuous along a ring too: an upright, well-filled bin rejected in step 5 is ground
   when its centroid lies within `neighbour_step` of the plane of an accepted neighbour in the same
   ring (the next sector on either side), extrapolated there; repeated until no bin joins. The
   inner plane is extrapolated across a whole ring of bins (5-10 m far out), so a small tilt of it,
   or a stale reference behind a rejected inner bin (a bush, a car), rejects sloping or uneven
   terrain, while the neighbour in the same ring is at the same range and sees the same terrain;
5c. a dip is not a new ground level: an accepted bin whose centroid lies more than
   `distance_threshold` below the plane it was judged against is a dip (a ditch, a gutter: its
   lowest points, and so its plane, are the dip's bottom), and the bins beyond it may continue
   either its plane or the ground from before the dip (`resume_after_dips`); otherwise the
   terrain coming back up beyond a ditch is a step above the ditch's plane, and every bin behind it
   is lost. A plane steeper than `reference_uprightness` (a ditch's side) is ground but is not
   extrapolated to judge the bins beyond it: they continue what it was judged against;
5d. in an accepted bin whose plane is a dip or steeper than `reference_uprightness`, the level
   it was judged against is ground too where points lie on it: a second plane is fitted to the
   points near that level (`level_beside_dips`). A bin 5-10 m wide often holds road, verge and
   ditch together, and its lowest points, so its first plane, are the ditch's;
6. a point is ground when it lies within `distance_threshold` of its bin's accepted plane; the
   points of bins too sparse for their own plane are judged against the nearest inner ground
   plane at the same azimuth;
7. the foot of vertical surfaces (walls, car bumpers, planters) lies within `distance_threshold`
   of the ground and tilts the fitted planes up towards it: in `structure_cell` x-y cells where
   a surface rises `structure_rise` above the cell's lowest point, points more than
   `structure_keep` above that lowest point are not ground.

Cost: one argsort of the scan plus a few dozen linear numpy passes (time per scan:
`python bench/ground.py`; docs/results.md).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .ground_bins import (BinFit, BinnedPoints, ZoneLayout, lowest_point_levels, sorted_by_bin, turn_about_lines,
                          zone_layout)


@dataclass(frozen=True)
class PatchworkParams:
    """Parameters of the default method (metres, unless stated).

    Attributes:
        min_range: points nearer than this (horizontal range) are never ground: the ego vehicle.
        max_range: points at or beyond this range are never ground (beyond the zone model).
        zone_edges: range at which each zone starts, plus the outer edge of the last zone.
        rings_per_zone: rings of equal width in each zone.
        sectors_per_zone: azimuth sectors of each ring of each zone.
        lpr_points: lowest points per bin whose median is the bin's lowest-point representative.
        seed_margin: seeds are the points at most this far above their bin's LPR ...
        seed_margin_below: ... and at most this far below it.
        distance_threshold: largest point-to-plane distance of a ground point.
        iterations: plane fits per bin (the first on the seeds, the next on the points near the
            previous plane).
        min_points: bins with fewer points get no plane of their own; their points are judged
            against the plane of the nearest inner ground bin.
        line_spread: a bin whose fitted points spread less than this (standard deviation, metres)
            across their main direction lie along one line (a single laser ring through a far
            bin); its plane is the one through that line closest to level.
        uprightness: least z component of a ground plane's unit normal (0.707: 45 degrees).
        max_step: largest height difference between a bin's plane at its centroid and the inner
            ground plane extrapolated there.
        neighbour_step: largest height difference between a bin's centroid and the plane of an
            accepted neighbour in the same ring extrapolated there (step 5b): a kerb, no more.
        resume_after_dips: bins beyond a dip may continue the ground from before it (step 5c).
        reference_uprightness: least z component of an accepted plane's normal for it to be
            extrapolated to judge the bins beyond it (0.95: 18 degrees, steeper than roads).
        level_beside_dips: fit a second plane at the judged level in dip and steep bins (step 5d).
        structure_cell: side of the square x-y cells in which ground points are dropped when a
            vertical surface rises there (see `structure_rise`); 0 turns this off.
        structure_rise: (low, high): a cell holds a vertical surface when one of its points lies
            between low and high above its lowest point; low must exceed the kerbs that count
            as ground.
        structure_keep: in such a cell, ground points up to this height above its lowest point
            stay ground (the road in front of a wall); higher ones are the surface's foot.
        sensor_height: sensor height used when the scan has too few near points to estimate it.
        sensor_height_bounds: (low, high): estimates outside these bounds fall back to
            `sensor_height`.
    """

    min_range: float = 2.7
    max_range: float = 80.0
    zone_edges: tuple[float, ...] = (2.7, 12.3625, 22.025, 41.35, 80.0)
    rings_per_zone: tuple[int, ...] = (2, 4, 4, 4)
    sectors_per_zone: tuple[int, ...] = (16, 32, 54, 32)
    lpr_points: int = 20
    seed_margin: float = 0.3
    seed_margin_below: float = 0.3
    distance_threshold: float = 0.125
    iterations: int = 2
    min_points: int = 10
    line_spread: float = 0.1
    uprightness: float = 0.707
    max_step: float = 0.35
    neighbour_step: float = 0.2
    reference_uprightness: float = 0.95
    level_beside_dips: bool = True
    resume_after_dips: bool = True
    structure_cell: float = 0.4
    structure_rise: tuple[float, float] = (0.25, 0.75)
    structure_keep: float = 0.15
    sensor_height: float = 1.73
    sensor_height_bounds: tuple[float, float] = (0.5, 3.0)

    def __post_init__(self) -> None:
        zones = len(self.zone_edges) - 1
        if zones < 1 or len(self.rings_per_zone) != zones or len(self.sectors_per_zone) != zones:
            raise ValueError("zone_edges needs one more entry than rings_per_zone and sectors_per_zone")
        if any(b <= a for a, b in zip(self.zone_edges, self.zone_edges[1:])):
            raise ValueError(f"zone_edges must increase, got {self.zone_edges}")
        if min(self.rings_per_zone) < 1 or min(self.sectors_per_zone) < 1:
            raise ValueError("rings_per_zone and sectors_per_zone must be positive")
        if self.iterations < 1 or self.lpr_points < 1 or self.min_points < 3:
            raise ValueError("iterations and lpr_points must be >= 1 and min_points >= 3")
        if not 0 <= self.min_range < self.max_range:
            raise ValueError(f"need 0 <= min_range < max_range, got {self.min_range}, {self.max_range}")
        if self.structure_cell != 0 and not self.structure_cell >= self.max_range / 1000:
            raise ValueError(f"structure_cell must be 0 (off) or at least max_range / 1000 (the grid spans "
                             f"+-max_range), got {self.structure_cell}")
        if len(self.structure_rise) != 2 or self.structure_rise[0] >= self.structure_rise[1]:
            raise ValueError(f"structure_rise must be a (low, high) pair with low < high, got {self.structure_rise}")
        if self.max_step < 0 or self.neighbour_step < 0:
            raise ValueError(f"max_step and neighbour_step must be >= 0, got {self.max_step}, {self.neighbour_step}")
        if len(self.sensor_height_bounds) != 2 or self.sensor_height_bounds[0] > self.sensor_height_bounds[1]:
            raise ValueError("sensor_height_bounds must be a (low, high) pair with low <= high")


def _accept_bins(fit: BinFit, counts: np.ndarray, layout: ZoneLayout, height: float,
                 p: PatchworkParams) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Which bins are ground (step 5 of the module docstring). The planes of line bins in `fit`
    (sensor frame) are turned, in place, to continue the ground they are judged against.

    Returns:
        accepted (n_bins,) bool; dip (n_bins,) bool, read where accepted: the bin's centroid lies
        more than `distance_threshold` below the plane it was judged against; judged (n_bins, 4):
        that plane, sensor frame.
    """
    planes, centroid = fit.planes, fit.centroid
    accepted = np.zeros(layout.n_bins, dtype=bool)
    enough = (fit.fitted >= 3) & (counts >= p.min_points)
    # The plane each bin must continue: the inner ground, else what the inner bin had to continue.
    reference = np.tile([0.0, 0.0, 1.0, height], (layout.n_bins, 1))
    # The plane each bin was judged against; dip: its centroid lies more than distance_threshold
    # below that plane (read for accepted bins only); before_dip: the ground before the last
    # accepted dip on the way in, which `resumable` bins may continue instead of `reference`.
    judged, before_dip = reference.copy(), reference.copy()
    dip = np.zeros(layout.n_bins, dtype=bool)
    resumable = np.zeros(layout.n_bins, dtype=bool)
    for ring in range(len(layout.sectors)):
        bins = np.arange(layout.offsets[ring], layout.offsets[ring + 1])
        if ring > 0:
            inner = layout.inner[bins]
            extends = accepted[inner] & (planes[inner, 2] >= p.reference_uprightness)
            reference[bins] = np.where(extends[:, None], planes[inner], reference[inner])
            before_dip[bins] = np.where(accepted[inner, None], judged[inner], before_dip[inner])
            resumable[bins] = np.where(accepted[inner], dip[inner], resumable[inner]) & p.resume_after_dips
        lines = bins[fit.line[bins]]
        if len(lines):
            normal = turn_about_lines(planes[lines, :3], fit.axis[lines], reference[lines, :3])
            planes[lines] = np.c_[normal, -(normal * centroid[lines]).sum(axis=1)]
        centre = centroid[bins]
        candidate = enough[bins] & (planes[bins, 2] >= p.uprightness)
        continues = np.abs(centre[:, 2] - _height_on(reference[bins], centre)) < p.max_step
        back = np.abs(centre[:, 2] - _height_on(before_dip[bins], centre)) < p.max_step
        resumes = resumable[bins] & ~continues & back
        judged[bins] = np.where(resumes[:, None], before_dip[bins], reference[bins])
        dip[bins] = centre[:, 2] - _height_on(judged[bins], centre) < -p.distance_threshold
        accepted[bins] = candidate & (continues | resumes)
        accepted[bins] = _grow_along_ring(accepted[bins], candidate, planes[bins], centre, p.neighbour_step)
    return accepted, dip, judged


def _level_beside(sorted_points: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray], counts: np.ndarray,
                  uneven: np.ndarray, judged: np.ndarray, p: PatchworkParams) -> np.ndarray:
    """Ground at the level beside a dip (step 5d of the module docstring): (n,) bool per sorted point.

    In each `uneven` bin (accepted, but its plane fitted to a dip or a steep side of one), a
    second plane is fitted to the points within `seed_margin` of the plane the bin was judged
    against (`judged`, (n_bins, 4) sensor frame), refined like the first; where it is upright,
    holds `min_points` and its centroid lies within `max_step` of the judged plane, its points
    within `distance_threshold` are ground too. Only the uneven bins' points are binned again
    (`sorted_points`: x, y, z and bin LPR of every point, sorted by bin; `counts` per bin), so the
    fits cost what those bins hold, and each such bin's local frame is the one of the first fit.
    """
    members = np.repeat(uneven, counts)
    if not members.any():
        return members
    x, y, z, level_of_bin = (values[members] for values in sorted_points)
    cloud = BinnedPoints(x, y, z, level_of_bin, np.where(uneven, counts, 0), p.line_spread)
    reference = cloud.to_local(judged)
    selected = cloud.distances(reference) < p.seed_margin
    for _ in range(p.iterations):
        fit = cloud.fit(selected)
        selected = cloud.distances(fit.planes) < p.distance_threshold
    level = cloud.to_sensor(fit)
    kept = (uneven & (level.fitted >= p.min_points) & (level.planes[:, 2] >= p.uprightness)
            & (np.abs(level.centroid[:, 2] - _height_on(judged, level.centroid)) < p.max_step))
    members[members] = selected & cloud.spread(kept)
    return members


def _height_on(planes: np.ndarray, points: np.ndarray) -> np.ndarray:
    """(m,) height z of each plane (m, 4), normal z > 0, above the x, y of each point (m, 3+)."""
    return -(planes[:, 0] * points[:, 0] + planes[:, 1] * points[:, 1] + planes[:, 3]) / planes[:, 2]


def _grow_along_ring(accepted: np.ndarray, candidate: np.ndarray, planes: np.ndarray, centre: np.ndarray,
                     step: float) -> np.ndarray:
    """The ground bins of one ring, grown sideways (step 5b of the module docstring).

    Args:
        accepted: (s,) bool, the ring's bins accepted against the inner ground, in azimuth order
            (the last sector neighbours the first).
        candidate: (s,) bool, bins that could be ground (enough points, upright plane).
        planes: (s, 4) their planes, sensor frame; centre: (s, 3) their centroids.
        step: largest height difference between a candidate's centroid and an accepted
            neighbour's plane extrapolated there.

    Returns:
        (s,) bool: `accepted` plus the candidates joined, directly or through other joined bins,
        to an accepted bin by steps below `step`.
    """
    accepted = accepted.copy()
    for _ in range(len(accepted)):
        joined = np.zeros_like(accepted)
        for shift in (1, -1):
            neighbour = np.roll(np.arange(len(accepted)), shift)
            open_ = candidate & ~accepted & accepted[neighbour]
            if open_.any():
                heights = _height_on(planes[neighbour[open_]], centre[open_])
                joined[np.flatnonzero(open_)[np.abs(centre[open_, 2] - heights) < step]] = True
        if not joined.any():
            break
        accepted |= joined
    return accepted


def _plane_owners(accepted: np.ndarray, counts: np.ndarray, layout: ZoneLayout, p: PatchworkParams) -> np.ndarray:
    """Index of the plane each bin's points are judged against: its own when accepted; for a bin
    too sparse for its own plane, the one its inner neighbour uses; -1 for none."""
    owner = np.where(accepted, np.arange(layout.n_bins), -1)
    sparse = counts < p.min_points
    for ring in range(1, len(layout.sectors)):
        bins = np.arange(layout.offsets[ring], layout.offsets[ring + 1])
        owner[bins] = np.where(sparse[bins], owner[layout.inner[bins]], owner[bins])
    return owner


def estimate(points: np.ndarray, p: PatchworkParams) -> tuple[np.ndarray, np.ndarray, float]:
    """Ground mask of a scan with the default method (see the module docstring).

    Args:
        points: (N, 3+) real array of finite x, y, z (sensor frame, z up, metres) and any further
            columns, which are ignored; N >= 1.
        p: the parameters.

    Returns:
        mask (N,) bool, True for ground; planes (G, 4) float64 [a, b, c, d] in the sensor frame of
        the G bins accepted as ground (unit normal, c > 0); the estimated sensor height, metres.
    """
    layout = zone_layout(p.zone_edges, p.rings_per_zone, p.sectors_per_zone, p.min_range, p.max_range)
    x, y, z = (points[:, k].astype(np.float64) for k in range(3))
    index, bins = sorted_by_bin(x, y, z, layout)
    counts = np.bincount(bins, minlength=layout.n_bins)
    lpr = lowest_point_levels(z[index], counts, p.lpr_points)
    height = _sensor_height(lpr, counts, layout, p)
    xs, ys, zs = x[index], y[index], z[index]
    levels = np.repeat(lpr, counts)
    cloud = BinnedPoints(xs, ys, zs, levels, counts, p.line_spread)

    w = cloud.local[2]  # height above the bin's LPR
    selected = (w > -p.seed_margin_below) & (w < p.seed_margin)
    for _ in range(p.iterations):
        fit = cloud.fit(selected)
        selected = cloud.distances(fit.planes) < p.distance_threshold
    fit = cloud.to_sensor(fit)
    planes = fit.planes

    accepted, dip, judged = _accept_bins(fit, counts, layout, height, p)
    owner = _plane_owners(accepted, counts, layout, p)
    # Each bin's points against the plane of its owner (its own or borrowed), in local coordinates.
    judged_planes = cloud.to_local(planes[np.maximum(owner, 0)])
    is_ground = cloud.spread(owner >= 0) & (cloud.distances(judged_planes) < p.distance_threshold)
    if p.level_beside_dips:
        uneven = accepted & (dip | (planes[:, 2] < p.reference_uprightness))
        is_ground |= _level_beside((xs, ys, zs, levels), counts, uneven, judged, p)
    if p.structure_cell > 0:
        is_ground &= ~_at_vertical_structures(xs, ys, zs, w > -p.seed_margin_below, p)
    mask = np.zeros(len(points), dtype=bool)
    mask[index[is_ground]] = True
    return mask, planes[accepted], height


def _at_vertical_structures(x: np.ndarray, y: np.ndarray, z: np.ndarray, usable: np.ndarray,
                            p: PatchworkParams) -> np.ndarray:
    """Points at the foot of vertical surfaces (step 7 of the module docstring).

    A cell of the `structure_cell` x-y grid holds a vertical surface (a wall, a car's bumper, a
    planter) when one of its points lies between `structure_rise[0]` and `structure_rise[1]`
    above the cell's lowest point; its points more than `structure_keep` above that lowest point
    are flagged. Only `usable` points (not below the road, where reflections lie) count.

    Args:
        x, y, z: (n,) sensor-frame coordinates, metres, all within `max_range` of the sensor.
        usable: (n,) bool.

    Returns:
        (n,) bool, True for the flagged points.
    """
    side = int(np.ceil(2 * p.max_range / p.structure_cell))
    column = np.clip(((x + p.max_range) / p.structure_cell).astype(np.int64), 0, side - 1)
    row = np.clip(((y + p.max_range) / p.structure_cell).astype(np.int64), 0, side - 1)
    cell = row * side + column
    lowest = np.full(side * side, np.inf)
    np.minimum.at(lowest, cell[usable], z[usable])
    rise = z - lowest[cell]
    rising = usable & (rise > p.structure_rise[0]) & (rise < p.structure_rise[1])
    structured = np.zeros(side * side, dtype=bool)
    structured[cell[rising]] = True
    return structured[cell] & (rise > p.structure_keep)


def _sensor_height(lpr: np.ndarray, counts: np.ndarray, layout: ZoneLayout, p: PatchworkParams) -> float:
    """Sensor height above the ground, metres: minus the median LPR of the well-filled bins of the
    innermost zone; `p.sensor_height` when there are none or the estimate is out of bounds."""
    first_zone = slice(0, int(layout.offsets[p.rings_per_zone[0]]))
    levels = lpr[first_zone][counts[first_zone] >= p.min_points]
    if len(levels) == 0:
        return p.sensor_height
    height = -float(np.median(levels))
    low, high = p.sensor_height_bounds
    return height if low <= height <= high else p.sensor_height
