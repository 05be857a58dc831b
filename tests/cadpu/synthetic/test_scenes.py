"""Tests of the scene types of the simulator (cadpu.synthetic.scenes)."""

from __future__ import annotations

import hashlib

import numpy as np
import pytest

from cadpu.synthetic.lidar import SceneCaster, mount_pose, simulate_scan
from cadpu.synthetic.scenes import LAYOUTS, SCENE_TYPES, make_scene
from cadpu.synthetic.street import (BUILDING, LANE_HALF_WIDTH, ROAD, SIDEWALK, TERRAIN, VEGETATION, is_ground,
                                    make_street)

#: sha256 of make_street(3, length_m=40.0) (vertices rounded to the micrometre, triangles, labels)
#: as main built it before the scene types existed: the urban scene, and so the training data and
#: every test built on it, must not change.
URBAN_DIGEST = "9cc2cd7f356fa7c8de6d8940307994f423eb371abb5df39feca86ebb8fa4c9f8"


def digest(vertices: np.ndarray, triangles: np.ndarray, labels: np.ndarray) -> str:
    hasher = hashlib.sha256()
    for array in (np.round(vertices, 6), triangles, labels):
        hasher.update(np.ascontiguousarray(array).tobytes())
    return hasher.hexdigest()


@pytest.fixture(scope="module", params=[t for t in SCENE_TYPES if t != "urban"])
def scene_type(request: pytest.FixtureRequest) -> str:
    return request.param


def test_urban_is_the_street_of_before_bit_for_bit() -> None:
    urban = make_scene("urban", 3, length_m=40.0)
    street = make_street(3, length_m=40.0)
    for a, b in ((urban.vertices, street.vertices), (urban.triangles, street.triangles), (urban.labels, street.labels)):
        assert a.dtype == b.dtype and np.array_equal(a, b)
    assert digest(urban.vertices, urban.triangles, urban.labels) == URBAN_DIGEST
    assert make_scene().slope == make_street().slope  # the default type is urban


def test_urban_scan_is_unchanged(street_scan) -> None:
    scene = make_scene("urban", 1, length_m=60.0, slope=0.03)
    scan = simulate_scan(scene, mount_pose(scene, 5.0), seed=4)
    assert scan.points.tobytes() == street_scan.points.tobytes()
    assert np.array_equal(scan.labels, street_scan.labels) and np.array_equal(scan.ring, street_scan.ring)


def test_unknown_scene_type_and_short_road_are_rejected() -> None:
    with pytest.raises(ValueError, match="unknown scene type 'forest'; known: urban, suburban, open, rural"):
        make_scene("forest", 0)
    with pytest.raises(ValueError, match="length_m"):
        make_scene("open", 0, length_m=-25.0)
    assert set(LAYOUTS) == set(SCENE_TYPES) - {"urban"}


def test_same_seed_same_scene_and_types_differ(scene_type: str) -> None:
    a, b = make_scene(scene_type, 7, length_m=30.0), make_scene(scene_type, 7, length_m=30.0)
    assert digest(a.vertices, a.triangles, a.labels) == digest(b.vertices, b.triangles, b.labels)
    other = make_scene(scene_type, 8, length_m=30.0)
    assert digest(a.vertices, a.triangles, a.labels) != digest(other.vertices, other.triangles, other.labels)
    assert a.vertices.dtype == np.float64 and a.triangles.dtype == np.int64 and a.labels.dtype == np.int32
    assert a.triangles.max() < len(a.vertices) and np.isfinite(a.vertices).all()


def test_scene_holds_terrain_vegetation_and_keeps_the_lanes_free(scene_type: str) -> None:
    scene = make_scene(scene_type, 2, length_m=60.0, slope=0.0)
    assert {ROAD, TERRAIN, VEGETATION} <= set(np.unique(scene.labels).tolist())
    objects = ~is_ground(scene.labels)
    vertices = scene.vertices[np.unique(scene.triangles[objects])]
    assert np.all(np.abs(vertices[:, 1]) > LANE_HALF_WIDTH - 0.3)


def test_suburban_has_sidewalks_with_kerbs_and_buildings() -> None:
    scene = make_scene("suburban", 4, length_m=60.0, slope=0.0)
    walk = scene.vertices[np.unique(scene.triangles[scene.labels == SIDEWALK])]
    top = walk[:, 2].max()
    assert 0.12 <= top <= 0.18  # a raised sidewalk behind a 12-18 cm kerb
    assert (scene.labels == BUILDING).any()


def test_rural_road_has_no_kerb_and_a_ditch_beside_it() -> None:
    scene = make_scene("rural", 5, length_m=60.0, slope=0.0)
    assert not (scene.labels == SIDEWALK).any()
    terrain = scene.vertices[np.unique(scene.triangles[scene.labels == TERRAIN])]
    for side in (-1.0, 1.0):
        beside = terrain[(side * terrain[:, 1] > 3.75) & (side * terrain[:, 1] < 3.75 + 5.0)]
        assert beside[:, 2].min() < -0.25  # the ditch, 0.3-0.7 m deep (roughness aside)
        assert np.abs(beside[side * beside[:, 1] < 4.5, 2]).max() < 0.2  # the verge, near road level


def test_open_area_seen_by_the_sensor_is_ground_a_little_above_the_road() -> None:
    # The phenomenon the scene type is for: 15-30 m out, beside the road, ground-like surfaces
    # (sidewalks, terrain) about 0.1-0.2 m above the road, next to rough low vegetation.
    scene = make_scene("open", 1, length_m=60.0, slope=0.0)
    scan = simulate_scan(SceneCaster(scene), mount_pose(scene, 15.0), seed=1)
    reach = np.hypot(scan.points[:, 0], scan.points[:, 1])
    band = (reach >= 15.0) & (reach < 30.0)
    beside = np.isin(scan.labels, (SIDEWALK, TERRAIN)) & band
    rise = scan.points[beside, 2] + 1.73
    assert beside.sum() > 5000
    assert 0.05 < np.median(rise) < 0.4
    assert (scan.labels[band] == VEGETATION).sum() > 200
    assert (scan.labels[band] == ROAD).sum() > 1000
