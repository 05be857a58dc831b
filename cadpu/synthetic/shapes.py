"""Procedural triangle meshes for training and testing CAD-PU (pure numpy, deterministic per seed).

A mesh is a `Mesh(vertices (V, 3) float64, triangles (T, 3) int64)`. Families:
smooth closed shapes, shapes with sharp edges and flat faces, thin parts, compositions of several
parts, and street-scene objects (car-like bodies, poles, walls and facades, kerbs).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Mesh:
    """A triangle mesh: vertices (V, 3) float64, triangles (T, 3) int64 (counter-clockwise outward)."""

    vertices: np.ndarray
    triangles: np.ndarray

    def transformed(self, rotation: np.ndarray, scale: np.ndarray | float = 1.0,
                    offset: np.ndarray | float = 0.0) -> "Mesh":
        """The mesh with vertices mapped to (v * scale) @ rotation.T + offset."""
        return Mesh((self.vertices * scale) @ rotation.T + offset, self.triangles)

    def triangle_areas(self) -> np.ndarray:
        """(T,) triangle areas."""
        a, b, c = (self.vertices[self.triangles[:, i]] for i in range(3))
        return 0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=1)


def merge(meshes: list[Mesh]) -> Mesh:
    """One mesh holding all triangles of `meshes`."""
    vertices, triangles, offset = [], [], 0
    for mesh in meshes:
        vertices.append(mesh.vertices)
        triangles.append(mesh.triangles + offset)
        offset += len(mesh.vertices)
    return Mesh(np.concatenate(vertices), np.concatenate(triangles))


def sample_surface(mesh: Mesh, count: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Uniform random points on the mesh surface (area-weighted) and their face normals.

    Returns:
        points (count, 3) float64, normals (count, 3) float64 unit vectors.
    """
    areas = mesh.triangle_areas()
    face = rng.choice(len(areas), size=count, p=areas / areas.sum())
    u, v = rng.random(count), rng.random(count)
    flip = u + v > 1.0
    u[flip], v[flip] = 1.0 - u[flip], 1.0 - v[flip]
    a, b, c = (mesh.vertices[mesh.triangles[face, i]] for i in range(3))
    points = a + u[:, None] * (b - a) + v[:, None] * (c - a)
    normals = np.cross(b - a, c - a)
    normals /= np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-12)
    return points, normals


def random_rotation(rng: np.random.Generator) -> np.ndarray:
    """A uniformly random 3x3 rotation matrix."""
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q *= np.sign(np.diag(r))
    if np.linalg.det(q) < 0:
        q[:, 0] *= -1
    return q


def rotation_z(angle: float) -> np.ndarray:
    """Rotation by `angle` radians about z."""
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


# --- primitives ---------------------------------------------------------------------------


def grid_surface(function: Callable[[np.ndarray, np.ndarray], np.ndarray], rows: int, cols: int,
                 wrap_u: bool, wrap_v: bool) -> Mesh:
    """Mesh of a parametric surface f(u, v) -> (..., 3) on [0, 1]^2 with optional wrap-around."""
    u = np.linspace(0.0, 1.0, rows, endpoint=not wrap_u)
    v = np.linspace(0.0, 1.0, cols, endpoint=not wrap_v)
    uu, vv = np.meshgrid(u, v, indexing="ij")
    vertices = function(uu, vv).reshape(-1, 3)
    i, j = np.meshgrid(np.arange(rows if wrap_u else rows - 1), np.arange(cols if wrap_v else cols - 1),
                       indexing="ij")
    i, j = i.ravel(), j.ravel()
    i1, j1 = (i + 1) % rows, (j + 1) % cols
    a, b, c, d = i * cols + j, i1 * cols + j, i1 * cols + j1, i * cols + j1
    return Mesh(vertices, np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)]))


def superquadric(exponent_a: float, exponent_b: float, radii: tuple[float, float, float],
                 resolution: int = 48) -> Mesh:
    """Superellipsoid: exponent 1 = ellipsoid, small = box-like with rounded edges."""

    def signed_power(x: np.ndarray, e: float) -> np.ndarray:
        return np.sign(x) * np.abs(x) ** e

    def surface(u: np.ndarray, v: np.ndarray) -> np.ndarray:
        theta = (u - 0.5) * np.pi * 0.999
        phi = v * 2 * np.pi
        x = signed_power(np.cos(theta), exponent_a) * signed_power(np.cos(phi), exponent_b)
        y = signed_power(np.cos(theta), exponent_a) * signed_power(np.sin(phi), exponent_b)
        z = signed_power(np.sin(theta), exponent_a)
        return np.stack([x, y, z], -1) * np.asarray(radii)

    return grid_surface(surface, resolution, resolution, wrap_u=False, wrap_v=True)


