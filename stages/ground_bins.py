"""The zone model of `stages.ground_patchwork` and the per-bin plane fits over it.

Bins: rings of horizontal range (zones of equal-width rings, coarser far away) times sectors of
azimuth, numbered ring after ring from the sensor outwards (`ZoneLayout`). The points inside the
model are sorted once by (bin, height) (`sorted_by_bin`), after which every per-bin quantity is a
`np.bincount` or a lookup: the lowest-point representative of each bin (`lowest_point_levels`)
and the PCA plane of each bin, all bins in one batched 3x3 `np.linalg.eigh` (`BinnedPoints.fit`).

Frames: points in the sensor frame (x forward, y left, z up, metres).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache
from typing import NamedTuple

import numpy as np
import scipy.sparse


@dataclass(frozen=True)
class ZoneLayout:
    """The bins of the zone model.

    Ring r covers horizontal ranges [ring_edges[r], ring_edges[r + 1]) (clipped to [min_range,
    max_range)) and has sectors[r] bins, numbered from offsets[r]; inner[b] is the bin of the
    previous ring at the azimuth of bin b's centre (-1 for the first ring). For `bin_ids`:
    squared_edges are the clipped ring edges squared, and ring_sectors / ring_offsets are indexed
    by `searchsorted(squared_edges, range ** 2, "right")`: 0 before the first ring, r + 1 for
    ring r, one past the last ring after it (offset -2**40 there: never a bin).
    """

    ring_edges: np.ndarray
    sectors: np.ndarray
    offsets: np.ndarray
    inner: np.ndarray
    squared_edges: np.ndarray
    ring_sectors: np.ndarray
    ring_offsets: np.ndarray

    @property
    def n_bins(self) -> int:
        return int(self.offsets[-1])


_OUTSIDE = -(2 ** 40)


@lru_cache(maxsize=8)
def zone_layout(zone_edges: tuple[float, ...], rings_per_zone: tuple[int, ...], sectors_per_zone: tuple[int, ...],
            min_range: float, max_range: float) -> ZoneLayout:
    """The bin layout of a zone model (cached: it depends on the parameters only)."""
    edges: list[float] = []
    sectors: list[int] = []
    for zone, (start, stop) in enumerate(zip(zone_edges[:-1], zone_edges[1:])):
        edges += list(np.linspace(start, stop, rings_per_zone[zone] + 1)[:-1])
        sectors += [sectors_per_zone[zone]] * rings_per_zone[zone]
    edges.append(zone_edges[-1])
    sectors_arr = np.asarray(sectors, dtype=np.int64)
    offsets = np.concatenate([[0], np.cumsum(sectors_arr)])
    inner = [np.full(sectors_arr[0], -1, dtype=np.int64)]
    for ring in range(1, len(sectors_arr)):
        centre = (np.arange(sectors_arr[ring]) + 0.5) / sectors_arr[ring]
        inner.append(offsets[ring - 1] + np.minimum((centre * sectors_arr[ring - 1]).astype(np.int64),
                                                    sectors_arr[ring - 1] - 1))
    clipped = np.clip(np.asarray(edges), min_range, max(max_range, min_range))
    return ZoneLayout(
        ring_edges=np.asarray(edges), sectors=sectors_arr, offsets=offsets, inner=np.concatenate(inner),
        squared_edges=clipped ** 2,
        ring_sectors=np.r_[1, sectors_arr, 1].astype(np.float32),
        ring_offsets=np.r_[_OUTSIDE, offsets[:-1], _OUTSIDE])


def bin_ids(x: np.ndarray, y: np.ndarray, layout: ZoneLayout) -> np.ndarray:
    """Bin of every point; negative outside [min_range, max_range) and the zone model.

    Args:
        x, y: (N,) float64 sensor-frame coordinates, metres.
    """
    ring = np.searchsorted(layout.squared_edges, x * x + y * y, side="right")
    # Sectors count from azimuth -180 degrees; float32 is plenty for an azimuth, and faster.
    turn = np.arctan2(y.astype(np.float32), x.astype(np.float32))
    turn *= np.float32(0.5 / np.pi)
    turn += np.float32(0.5)
    np.minimum(turn, np.float32(1 - 2 ** -23), out=turn)  # [0, 1)
    turn *= layout.ring_sectors[ring]
    return layout.ring_offsets[ring] + turn.astype(np.int64)


class BinFit(NamedTuple):
    """Plane fits of all bins.

    Attributes:
        planes: (n_bins, 4) [a, b, c, d], unit normal with c >= 0.
        centroid: (n_bins, 3) centroid of the fitted points.
        fitted: (n_bins,) float number of fitted points.
        axis: (n_bins, 3) unit main direction of the fitted points.
        line: (n_bins,) bool, the fitted points lie along one line (see `line_spread`).
    """

    planes: np.ndarray
    centroid: np.ndarray
    fitted: np.ndarray
    axis: np.ndarray
    line: np.ndarray


def turn_about_lines(normal: np.ndarray, axis: np.ndarray, target: np.ndarray) -> np.ndarray:
    """Normals (m, 3) of planes through lines of direction `axis` (m, 3), each turned about its line
    to be as close as possible to `target` ((3,) or (m, 3) unit vectors); a normal whose target is
    along its line is left as it was."""
    turned = target - (axis * target).sum(axis=-1, keepdims=True) * axis
    length = np.linalg.norm(turned, axis=1, keepdims=True)
    return np.where(length > 1e-6, turned / np.maximum(length, 1e-6), normal)


class BinnedPoints:
    """The points inside the zone model, sorted by bin, in per-bin local coordinates.

    Local coordinates (u, v, w) = point - origin of its bin, where the origin is one of the bin's
    points at the bin's LPR height: plane fits on moments stay accurate in float64 far from the
    sensor, and every per-bin value reaches its points with one `np.repeat`.
    """

    def __init__(self, x: np.ndarray, y: np.ndarray, z: np.ndarray, level: np.ndarray,
                 counts: np.ndarray, line_spread: float) -> None:
        """x, y, z: (n,) sensor-frame coordinates sorted by bin; level: (n,) the LPR of each
        point's bin; counts: (n_bins,) points per bin; line_spread: see `PatchworkParams`."""
        self.counts = counts
        self.line_spread = line_spread
        self.indptr = np.concatenate([[0], np.cumsum(counts)])
        occupied = counts > 0
        self.origin = np.zeros((len(counts), 3))
        first = self.indptr[:-1][occupied]
        self.origin[occupied] = np.c_[x[first], y[first], level[first]]
        u = x - self.spread(self.origin[:, 0])
        v = y - self.spread(self.origin[:, 1])
        w = z - level
        self.local = (u, v, w)
        # Columns: 1, u, v, w, uu, uv, uw, vv, vw, ww; summed per bin by one sparse product.
        # Written row by row and transposed once: much faster than stacking columns.
        rows = np.empty((10, len(u)))
        rows[0], rows[1], rows[2], rows[3] = 1.0, u, v, w
        for row, (a, b) in enumerate(((u, u), (u, v), (u, w), (v, v), (v, w), (w, w)), start=4):
            np.multiply(a, b, out=rows[row])
        self.features = np.ascontiguousarray(rows.T)

    def spread(self, per_bin: np.ndarray) -> np.ndarray:
        """(n_bins,) values -> (n,) the value of each point's bin."""
        return np.repeat(per_bin, self.counts)

    def fit(self, selected: np.ndarray) -> BinFit:
        """PCA plane per bin through its selected points, in local coordinates.

        Args:
            selected: (n,) bool.

        Returns:
            The `BinFit`; planes of bins with fewer than 3 selected points are arbitrary.
        """
        n_bins, n = len(self.counts), len(selected)
        weights = scipy.sparse.csr_matrix((selected.astype(np.float64), np.arange(n), self.indptr),
                                          shape=(n_bins, n))
        moments = np.asarray(weights @ self.features)
        fitted = moments[:, 0]
        safe = np.maximum(fitted, 1.0)[:, None]
        centroid = moments[:, 1:4] / safe
        upper = moments[:, 4:] / safe  # uu, uv, uw, vv, vw, ww
        cov = upper[:, [[0, 1, 2], [1, 3, 4], [2, 4, 5]]] - centroid[:, :, None] * centroid[:, None, :]
        values, vectors = np.linalg.eigh(cov)
        normal = vectors[:, :, 0]  # eigenvector of the smallest eigenvalue
        axis = vectors[:, :, 2]
        # Points along one line (a single laser ring crossing a far bin) fix no plane: the normal
        # may turn about the line. Until the bin's neighbours are known, take the most level one.
        line = values[:, 1] < self.line_spread ** 2
        normal[line] = turn_about_lines(normal[line], axis[line], np.array([0.0, 0.0, 1.0]))
        normal *= np.where(normal[:, 2:3] < 0, -1.0, 1.0)
        planes = np.concatenate([normal, -(normal * centroid).sum(axis=1, keepdims=True)], axis=1)
        return BinFit(planes, centroid, fitted, axis, line)

    def distances(self, planes: np.ndarray) -> np.ndarray:
        """(n,) |distance| of every point to the local-coordinate plane of its bin, metres."""
        u, v, w = self.local
        a, b, c, d = (self.spread(planes[:, k]) for k in range(4))
        return np.abs(a * u + b * v + c * w + d)

    def to_sensor(self, fit: BinFit) -> BinFit:
        """A fit in local coordinates -> the same fit in the sensor frame."""
        planes = fit.planes.copy()
        planes[:, 3] -= (fit.planes[:, :3] * self.origin).sum(axis=1)
        return fit._replace(planes=planes, centroid=fit.centroid + self.origin)

    def to_local(self, planes: np.ndarray) -> np.ndarray:
        """Per-bin sensor-frame planes (n_bins, 4) -> each in its bin's local coordinates."""
        moved = planes.copy()
        moved[:, 3] += (planes[:, :3] * self.origin).sum(axis=1)
        return moved


def sorted_by_bin(x: np.ndarray, y: np.ndarray, z: np.ndarray, layout: ZoneLayout) -> tuple[np.ndarray, np.ndarray]:
    """The points inside the zone model sorted by bin, then height: (n,) their indices into the
    scan and (n,) their bins."""
    bin_all = bin_ids(x, y, layout)
    inside = np.flatnonzero(bin_all >= 0)
    # One sort on a combined key; heights are clipped to +-499 m so the key stays ordered.
    order = np.argsort(bin_all[inside] * 1000.0 + np.clip(z[inside], -499.0, 499.0))
    index = inside[order]
    return index, bin_all[index]


def lowest_point_levels(z_sorted: np.ndarray, counts: np.ndarray, lpr_points: int) -> np.ndarray:
    """Per bin, the median height of its `lpr_points` lowest points (0 for empty bins).

    Args:
        z_sorted: (n,) heights sorted by bin, then height. counts: (n_bins,) points per bin.
    """
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    occupied = counts > 0
    lpr = np.zeros(len(counts))
    lpr[occupied] = z_sorted[starts[occupied] + np.minimum(counts[occupied], lpr_points) // 2]
    return lpr
