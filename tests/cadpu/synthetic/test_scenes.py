"""Tests of the scene types of the simulator (cadpu.synthetic.scenes)."""

from __future__ import annotations

import hashlib

import numpy as np
import pytest

from cadpu.synthetic.lidar import SceneCaster, mount_pose, simulate_scan
from cadpu.synthetic.scenes import LAYOUTS, SCENE_TYPES, foliage, make_scene
from cadpu.synthetic.street import (BUILDING, CAR, FENCE, LANE_HALF_WIDTH, ROAD, SIDEWALK, TERRAIN, VEGETATION,
                                    is_ground, make_street)

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


#: sha256 (as `digest`) of make_scene(TYPE, 3, length_m=40.0) for the types made before
#: "residential": the training caches of those types must not change when a type is added.
SCENE_DIGESTS = {"suburban": "48e4f532a7a60f69fdb3072ac123feab4efb96adec6d4d29a1d8e3590b1a1412",
                 "open": "5fd31b51535dfc43e5d8c490f642b47f564f1bcc3b38cce869944d72df2ae156",
                 "rural": "d9f8af85e523bc10af395cc60b5fbf355e89264b5d70d7412c2b93d8ff5a6d46"}


@pytest.mark.parametrize("scene_type", sorted(SCENE_DIGESTS))
def test_earlier_scene_types_are_unchanged_bit_for_bit(scene_type: str) -> None:
    scene = make_scene(scene_type, 3, length_m=40.0)
    assert digest(scene.vertices, scene.triangles, scene.labels) == SCENE_DIGESTS[scene_type]


def test_urban_scan_is_unchanged(street_scan) -> None:
    scene = make_scene("urban", 1, length_m=60.0, slope=0.03)
    scan = simulate_scan(scene, mount_pose(scene, 5.0), seed=4)
    assert scan.points.tobytes() == street_scan.points.tobytes()
    assert np.array_equal(scan.labels, street_scan.labels) and np.array_equal(scan.ring, street_scan.ring)


def test_unknown_scene_type_and_short_road_are_rejected() -> None:
    with pytest.raises(ValueError, match="unknown scene type 'forest'; known: urban, suburban, open, rural, residential"):
        make_scene("forest", 0)
    with pytest.raises(ValueError, match="length_m"):
        make_scene("open", 0, length_m=-25.0)
    with pytest.raises(ValueError, match="make_scene: seed must be a whole number >= 0, got -1"):
        make_scene("residential", -1)  # numpy's bare "expected non-negative integer"
    with pytest.raises(ValueError, match="make_scene: slope and length_m must be finite, got nan"):
        make_scene("urban", 0, slope=float("nan"))  # a scene of NaN vertices
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


def surface_variation(points: np.ndarray, k: int = 16) -> np.ndarray:
    """(N,) smallest eigenvalue share of the covariance of each point's k nearest neighbours."""
    from scipy.spatial import cKDTree

    _, index = cKDTree(points).query(points, k=k)
    centred = points[index] - points[index].mean(axis=1, keepdims=True)
    eig = np.linalg.eigvalsh(np.einsum("nki,nkj->nij", centred, centred))
    return eig[:, 0] / eig.sum(axis=1)


def test_foliage_returns_scatter_in_depth_and_stop_at_the_core() -> None:
    # Real foliage returns from leaves at random depths (72% of KITTI's vegetation points rough);
    # a closed blob returns from one surface. Beams into a foliage volume must stop within the
    # leaf shell or on the core, and scatter in depth.
    rng = np.random.default_rng(0)
    axes = np.array([2.0, 0.6, 0.9])
    bush = foliage(rng, axes)
    leaves = bush.vertices[bush.triangles[-1]]
    assert np.isclose(np.linalg.norm(leaves[0] - leaves[1]), 0.12)  # a leaf is a 12 cm triangle
    import open3d as o3d

    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(bush.vertices.astype(np.float32)),
                        o3d.core.Tensor(bush.triangles.astype(np.uint32)))
    xs, zs = np.meshgrid(np.linspace(-1.2, 1.2, 60), np.linspace(-0.5, 0.5, 30))
    origins = np.stack([xs.ravel(), np.full(xs.size, -10.0), zs.ravel()], axis=1)
    rays = np.concatenate([origins, np.tile([0.0, 1.0, 0.0], (len(origins), 1))], axis=1).astype(np.float32)
    hit = scene.cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy()
    assert np.isfinite(hit).all()  # nothing passes through the middle of the bush
    y = hit - 10.0
    surface = -axes[1] * np.sqrt(np.clip(1 - (xs.ravel() / axes[0]) ** 2 - (zs.ravel() / axes[2]) ** 2, 0, 1))
    depth = y - surface  # how far past the ellipsoid's surface each beam went
    assert depth.min() > -0.1 and np.percentile(depth, 95) < 0.8
    assert 0.05 < np.median(depth) < 0.4 and depth.std() > 0.05  # in the shell, at random depths


def test_residential_streets_have_hedges_fences_few_cars_and_rough_vegetation() -> None:
    scenes = [make_scene("residential", seed, length_m=40.0) for seed in range(3)]
    assert any(FENCE in scene.labels for scene in scenes)
    cars = sum(int((scene.labels == CAR).sum()) for scene in scenes)
    urban_cars = sum(int((make_scene("urban", seed, length_m=40.0).labels == CAR).sum()) for seed in range(3))
    assert 0 < cars < 0.5 * urban_cars  # 15% of the parking slots taken, against 65%
    scene = make_scene("residential", 3, length_m=60.0, slope=0.0)
    assert {ROAD, SIDEWALK, TERRAIN, VEGETATION, BUILDING} <= set(np.unique(scene.labels).tolist())
    scan = simulate_scan(SceneCaster(scene), mount_pose(scene, 15.0), seed=3)
    near = np.hypot(scan.points[:, 0], scan.points[:, 1]) < 30.0
    vegetation = (scan.labels == VEGETATION) & near
    assert vegetation.mean() > 0.1  # KITTI's scenes: 22-27% vegetation; the urban street about 4%
    rough = surface_variation(scan.points[near, :3].astype(np.float64)) > 0.05
    assert rough[vegetation[near]].mean() > 0.5  # urban's closed blobs: 7-9%
    assert rough[(scan.labels[near] == ROAD)].mean() < 0.05
