"""The default ground method on simulated scenes it was not tuned on (cadpu.synthetic.scenes),
against the simulator's labels, and its growth of ground along a ring."""

from __future__ import annotations

import numpy as np
import pytest

from cadpu.synthetic.lidar import LidarModel, ScanResult, SceneCaster, mount_pose, simulate_scan
from cadpu.synthetic.scenes import make_scene
from cadpu.synthetic.street import SIDEWALK, TERRAIN, VEGETATION, is_ground
from stages import ground
from stages.ground import PatchworkParams
from stages.ground_patchwork import _grow_along_ring


@pytest.fixture(scope="module")
def open_scan() -> ScanResult:
    """A scan 15 m along an open area (seed 1): terrain sloping gently away from the road, seen by
    the clean sensor the figures below were measured with (the measured sensor's 0.8 cm noise,
    against 2 cm, lets the inner ring's plane alone keep 98.9 % of the terrain, 99.9 % with the growth)."""
    scene = make_scene("open", 1, length_m=60.0, slope=0.0)
    return simulate_scan(SceneCaster(scene), mount_pose(scene, 15.0), seed=1, model=LidarModel.clean())


def test_sidewalk_and_terrain_of_an_open_area_are_ground(open_scan: ScanResult) -> None:
    # Sidewalks and terrain 15-30 m out, half of them 0.05-0.3 m above the road. Judged only
    # against the inner ring's plane, extrapolated 5-10 m, 3 % of them were lost (recall 97.3 %,
    # and 96.7 % of the elevated ones, before the growth along the ring of step 5b).
    points, labels = open_scan.points, open_scan.labels
    mask = ground.segment(points).mask
    reach = np.hypot(points[:, 0], points[:, 1])
    beside = np.isin(labels, (SIDEWALK, TERRAIN)) & (reach >= 15.0) & (reach < 30.0)
    rise = points[:, 2] + 1.73
    elevated = beside & (rise > 0.05) & (rise < 0.3)
    assert beside.sum() > 10_000 and elevated.sum() > 5_000
    assert mask[beside].mean() >= 0.99
    assert mask[elevated].mean() >= 0.99
    # ... without taking the objects there: what is labelled ground is ground.
    scored = (reach >= 15.0) & (reach < 30.0) & (labels != VEGETATION)
    truth = is_ground(labels)
    assert (truth & mask)[scored].sum() / mask[scored].sum() >= 0.99


def test_without_growth_along_the_ring_the_open_area_loses_terrain(open_scan: ScanResult) -> None:
    points, labels = open_scan.points, open_scan.labels
    reach = np.hypot(points[:, 0], points[:, 1])
    beside = np.isin(labels, (SIDEWALK, TERRAIN)) & (reach >= 15.0) & (reach < 30.0)
    grown = ground.segment(points, params=PatchworkParams()).mask
    inner_only = ground.segment(points, params=PatchworkParams(neighbour_step=0.0)).mask
    assert inner_only[beside].mean() < grown[beside].mean() - 0.01
    assert not (inner_only & ~grown).any()  # growth only adds ground bins


def level(z: float) -> list[float]:
    return [0.0, 0.0, 1.0, -z]  # the plane z = z


def test_growth_joins_continuous_neighbours_around_the_ring_and_stops_at_a_step() -> None:
    heights = np.array([0.0, 0.1, 0.25, 0.3, 0.9, 0.15, 0.05])
    centre = np.c_[np.zeros(7), np.zeros(7), heights]
    planes = np.array([level(z) for z in heights])
    accepted = np.array([True, False, False, False, False, False, False])
    candidate = np.array([True, True, True, True, True, True, True])
    grown = _grow_along_ring(accepted, candidate, planes, centre, 0.2)
    # 1 (0.1 m) joins 0; 2 (0.25) joins 1; 3 joins 2; 4 is a 0.6 m step; 6 and 5 join around the
    # ring's end (sector 6 neighbours sector 0).
    assert grown.tolist() == [True, True, True, True, False, True, True]
    assert accepted.tolist() == [True] + [False] * 6  # the input is not changed
    not_candidates = _grow_along_ring(accepted, np.array([True, False] + [True] * 5), planes, centre, 0.2)
    assert not_candidates.tolist() == [True, False, False, False, False, True, True]


def test_neighbour_step_is_validated() -> None:
    with pytest.raises(ValueError, match="neighbour_step"):
        PatchworkParams(neighbour_step=-0.1)
    with pytest.raises(ValueError, match="ground.params.neighbour_step"):
        ground.Options(params={"neighbour_step": "high"})


@pytest.fixture(scope="module")
def rural_scan() -> ScanResult:
    """A scan 15 m along a country road (seed 1): a 0.3-0.7 m ditch beside the verge, fields beyond."""
    scene = make_scene("rural", 1, length_m=60.0, slope=0.0)
    return simulate_scan(SceneCaster(scene), mount_pose(scene, 15.0), seed=1)


def test_terrain_beyond_a_ditch_is_ground(rural_scan: ScanResult) -> None:
    # Ring 0 and 1 bins beside the road hold the ditch; their lowest points, and so their planes,
    # are its bottom. Judged against those planes, the fields coming back up beyond the ditch were
    # a step too high, and so was every bin behind them: 39 % of the terrain 10-30 m out was
    # ground before (48 % with the growth along the ring alone), 91 % now that bins beyond a dip
    # may continue the ground from before it (step 5c).
    points, labels = rural_scan.points, rural_scan.labels
    reach = np.hypot(points[:, 0], points[:, 1])
    fields = (labels == TERRAIN) & (reach >= 10.0) & (reach < 30.0)
    assert fields.sum() > 20_000
    mask = ground.segment(points).mask
    assert mask[fields].mean() >= 0.85
    scored = (reach >= 10.0) & (reach < 30.0) & (labels != VEGETATION)
    assert (is_ground(labels) & mask)[scored].sum() / mask[scored].sum() >= 0.99
    no_resume = ground.segment(points, params=PatchworkParams(resume_after_dips=False, reference_uprightness=0.0,
                                                              level_beside_dips=False)).mask
    assert no_resume[fields].mean() < 0.6


def test_the_level_beside_a_ditch_is_ground(rural_scan: ScanResult) -> None:
    # Bins within 15 m hold road, verge and ditch together; their planes are fitted to the ditch's
    # bottom or its steep side, so the road and verge beside it were not ground (80 % recall
    # within 15 m), and a steep side extrapolated outwards rejected the fields behind it. With a
    # second plane at the level the bin was judged against (step 5d), and steep planes not
    # extrapolated (`reference_uprightness`): 95 %, precision unchanged.
    points, labels = rural_scan.points, rural_scan.labels
    reach = np.hypot(points[:, 0], points[:, 1])
    near = (reach < 15.0) & (labels != VEGETATION)
    truth = is_ground(labels)

    def recall_and_precision(params: PatchworkParams) -> tuple[float, float]:
        mask = ground.segment(points, params=params).mask
        hits = (mask & truth)[near].sum()
        return hits / truth[near].sum(), hits / mask[near].sum()

    before = recall_and_precision(PatchworkParams(reference_uprightness=0.0, level_beside_dips=False))
    level_only = recall_and_precision(PatchworkParams(reference_uprightness=0.0))
    now = recall_and_precision(PatchworkParams())
    assert before[0] < 0.85 and level_only[0] >= before[0] + 0.05 and now[0] >= 0.93
    assert now[1] >= 0.99