def blob(rng: np.random.Generator, resolution: int = 48) -> Mesh:
    """A smooth closed shape: a sphere with a few low-frequency radial bumps."""
    waves = rng.normal(size=(4, 3))
    amplitude = rng.uniform(0.05, 0.25, size=4)

    def surface(u: np.ndarray, v: np.ndarray) -> np.ndarray:
        theta = (u - 0.5) * np.pi * 0.999
        phi = v * 2 * np.pi
        direction = np.stack([np.cos(theta) * np.cos(phi), np.cos(theta) * np.sin(phi), np.sin(theta)], -1)
        radius = 1.0 + sum(a * np.sin(direction @ w * 2.0) for a, w in zip(amplitude, waves))
        return direction * radius[..., None]

    return grid_surface(surface, resolution, resolution, wrap_u=False, wrap_v=True)


def torus(major: float, minor: float, resolution: int = 48) -> Mesh:
    """Torus about z."""

    def surface(u: np.ndarray, v: np.ndarray) -> np.ndarray:
        a, b = u * 2 * np.pi, v * 2 * np.pi
        ring = major + minor * np.cos(b)
        return np.stack([ring * np.cos(a), ring * np.sin(a), minor * np.sin(b)], -1)

    return grid_surface(surface, resolution, resolution // 2, wrap_u=True, wrap_v=True)


def box(size: tuple[float, float, float], centre: tuple[float, float, float] = (0.0, 0.0, 0.0)) -> Mesh:
    """Axis-aligned box with 12 triangles."""
    corners = np.array([[x, y, z] for x in (-0.5, 0.5) for y in (-0.5, 0.5) for z in (-0.5, 0.5)])
    faces = np.array([[0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5], [0, 4, 5], [0, 5, 1],
                      [2, 3, 7], [2, 7, 6], [0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3]])
    return Mesh(corners * np.asarray(size) + np.asarray(centre), faces)


def prism(sides: int, radius: float, height: float, taper: float = 1.0) -> Mesh:
    """Closed n-gon prism about z (taper < 1 narrows the top; sides >= 24 approximates a cylinder,
    taper 0 a cone)."""
    angles = np.linspace(0.0, 2 * np.pi, sides, endpoint=False)
    ring = np.stack([np.cos(angles), np.sin(angles)], 1)
    bottom = np.c_[ring * radius, np.full(sides, -height / 2)]
    top = np.c_[ring * radius * max(taper, 1e-3), np.full(sides, height / 2)]
    vertices = np.concatenate([bottom, top, [[0, 0, -height / 2], [0, 0, height / 2]]])
    i = np.arange(sides)
    j = (i + 1) % sides
    sides_faces = np.concatenate([np.stack([i, j, j + sides], 1), np.stack([i, j + sides, i + sides], 1)])
    caps = np.concatenate([np.stack([np.full(sides, 2 * sides), j, i], 1),
                           np.stack([np.full(sides, 2 * sides + 1), i + sides, j + sides], 1)])
    return Mesh(vertices, np.concatenate([sides_faces, caps]))


# --- families -----------------------------------------------------------------------------


def smooth_shape(rng: np.random.Generator) -> Mesh:
    """Ellipsoids, blobs and tori."""
    kind = rng.integers(3)
    if kind == 0:
        return superquadric(1.0, 1.0, tuple(rng.uniform(0.4, 1.0, 3)))
    if kind == 1:
        return blob(rng)
    return torus(1.0, rng.uniform(0.25, 0.5))


def sharp_shape(rng: np.random.Generator) -> Mesh:
    """Boxes, prisms, cones, cylinders and rounded boxes: sharp edges and flat faces."""
    kind = rng.integers(4)
    if kind == 0:
        return box(tuple(rng.uniform(0.3, 1.0, 3)))
    if kind == 1:
        return prism(int(rng.integers(3, 9)), rng.uniform(0.4, 0.8), rng.uniform(0.4, 1.5),
                     taper=rng.uniform(0.3, 1.0))
    if kind == 2:
        return prism(32, rng.uniform(0.3, 0.7), rng.uniform(0.5, 1.5), taper=rng.choice([0.0, 1.0]))
    return superquadric(rng.uniform(0.15, 0.4), rng.uniform(0.15, 0.4), tuple(rng.uniform(0.4, 1.0, 3)))


def thin_shape(rng: np.random.Generator) -> Mesh:
    """Plates, rods and thin rings."""
    kind = rng.integers(3)
    if kind == 0:
        return box((rng.uniform(0.6, 1.2), rng.uniform(0.6, 1.2), rng.uniform(0.03, 0.08)))
    if kind == 1:
        return prism(16, rng.uniform(0.04, 0.1), rng.uniform(1.0, 2.0))
    return torus(1.0, rng.uniform(0.06, 0.12))


def composition(rng: np.random.Generator) -> Mesh:
    """Two to four parts of the other families, placed next to and into each other."""
    parts = []
    for _ in range(int(rng.integers(2, 5))):
        family = [smooth_shape, sharp_shape, thin_shape][int(rng.integers(3))]
        part = family(rng)
        parts.append(part.transformed(random_rotation(rng), rng.uniform(0.3, 0.6), rng.uniform(-0.5, 0.5, 3)))
    return merge(parts)


def car_body(rng: np.random.Generator) -> Mesh:
    """A car-like body: rounded lower body, narrower cabin, four wheels (metres, z up)."""
    length, width = rng.uniform(3.8, 4.8), rng.uniform(1.6, 1.9)
    body = superquadric(0.3, 0.2, (length / 2, width / 2, 0.35)).transformed(np.eye(3), 1.0, (0, 0, 0.65))
    cabin = superquadric(0.4, 0.3, (length * 0.28, width * 0.45, 0.3)).transformed(
        np.eye(3), 1.0, (-0.2, 0, 1.15))
    wheels = []
    for x in (-length * 0.32, length * 0.32):
        for y in (-width / 2, width / 2):
            wheel = prism(24, 0.33, 0.22).transformed(np.array([[1, 0, 0], [0, 0, -1], [0, 1, 0.0]]),
                                                     1.0, (x, y, 0.33))
            wheels.append(wheel)
    return merge([body, cabin, *wheels])


def pole(rng: np.random.Generator) -> Mesh:
    """A pole with a lamp or sign head."""
    height = rng.uniform(3.0, 6.0)
    shaft = prism(24, rng.uniform(0.05, 0.12), height).transformed(np.eye(3), 1.0, (0, 0, height / 2))
    if rng.random() < 0.5:
        head = box((0.05, 0.7, 0.7), (0.1, 0, height - 0.5))
    else:
        head = superquadric(0.6, 1.0, (0.4, 0.15, 0.1)).transformed(np.eye(3), 1.0, (0.3, 0, height))
    return merge([shaft, head])


def facade(rng: np.random.Generator) -> Mesh:
    """A wall with window frames standing out of it and a recessed door."""
    width, height = rng.uniform(6.0, 12.0), rng.uniform(4.0, 8.0)
    parts = [box((width, 0.3, height), (0, 0, height / 2))]
    rows, cols = int(rng.integers(1, 3)), int(rng.integers(2, 5))
    for r in range(rows):
        for c in range(cols):
            x = (c + 0.5) / cols * width - width / 2
            z = (r + 1) / (rows + 1) * height + 0.5
            parts.append(box((1.0, 0.1, 0.08), (x, -0.2, z - 0.6)))
            parts.append(box((1.0, 0.1, 0.08), (x, -0.2, z + 0.6)))
            parts.append(box((0.08, 0.1, 1.2), (x - 0.5, -0.2, z)))
            parts.append(box((0.08, 0.1, 1.2), (x + 0.5, -0.2, z)))
    return merge(parts)


def kerb(rng: np.random.Generator) -> Mesh:
    """A stretch of road, a kerb step of 10-20 cm, and sidewalk."""
    step = rng.uniform(0.1, 0.2)
    length = rng.uniform(4.0, 8.0)
    road = box((length, 3.0, 0.1), (0, -1.5, -0.05))
    walk = box((length, 2.0, step + 0.1), (0, 1.0, (step - 0.1) / 2))
    return merge([road, walk])


def street_object(rng: np.random.Generator) -> Mesh:
    """Car, pole, facade or kerb."""
    return [car_body, pole, facade, kerb][int(rng.integers(4))](rng)


FAMILIES: dict[str, Callable[[np.random.Generator], Mesh]] = {
    "smooth": smooth_shape,
    "sharp": sharp_shape,
    "thin": thin_shape,
    "composition": composition,
    "street": street_object,
}


def random_mesh(seed: int, family: str | None = None) -> Mesh:
    """The mesh of `seed`: its family drawn from FAMILIES unless given, randomly rotated.

    Street objects are only rotated about z (they stand upright, as a LiDAR sees them).
    """
    rng = np.random.default_rng(seed)
    name = family or list(FAMILIES)[int(rng.integers(len(FAMILIES)))]
    mesh = FAMILIES[name](rng)
    rotation = rotation_z(rng.uniform(0, 2 * np.pi)) if name == "street" else random_rotation(rng)
    return mesh.transformed(rotation)
