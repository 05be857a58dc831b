"""Scores of a densified scan against the full 64-ring scan it was thinned from.

Regions: the ground of the FULL scan is found once; the reference region is the full scan's
non-ground points, and an output point belongs to the region when its nearest full-scan point is
non-ground (`Reference`). So every method is cut by the same, denser and more reliable ground mask,
whatever its own ground flags, and ground removal errors on the thinned input do not hide in the
score.

Metrics (metres, and fractions of occupied voxels), all from `cadpu.metrics`: Chamfer distance
(mean of the two directed mean nearest-neighbour distances), Hausdorff (larger directed maximum)
and HD95 (larger directed 95th percentile); precision, recall and F1 of occupied `voxel` cubes.
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import asdict, dataclass

import numpy as np
from scipy.spatial import cKDTree

from cadpu.metrics import chamfer_from_distances, directed_distances, hausdorff_from_distances, voxel_f1

NON_GROUND = "non-ground"
WHOLE = "whole"
REGIONS = (NON_GROUND, WHOLE)
#: Edge of the occupancy voxels, metres.
VOXEL_SIZE = 0.1


@dataclass(frozen=True)
class Score:
    """How close one output is to the full scan in one region.

    Attributes:
        points: output points in the region.
        chamfer, hausdorff, hd95: metres (NaN when the output or the reference region is empty).
        precision, recall, f1: occupied-voxel agreement, fractions in [0, 1].
    """

    points: int
    chamfer: float
    hausdorff: float
    hd95: float
    precision: float
    recall: float
    f1: float


@dataclass(frozen=True)
class Row:
    """One line of the result table: a method's score on one scan ("mean" for the average) and
    region, and the seconds the method took on that scan (densification only, not scoring)."""

    scan: str
    method: str
    region: str
    score: Score
    seconds: float

    def as_dict(self) -> dict[str, object]:
        """Flat {column: value} for the CSV."""
        return {"scan": self.scan, "method": self.method, "region": self.region, **asdict(self.score),
                "seconds": self.seconds}


class Reference:
    """The full 64-ring scan as the yardstick: scores any output against it in both regions.

    Args:
        full: (N, 3+) full scan, sensor frame, metres.
        full_ground: (N,) bool ground mask of the full scan.
        voxel: occupancy voxel edge, metres.
    """

    def __init__(self, full: np.ndarray, full_ground: np.ndarray, voxel: float = VOXEL_SIZE) -> None:
        self.xyz = np.asarray(full, dtype=np.float64)[:, :3]
        self.ground = np.asarray(full_ground, dtype=bool)
        if self.ground.shape != (len(self.xyz),):
            raise ValueError(f"Reference: {len(self.xyz)} points but a ground mask of shape {self.ground.shape}")
        self.voxel = voxel
        self._tree = cKDTree(self.xyz)
        non_ground = self.xyz[~self.ground]
        self._non_ground = non_ground
        self._non_ground_tree = cKDTree(non_ground) if len(non_ground) else None

    def score(self, predicted: np.ndarray) -> dict[str, Score]:
        """Score an output cloud.

        Args:
            predicted: (Q, 3+) output points, sensor frame, metres.

        Returns:
            {"non-ground": Score, "whole": Score}; an output point is in the non-ground region when
            its nearest full-scan point is non-ground.
        """
        xyz = np.asarray(predicted, dtype=np.float64)[:, :3]
        if len(xyz) == 0:
            return {region: _empty_score() for region in REGIONS}
        to_full, nearest = self._tree.query(xyz, k=1, workers=-1)
        in_region = ~self.ground[nearest]
        whole = _score(xyz, self.xyz, to_full, self.voxel)
        if self._non_ground_tree is None or not in_region.any():
            return {NON_GROUND: _empty_score(int(in_region.sum())), WHOLE: whole}
        region_xyz = xyz[in_region]
        to_region, _ = self._non_ground_tree.query(region_xyz, k=1, workers=-1)
        return {NON_GROUND: _score(region_xyz, self._non_ground, to_region, self.voxel), WHOLE: whole}


def _empty_score(points: int = 0) -> Score:
    return Score(points, math.nan, math.nan, math.nan, 0.0, 0.0, 0.0)


def _score(predicted: np.ndarray, reference: np.ndarray, to_reference: np.ndarray, voxel: float) -> Score:
    """Score of (Q, 3) predicted points against (N, 3) reference points, given the (Q,) distances
    of the predicted points to the reference (already computed for the region split)."""
    from_reference = directed_distances(reference, predicted)
    voxels = voxel_f1(predicted, reference, voxel)
    return Score(points=len(predicted),
                 chamfer=chamfer_from_distances(to_reference, from_reference),
                 hausdorff=hausdorff_from_distances(to_reference, from_reference),
                 hd95=hausdorff_from_distances(to_reference, from_reference, 95.0),
                 precision=voxels.precision, recall=voxels.recall, f1=voxels.f1)


def mean_rows(rows: Iterable[Row]) -> list[Row]:
    """One "mean" row per (method, region): the average of each metric over the scans (NaN
    distances are left out of the averages; point counts are rounded)."""
    groups: dict[tuple[str, str], list[Row]] = {}
    for row in rows:
        groups.setdefault((row.method, row.region), []).append(row)
    means = []
    for (method, region), group in groups.items():
        values = {name: [getattr(r.score, name) for r in group] for name in Score.__dataclass_fields__}
        averaged = {name: _nanmean(column) for name, column in values.items()}
        averaged["points"] = int(round(averaged["points"]))
        means.append(Row("mean", method, region, Score(**averaged), _nanmean([r.seconds for r in group])))
    return means


def _nanmean(values: list[float]) -> float:
    finite = [v for v in values if not math.isnan(v)]
    return float(np.mean(finite)) if finite else math.nan
