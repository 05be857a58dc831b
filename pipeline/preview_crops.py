"""Pick the regions a preview zooms into: a car-sized cluster, a wall edge, a pole or trunk.

The finder clusters the non-ground input points on a bird's-eye occupancy grid, measures each
cluster along its principal horizontal axis, and keeps, for each kind, the nearest cluster whose
size fits. Everything is deterministic: same cloud, same crops.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage

CROP_KINDS = ("car", "wall", "pole")
CELL_M = 0.3  # occupancy cell; clusters separated by a gap of one empty cell or more stay apart
MAX_RANGE_M = 40.0  # farther away the rings are too sparse to read in a crop
MIN_POINTS = 30
WALL_WINDOW_M = 6.0  # a wall crop shows this much wall, starting just before its nearer end
MARGIN_M = 0.5


@dataclass(frozen=True)
class Crop:
    """An oriented box around one structure, in the sensor frame, metres.

    `axis` is the unit horizontal direction the side view looks across (the structure's length);
    the box spans `along` (min, max) on it, `across` (min, max) on the perpendicular, `z` (min, max).
    """

    kind: str
    axis: tuple[float, float]
    along: tuple[float, float]
    across: tuple[float, float]
    z: tuple[float, float]

    def _frame(self, xyz: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        ax, ay = self.axis
        return xyz[:, 0] * ax + xyz[:, 1] * ay, -xyz[:, 0] * ay + xyz[:, 1] * ax

    def select(self, xyz: np.ndarray) -> np.ndarray:
        """(N,) bool: which of the (N, 3+) points lie inside the box."""
        u, w = self._frame(xyz)
        return ((u >= self.along[0]) & (u <= self.along[1]) & (w >= self.across[0]) & (w <= self.across[1])
                & (xyz[:, 2] >= self.z[0]) & (xyz[:, 2] <= self.z[1]))

    def side_view(self, xyz: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(along, z) in metres of (N, 3+) points, `along` measured from the box's start."""
        return self._frame(xyz)[0] - self.along[0], xyz[:, 2]

    @property
    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """Axis-aligned (min xyz, max xyz) of the box, metres."""
        ax, ay = self.axis
        corners = np.array([[u * ax - w * ay, u * ay + w * ax] for u in self.along for w in self.across])
        return (np.array([*corners.min(axis=0), self.z[0]]), np.array([*corners.max(axis=0), self.z[1]]))


@dataclass(frozen=True)
class _Cluster:
    points: np.ndarray  # (K, 3)
    axis: np.ndarray  # (2,) unit, principal horizontal direction
    along: tuple[float, float]
    across: tuple[float, float]
    range_m: float

    @property
    def length(self) -> float:
        return self.along[1] - self.along[0]

    @property
    def width(self) -> float:
        return self.across[1] - self.across[0]

    @property
    def height(self) -> float:
        return float(np.ptp(self.points[:, 2]))


def _clusters(xyz: np.ndarray) -> list[_Cluster]:
    if xyz.shape[0] == 0:
        return []
    cells = np.floor(xyz[:, :2] / CELL_M).astype(np.int64)
    origin = cells.min(axis=0)
    cells -= origin
    grid = np.zeros(cells.max(axis=0) + 1, bool)
    grid[cells[:, 0], cells[:, 1]] = True
    labels, count = ndimage.label(grid, structure=np.ones((3, 3), bool))
    point_labels = labels[cells[:, 0], cells[:, 1]]
    order = np.argsort(point_labels, kind="stable")
    starts = np.searchsorted(point_labels[order], np.arange(1, count + 2))
    found = []
    for label in range(count):
        members = xyz[order[starts[label]:starts[label + 1]]]
        if members.shape[0] < MIN_POINTS:
            continue
        flat = members[:, :2] - members[:, :2].mean(axis=0)
        _, vectors = np.linalg.eigh(flat.T @ flat)
        axis = vectors[:, 1] if vectors[0, 1] >= 0 else -vectors[:, 1]  # sign fixed for determinism
        u = members[:, :2] @ axis
        w = members[:, :2] @ np.array([-axis[1], axis[0]])
        found.append(_Cluster(members, axis, (float(u.min()), float(u.max())), (float(w.min()), float(w.max())),
                              float(np.linalg.norm(members[:, :2].mean(axis=0)))))
    return found


def _is_car(c: _Cluster) -> bool:
    return 2.5 <= c.length <= 5.5 and 1.0 <= c.width <= 2.6 and 0.8 <= c.height <= 2.2


def _is_wall(c: _Cluster) -> bool:
    # Planar: thin across its length (spread of the across coordinate, robust to a few strays).
    w = c.points[:, :2] @ np.array([-c.axis[1], c.axis[0]])
    if not (c.length >= 4.0 and c.height >= 2.0 and float(np.std(w)) <= 0.3):
        return False
    # Vertical along most of its length: most 0.5 m slices span 1.5 m of height or more.
    u = c.points[:, :2] @ c.axis
    slices = np.floor((u - u.min()) / 0.5).astype(np.int64)
    tops = np.full(slices.max() + 1, -np.inf)
    bottoms = np.full(slices.max() + 1, np.inf)
    np.maximum.at(tops, slices, c.points[:, 2])
    np.minimum.at(bottoms, slices, c.points[:, 2])
    return float(np.mean(tops - bottoms >= 1.5)) >= 0.6


def _is_pole(c: _Cluster) -> bool:
    return c.length <= 0.8 and c.width <= 0.8 and c.height >= 1.5


def _box(kind: str, c: _Cluster, z_floor: float) -> Crop:
    along = (c.along[0] - MARGIN_M, c.along[1] + MARGIN_M)
    if kind == "wall":
        # Window at the wall's end nearer the sensor, so the crop shows the edge and some face.
        ends = [c.along[0], c.along[1]]
        near = min(ends, key=lambda u: float(np.linalg.norm(u * c.axis)))
        along = (near - 1.0, near + WALL_WINDOW_M - 1.0) if near == c.along[0] else (near - WALL_WINDOW_M + 1.0, near + 1.0)
    axis = c.axis
    if kind == "pole":
        # A pole has no length: look across it, perpendicular to the ray from the sensor.
        centre = c.points[:, :2].mean(axis=0)
        ray = centre / max(float(np.linalg.norm(centre)), 1e-6)
        axis = np.array([-ray[1], ray[0]])
        u_c, w_c = float(centre @ axis), float(centre @ np.array([-axis[1], axis[0]]))
        along, across = (u_c - 1.5, u_c + 1.5), (w_c - 1.0, w_c + 1.0)
    else:
        across = (c.across[0] - MARGIN_M, c.across[1] + MARGIN_M)
    z = (min(z_floor, float(c.points[:, 2].min())) - 0.3, float(c.points[:, 2].max()) + 0.3)
    return Crop(kind, (float(axis[0]), float(axis[1])), along, across, z)


def find_crops(xyz: np.ndarray, ground: np.ndarray | None = None) -> dict[str, Crop | None]:
    """Choose one crop of each kind in `CROP_KINDS` from an input scan.

    Args:
        xyz: (N, 3+) input points (no generated ones), sensor frame, metres.
        ground: optional (N,) bool, True for ground points; without it, points below the 5th
            percentile of height plus 0.3 m count as ground.

    Returns:
        {kind: Crop or None}, None where no cluster of that kind is within `MAX_RANGE_M`.
    """
    xyz = np.asarray(xyz, dtype=np.float64)[:, :3]
    if ground is None:
        floor = float(np.percentile(xyz[:, 2], 5)) if xyz.shape[0] else 0.0
        ground = xyz[:, 2] < floor + 0.3
    ground = np.asarray(ground, bool)
    z_floor = float(np.median(xyz[ground, 2])) if ground.any() else (float(xyz[:, 2].min()) if xyz.size else 0.0)
    above = xyz[~ground]
    above = above[np.linalg.norm(above[:, :2], axis=1) <= MAX_RANGE_M]
    clusters = sorted(_clusters(above), key=lambda c: (c.range_m, -c.points.shape[0]))
    tests = {"car": _is_car, "wall": _is_wall, "pole": _is_pole}
    crops: dict[str, Crop | None] = {}
    for kind in CROP_KINDS:
        match = next((c for c in clusters if c.range_m >= 2.0 and tests[kind](c)), None)
        crops[kind] = None if match is None else _box(kind, match, z_floor)
    return crops
