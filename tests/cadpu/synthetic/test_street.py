"""Tests of the procedural street scene (cadpu.synthetic.street)."""

from __future__ import annotations

import numpy as np
import pytest

from cadpu.synthetic import street
from cadpu.synthetic.street import (BUILDING, CAR, GROUND_CLASSES, KERB_HEIGHT, LANE_HALF_WIDTH, POLE, ROAD, SIDEWALK,
                          TERRAIN, VEGETATION, displaced_icosphere, facade, ground_labels, icosphere, is_ground,
                          make_street)


@pytest.fixture(scope="module")
def scene() -> street.Scene:
    return make_street(3, length_m=40.0)


def test_same_seed_same_scene_and_other_seed_differs() -> None:
    a, b, c = make_street(7, length_m=30.0), make_street(7, length_m=30.0), make_street(8, length_m=30.0)
    assert np.array_equal(a.vertices, b.vertices)
    assert np.array_equal(a.triangles, b.triangles)
    assert np.array_equal(a.labels, b.labels)
    assert a.vertices.shape != c.vertices.shape or not np.array_equal(a.vertices, c.vertices)


def test_arrays_have_documented_shapes_and_types(scene: street.Scene) -> None:
    assert scene.vertices.ndim == 2 and scene.vertices.shape[1] == 3 and scene.vertices.dtype == np.float64
    assert scene.triangles.shape[1] == 3 and scene.triangles.dtype == np.int64
    assert scene.labels.shape == (len(scene.triangles),) and scene.labels.dtype == np.int32
    assert scene.triangles.min() >= 0 and scene.triangles.max() < len(scene.vertices)
    assert np.all(np.isfinite(scene.vertices))


def test_scene_holds_every_street_class(scene: street.Scene) -> None:
    present = set(np.unique(scene.labels).tolist())
    assert {ROAD, SIDEWALK, BUILDING, CAR, POLE, VEGETATION} <= present


def test_road_follows_the_slope_and_sidewalk_top_is_a_kerb_above_it() -> None:
    scene = make_street(0, length_m=40.0, slope=0.05)
    assert scene.slope == 0.05
    road = scene.vertices[np.unique(scene.triangles[scene.labels == ROAD])]
    top = road[road[:, 2] > 0.05 * road[:, 0] - 0.01]
    assert len(top) >= 4
    assert np.allclose(top[:, 2], 0.05 * top[:, 0], atol=1e-9)
    walk = scene.vertices[np.unique(scene.triangles[scene.labels == SIDEWALK])]
    heights = np.round(walk[:, 2] - 0.05 * walk[:, 0], 6)
    assert heights.max() == pytest.approx(KERB_HEIGHT)


def test_driving_lanes_are_free_of_objects(scene: street.Scene) -> None:
    objects = ~is_ground(scene.labels)
    vertices = scene.vertices[np.unique(scene.triangles[objects])]
    assert np.all(np.abs(vertices[:, 1]) > LANE_HALF_WIDTH - 0.3)


def test_ground_labels_are_road_sidewalk_and_terrain() -> None:
    assert set(ground_labels()) == {ROAD, SIDEWALK, TERRAIN} == set(GROUND_CLASSES)
    labels = np.array([ROAD, SIDEWALK, BUILDING, CAR, POLE, VEGETATION, TERRAIN])
    assert is_ground(labels).tolist() == [True, True, False, False, False, False, True]


def test_every_class_has_a_name_a_reflectivity_and_a_semantic_kitti_id() -> None:
    assert len(street.CLASS_NAMES) == len(street.REFLECTIVITY) == len(street.SEMANTIC_KITTI) == street.FENCE + 1
    assert street.SEMANTIC_KITTI[[ROAD, SIDEWALK, TERRAIN, VEGETATION, street.FENCE]].tolist() == [40, 48, 72, 70, 51]
    assert not is_ground(np.array([street.FENCE]))[0]


def test_icosphere_is_a_closed_unit_sphere() -> None:
    sphere = icosphere(2)
    assert sphere.triangles.shape == (320, 3)
    assert np.allclose(np.linalg.norm(sphere.vertices, axis=1), 1.0)
    edges = np.sort(np.concatenate([sphere.triangles[:, [0, 1]], sphere.triangles[:, [1, 2]],
                                    sphere.triangles[:, [2, 0]]]), axis=1)
    _, counts = np.unique(edges, axis=0, return_counts=True)
    assert np.all(counts == 2)  # every edge shared by two faces: watertight
    centroids = sphere.vertices[sphere.triangles].mean(axis=1)
    a, b, c = (sphere.vertices[sphere.triangles[:, i]] for i in range(3))
    assert np.all((np.cross(b - a, c - a) * centroids).sum(axis=1) > 0)  # outward winding


def test_displaced_icosphere_is_bumpy_but_bounded() -> None:
    radius = np.linalg.norm(displaced_icosphere(np.random.default_rng(1)).vertices, axis=1)
    assert radius.std() > 0.03
    assert 0.5 < radius.min() and radius.max() < 1.6


def test_facade_has_recessed_windows_and_door() -> None:
    # Rays shot straight at the front (+y) on a grid: the depth at which they first meet the
    # facade shows its relief.
    from cadpu.synthetic.lidar import SceneCaster

    mesh = facade(np.random.default_rng(0), 12.0)
    caster = SceneCaster(street.Scene(mesh.vertices, mesh.triangles, np.zeros(len(mesh.triangles), np.int32)))
    x, z = np.meshgrid(np.linspace(-5.9, 5.9, 120), np.linspace(0.05, 5.9, 60))
    origins = np.stack([x.ravel(), np.full(x.size, -1.0), z.ravel()], axis=1)
    distance, _, _ = caster.cast(origins, np.tile([0.0, 1.0, 0.0], (x.size, 1)))
    depth = np.round(distance - 1.0, 3)
    fractions = {d: np.mean(depth == d) for d in (-0.05, 0.0, 0.15, 0.3)}
    assert fractions[0.0] > 0.4  # wall
    assert fractions[0.15] > 0.05  # window openings, 15 cm deep
    assert fractions[0.3] > 0.002  # the door, 30 cm deep
    assert fractions[-0.05] > 0.02  # plinth
    assert sum(fractions.values()) == pytest.approx(1.0)


def test_too_short_street_is_rejected() -> None:
    with pytest.raises(ValueError, match="length_m"):
        make_street(0, length_m=-25.0)
