"""A procedural street scene as labelled triangles (pure numpy, deterministic per seed).

World frame: x along the street, y to the left, z up, metres. The road surface is the plane
z = slope * x (a gentle climb); the street runs from x = -30 to x = `length_m`. Across the street
(y), from the centre out on each side: two driving lanes of 3.5 m in all, a 2 m parking lane,
a 15 cm kerb, a 3 m sidewalk, then building facades.

The scene holds:
- road (one flat slab) and, on both sides, sidewalks whose road-facing side is the kerb;
- building facades with relief: windows recessed 15 cm behind the wall, doors recessed 30 cm,
  a plinth, varying widths and heights and gaps between buildings;
- parked cars in the parking lanes (rounded lower body, narrower cabin, wheels);
- poles at the kerb with lamp or sign heads;
- vegetation: bushes against the facades and trees (trunk + crown), both displaced icospheres.

The driving lanes (|y| < `LANE_HALF_WIDTH`) are kept free, so a sensor driven along them never
sits inside an object.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .shapes import Mesh, merge, prism, rotation_z, superquadric
from .shapes import box as _box

ROAD, SIDEWALK, BUILDING, CAR, POLE, VEGETATION, TRUNK, TERRAIN, FENCE = range(9)
CLASS_NAMES = ("road", "sidewalk", "building", "car", "pole", "vegetation", "trunk", "terrain", "fence")
#: Classes that count as ground (what a vehicle could drive or walk on); the kerb is SIDEWALK.
#: TERRAIN (grass, soil) appears in the other scene types of `cadpu.synthetic.scenes`, and so does
#: FENCE (not ground), in the residential one.
GROUND_CLASSES = (ROAD, SIDEWALK, TERRAIN)
#: Base (normal-incidence) reflectance of each class, in KITTI's [0, 1] reflectance scale.
REFLECTIVITY = np.array([0.22, 0.30, 0.35, 0.55, 0.45, 0.20, 0.25, 0.28, 0.30])
#: The SemanticKITTI class id of each class (road 40, sidewalk 48, building 50, car 10, pole 80,
#: vegetation 70, trunk 71, terrain 72, fence 51), so simulated labels score like SemanticKITTI's.
SEMANTIC_KITTI = np.array([40, 48, 50, 10, 80, 70, 71, 72, 51], dtype=np.uint32)

LANE_HALF_WIDTH = 3.5  # two driving lanes of 3.5 m
PARKING_WIDTH = 2.0
ROAD_HALF_WIDTH = LANE_HALF_WIDTH + PARKING_WIDTH
KERB_HEIGHT = 0.15
SIDEWALK_WIDTH = 3.0
STREET_START = -30.0
SLAB = 0.3  # thickness of road and sidewalk slabs below their top surfaces


@dataclass(frozen=True)
class Scene:
    """Labelled triangles in the world frame (metres, z up).

    Attributes:
        vertices: (V, 3) float64 vertex positions.
        triangles: (T, 3) int64 vertex indices, counter-clockwise seen from outside.
        labels: (T,) int32 semantic class per triangle (ROAD, SIDEWALK, ... of this module).
        slope: road gradient dz/dx; the road surface is z = slope * x.
    """

    vertices: np.ndarray
    triangles: np.ndarray
    labels: np.ndarray
    slope: float = 0.0


def ground_labels() -> tuple[int, ...]:
    """The semantic classes that count as ground: (ROAD, SIDEWALK, TERRAIN); the kerb is part of
    SIDEWALK."""
    return GROUND_CLASSES


def is_ground(labels: np.ndarray) -> np.ndarray:
    """(N,) bool: True where the (N,) semantic labels are a ground class (see `ground_labels`)."""
    return np.isin(labels, GROUND_CLASSES)


def make_street(seed: int = 0, length_m: float = 120.0, slope: float = 0.02) -> Scene:
    """Build the street of `seed` (layout in the module docstring).

    Args:
        seed: layout seed; the same seed always gives the same scene, bit for bit.
        length_m: the street runs from x = -30 m to x = `length_m` (must exceed -30 + 10).
        slope: road gradient dz/dx (0.02 = 2 %), applied to the whole scene.

    Returns:
        The `Scene` (world frame, metres).
    """
    if length_m <= STREET_START + 10.0:
        raise ValueError(f"make_street: length_m must be above {STREET_START + 10.0} m, got {length_m}")
    rng = np.random.default_rng(seed)
    span = length_m - STREET_START
    centre_x = (STREET_START + length_m) / 2
    parts: list[tuple[Mesh, int]] = [(_box((span, 2 * ROAD_HALF_WIDTH, SLAB), (centre_x, 0.0, -SLAB / 2)), ROAD)]
    for side in (-1.0, 1.0):
        parts += _sidewalk(side, span, centre_x)
        parts += _buildings(rng, side, length_m)
        parts += _parked_cars(rng, side, length_m)
        parts += _poles(rng, side, length_m)
        parts += _vegetation(rng, side, length_m)
    scene = _labelled(parts)
    vertices = scene.vertices.copy()
    vertices[:, 2] += slope * vertices[:, 0]
    return Scene(vertices, scene.triangles, scene.labels, float(slope))


def _labelled(parts: list[tuple[Mesh, int]]) -> Scene:
    """Merge (mesh, class) pairs into one `Scene`."""
    mesh = merge([m for m, _ in parts])
    labels = np.concatenate([np.full(len(m.triangles), label, dtype=np.int32) for m, label in parts])
    return Scene(mesh.vertices.astype(np.float64), mesh.triangles.astype(np.int64), labels)


def _facing(side: float) -> np.ndarray:
    """Rotation turning an object built to face -y (the street, for the left side) to face the
    street from `side` (+1 left, -1 right)."""
    return rotation_z(0.0 if side > 0 else np.pi)


def _sidewalk(side: float, span: float, centre_x: float) -> list[tuple[Mesh, int]]:
    """The sidewalk slab of one side; its road-facing face is the 15 cm kerb."""
    y = side * (ROAD_HALF_WIDTH + SIDEWALK_WIDTH / 2)
    height = SLAB + KERB_HEIGHT
    return [(_box((span, SIDEWALK_WIDTH, height), (centre_x, y, KERB_HEIGHT - height / 2)), SIDEWALK)]


def _buildings(rng: np.random.Generator, side: float, length_m: float) -> list[tuple[Mesh, int]]:
    """A row of facades along one side, with gaps between buildings."""
    parts = []
    facade_y = side * (ROAD_HALF_WIDTH + SIDEWALK_WIDTH)
    x = STREET_START
    while x < length_m:
        width = rng.uniform(8.0, 18.0)
        house = facade(rng, width).transformed(_facing(side), 1.0, (x + width / 2, facade_y, 0.0))
        parts.append((house, BUILDING))
        x += width + (rng.uniform(2.0, 5.0) if rng.random() < 0.4 else 0.0)
    return parts


def facade(rng: np.random.Generator, width: float) -> Mesh:
    """A building of `width` (m) whose front is the plane y = 0, facing -y, standing on z = 0.

    Three layers: the body behind y = 0.30; a glass layer (0.15 < y < 0.30) everywhere but the door
    opening; a front wall (0 < y < 0.15) of piers and horizontal bands around the window and door
    openings. So windows are recessed 15 cm and the door 30 cm; a plinth stands out 5 cm.
    """
    height = rng.uniform(6.0, 14.0)
    depth = 8.0
    recess, door_recess = 0.15, 0.30
    columns = max(1, int(width // 2.8))
    pitch = width / columns
    window_w = min(1.4, pitch - 0.6)
    door_col = int(rng.integers(columns))
    door_w, door_h = min(1.2, pitch - 0.4), 2.3
    door_x = -width / 2 + (door_col + 0.5) * pitch
    glass = door_recess - recess
    parts = [_box((width, depth, height), (0.0, door_recess + depth / 2, height / 2))]
    left, right = door_x - door_w / 2, door_x + door_w / 2
    for x0, x1, z0, z1 in ((-width / 2, left, 0.0, height), (right, width / 2, 0.0, height), (left, right, door_h, height)):
        parts.append(_box((x1 - x0, glass, z1 - z0), ((x0 + x1) / 2, recess + glass / 2, (z0 + z1) / 2)))
    for col in range(columns):
        x0 = -width / 2 + col * pitch
        opening_w = door_w if col == door_col else window_w
        pier = (pitch - opening_w) / 2
        for px in (x0 + pier / 2, x0 + pitch - pier / 2):
            parts.append(_box((pier, recess, height), (px, recess / 2, height / 2)))
        for z0, z1 in _column_bands(height, 3.0, 0.9, 1.5, door_h if col == door_col else None):
            parts.append(_box((opening_w, recess, z1 - z0), (x0 + pitch / 2, recess / 2, (z0 + z1) / 2)))
    parts.append(_box((width, 0.05, 0.4), (0.0, -0.025, 0.2)))  # plinth
    return merge(parts)


def _column_bands(height: float, storey: float, sill: float, window_h: float,
                  door_h: float | None) -> list[tuple[float, float]]:
    """Solid (z0, z1) wall bands of one facade column: everything but the window openings of each
    storey (and the door opening at ground level when `door_h` is given)."""
    openings = []
    storeys = max(1, int(height // storey))
    for level in range(storeys):
        base = level * storey
        if level == 0 and door_h is not None:
            openings.append((0.0, door_h))
        elif base + sill + window_h < height - 0.3:
            openings.append((base + sill, base + sill + window_h))
    bands, z = [], 0.0
    for z0, z1 in openings:
        if z0 > z:
            bands.append((z, z0))
        z = z1
    if z < height:
        bands.append((z, height))
    return bands


def _parked_cars(rng: np.random.Generator, side: float, length_m: float,
                 occupancy: float = 0.65) -> list[tuple[Mesh, int]]:
    """Cars parked in the parking lane of one side, bumper to bumper with random gaps: each 5.5-8 m
    slot holds a car with probability `occupancy`."""
    parts = []
    y = side * (LANE_HALF_WIDTH + PARKING_WIDTH / 2)
    x = STREET_START + rng.uniform(0.0, 6.0)
    while x < length_m - 3.0:
        if rng.random() < occupancy:
            heading = rng.normal(scale=0.03) + (0.0 if rng.random() < 0.5 else np.pi)
            kerb_offset = side * rng.uniform(-0.1, 0.15)  # parked up to 10 cm out, 15 cm in
            car = parked_car(rng).transformed(rotation_z(heading), 1.0, (x, y + kerb_offset, 0.0))
            parts.append((car, CAR))
        x += rng.uniform(5.5, 8.0)
    return parts


def parked_car(rng: np.random.Generator) -> Mesh:
    """A car standing on z = 0, length along x: a rounded lower body 0.3-1.0 m high, a narrower
    and shorter cabin on top (roof at about 1.45 m) and four wheels; about 2,600 triangles."""
    length, width = rng.uniform(3.8, 4.9), rng.uniform(1.65, 1.9)
    body = superquadric(0.25, 0.2, (length / 2, width / 2, 0.35), resolution=28).transformed(
        np.eye(3), 1.0, (0.0, 0.0, 0.65))
    cabin_length = length * rng.uniform(0.5, 0.6)
    cabin = superquadric(0.35, 0.3, (cabin_length / 2, width * 0.44, 0.3), resolution=24).transformed(
        np.eye(3), 1.0, (-length * rng.uniform(0.0, 0.08), 0.0, 1.15))
    axle = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])  # cylinder axis z -> y
    wheels = [prism(16, 0.32, 0.2).transformed(axle, 1.0, (x, y, 0.32))
              for x in (-length * 0.32, length * 0.32) for y in (-width / 2 + 0.08, width / 2 - 0.08)]
    return merge([body, cabin, *wheels])


def _poles(rng: np.random.Generator, side: float, length_m: float) -> list[tuple[Mesh, int]]:
    """Lamp posts and sign posts standing on the sidewalk 0.5 m behind the kerb."""
    parts = []
    y = side * (ROAD_HALF_WIDTH + 0.5)
    x = STREET_START + rng.uniform(0.0, 10.0)
    while x < length_m:
        parts.append((street_pole(rng).transformed(_facing(side), 1.0, (x, y, KERB_HEIGHT)), POLE))
        x += rng.uniform(12.0, 22.0)
    return parts


def street_pole(rng: np.random.Generator) -> Mesh:
    """A pole standing on z = 0, its head reaching over -y: a lamp (arm + rounded head, 5-8 m) or a
    sign (square or round plate, 2.5-3.5 m)."""
    if rng.random() < 0.5:
        height = rng.uniform(5.0, 8.0)
        radius = rng.uniform(0.07, 0.12)
        shaft = prism(20, radius, height, taper=0.7).transformed(np.eye(3), 1.0, (0, 0, height / 2))
        arm = _box((0.06, 1.2, 0.06), (0.0, -0.6, height - 0.03))
        head = icosphere(2).transformed(np.eye(3), np.array([0.2, 0.35, 0.1]), (0.0, -1.2, height - 0.1))
        return merge([shaft, arm, head])
    height = rng.uniform(2.5, 3.5)
    shaft = prism(16, 0.04, height).transformed(np.eye(3), 1.0, (0, 0, height / 2))
    if rng.random() < 0.5:
        plate = _box((0.6, 0.03, 0.6), (0.0, -0.06, height - 0.35))
    else:
        plate = prism(20, 0.3, 0.03).transformed(np.array([[1, 0, 0], [0, 0, 1], [0, -1, 0.0]]), 1.0,
                                                 (0.0, -0.06, height - 0.35))
    return merge([shaft, plate])


def _vegetation(rng: np.random.Generator, side: float, length_m: float) -> list[tuple[Mesh, int]]:
    """Bushes against the facades and trees on the sidewalk between poles."""
    parts = []
    x = STREET_START + rng.uniform(0.0, 8.0)
    while x < length_m:
        radius = rng.uniform(0.5, 1.1)
        y = side * (ROAD_HALF_WIDTH + SIDEWALK_WIDTH - radius * 0.7)
        shape = np.array([rng.uniform(1.0, 2.0), 1.0, rng.uniform(0.7, 1.0)]) * radius
        parts.append((displaced_icosphere(rng).transformed(np.eye(3), shape, (x, y, KERB_HEIGHT + shape[2] * 0.6)),
                      VEGETATION))
        x += rng.uniform(6.0, 14.0)
    x = STREET_START + rng.uniform(0.0, 12.0)
    while x < length_m:
        trunk_h = rng.uniform(2.0, 3.0)
        crown = rng.uniform(1.5, 2.5)
        y = side * (ROAD_HALF_WIDTH + 1.2)
        trunk = prism(12, rng.uniform(0.12, 0.2), trunk_h + crown * 0.5).transformed(
            np.eye(3), 1.0, (x, y, KERB_HEIGHT + (trunk_h + crown * 0.5) / 2))
        top = displaced_icosphere(rng).transformed(np.eye(3), np.array([1.0, 1.0, 0.85]) * crown,
                                                   (x, y, KERB_HEIGHT + trunk_h + crown * 0.8))
        parts += [(trunk, TRUNK), (top, VEGETATION)]
        x += rng.uniform(14.0, 26.0)
    return parts


def icosphere(subdivisions: int = 2) -> Mesh:
    """Unit sphere from an icosahedron whose faces are split in four `subdivisions` times
    (20 * 4**subdivisions triangles, counter-clockwise outward)."""
    t = (1.0 + 5 ** 0.5) / 2
    vertices = np.array([[-1, t, 0], [1, t, 0], [-1, -t, 0], [1, -t, 0], [0, -1, t], [0, 1, t],
                         [0, -1, -t], [0, 1, -t], [t, 0, -1], [t, 0, 1], [-t, 0, -1], [-t, 0, 1]], dtype=np.float64)
    faces = np.array([[0, 11, 5], [0, 5, 1], [0, 1, 7], [0, 7, 10], [0, 10, 11], [1, 5, 9], [5, 11, 4],
                      [11, 10, 2], [10, 7, 6], [7, 1, 8], [3, 9, 4], [3, 4, 2], [3, 2, 6], [3, 6, 8],
                      [3, 8, 9], [4, 9, 5], [2, 4, 11], [6, 2, 10], [8, 6, 7], [9, 8, 1]], dtype=np.int64)
    for _ in range(subdivisions):
        vertices, faces = _subdivide(vertices, faces)
    return Mesh(vertices / np.linalg.norm(vertices, axis=1, keepdims=True), faces)


def _subdivide(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Split every triangle into four through its edge midpoints (midpoints shared between faces)."""
    edges = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    unique, inverse = np.unique(np.sort(edges, axis=1), axis=0, return_inverse=True)
    midpoints = (vertices[unique[:, 0]] + vertices[unique[:, 1]]) / 2
    mid = inverse.reshape(3, -1) + len(vertices)  # midpoint index of edges 01, 12, 20 per face
    a, b, c = faces.T
    ab, bc, ca = mid
    new_faces = np.concatenate([np.stack(f, 1) for f in ((a, ab, ca), (b, bc, ab), (c, ca, bc), (ab, bc, ca))])
    return np.concatenate([vertices, midpoints]), new_faces


def displaced_icosphere(rng: np.random.Generator, subdivisions: int = 3) -> Mesh:
    """A foliage-like blob about the unit sphere: an icosphere whose radius varies with a few
    random low-frequency waves (lobes) plus fine random roughness (leaves), radius about 0.7-1.3."""
    sphere = icosphere(subdivisions)
    directions = sphere.vertices
    waves = rng.normal(size=(5, 3)) * 1.5
    phases = rng.uniform(0.0, 2 * np.pi, 5)
    lobes = (rng.uniform(0.04, 0.12, 5) * np.sin(directions @ waves.T + phases)).sum(axis=1)
    roughness = rng.normal(scale=0.04, size=len(directions))
    return Mesh(directions * (1.0 + lobes + roughness)[:, None], sphere.triangles)
