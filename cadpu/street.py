"""A procedural street scene as labelled triangles (pure numpy, deterministic per seed).

World frame: x along the street, y to the left, z up, metres; the road surface is z = slope * x,
the street runs from x = -30 to x = length. The scene holds a road, 15 cm kerbs with sidewalks,
building facades with window frames and recessed doors, parked cars, poles with heads and
vegetation-like blobs.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .shapes import Mesh, blob, box, car_body, merge, pole, rotation_z

ROAD, SIDEWALK, BUILDING, CAR, POLE, VEGETATION = range(6)
CLASS_NAMES = ("road", "sidewalk", "building", "car", "pole", "vegetation")
#: Classes that count as ground (what a vehicle could drive or walk on).
GROUND_CLASSES = (ROAD, SIDEWALK)
#: Base reflectance of each class (KITTI reflectance is in [0, 1]).
REFLECTIVITY = np.array([0.25, 0.3, 0.35, 0.5, 0.45, 0.2])

ROAD_HALF_WIDTH = 4.0
KERB_HEIGHT = 0.15
SIDEWALK_WIDTH = 3.0


@dataclass(frozen=True)
class Scene:
    """Triangles with a semantic class each: vertices (V, 3), triangles (T, 3), labels (T,) int32."""

    vertices: np.ndarray
    triangles: np.ndarray
    labels: np.ndarray


def _labelled(parts: list[tuple[Mesh, int]]) -> Scene:
    mesh = merge([m for m, _ in parts])
    labels = np.concatenate([np.full(len(m.triangles), label, dtype=np.int32) for m, label in parts])
    return Scene(mesh.vertices, mesh.triangles, labels)


def make_street(seed: int = 0, length_m: float = 120.0, slope: float = 0.02) -> Scene:
    """The street of `seed` (see the module docstring)."""
    rng = np.random.default_rng(seed)
    start = -30.0
    span = length_m - start
    centre_x = (start + length_m) / 2
    parts: list[tuple[Mesh, int]] = [
        (box((span, 2 * ROAD_HALF_WIDTH, 0.2), (centre_x, 0.0, -0.1)), ROAD),
    ]
    for side in (-1.0, 1.0):
        y_walk = side * (ROAD_HALF_WIDTH + SIDEWALK_WIDTH / 2)
        parts.append((box((span, SIDEWALK_WIDTH, 0.2 + KERB_HEIGHT), (centre_x, y_walk, (KERB_HEIGHT - 0.2) / 2)),
                      SIDEWALK))
        facade_y = side * (ROAD_HALF_WIDTH + SIDEWALK_WIDTH)
        x = start
        while x < length_m:  # buildings of varying width, with gaps
            width = rng.uniform(8.0, 18.0)
            house = _facade(rng, width).transformed(rotation_z(0.0 if side > 0 else np.pi), 1.0,
                                                    (x + width / 2, facade_y + side * 0.2, 0.0))
            parts.append((house, BUILDING))
            x += width + rng.uniform(0.0, 4.0)
        for x in np.arange(start + rng.uniform(0, 6), length_m, rng.uniform(9.0, 14.0)):
            if rng.random() < 0.6:
                car = car_body(rng).transformed(rotation_z(rng.normal(scale=0.05)), 1.0,
                                                (x, side * (ROAD_HALF_WIDTH - 1.2), 0.0))
                parts.append((car, CAR))
        for x in np.arange(start + rng.uniform(0, 10), length_m, rng.uniform(15.0, 25.0)):
            parts.append((pole(rng).transformed(rotation_z(0.0 if side > 0 else np.pi), 1.0,
                                                (x, side * (ROAD_HALF_WIDTH + 0.5), KERB_HEIGHT)), POLE))
        for x in np.arange(start + rng.uniform(0, 8), length_m, rng.uniform(8.0, 16.0)):
            radius = rng.uniform(0.6, 1.5)
            bush = blob(rng, 24).transformed(np.eye(3), radius,
                                             (x, side * (ROAD_HALF_WIDTH + SIDEWALK_WIDTH - 1.0), KERB_HEIGHT + radius * 0.8))
            parts.append((bush, VEGETATION))
    scene = _labelled(parts)
    vertices = scene.vertices.copy()
    vertices[:, 2] += slope * vertices[:, 0]  # the whole street climbs gently
    return Scene(vertices, scene.triangles, scene.labels)


def _facade(rng: np.random.Generator, width: float) -> Mesh:
    """A building front of `width` facing -y: wall, window frames standing out, a recessed door."""
    height = rng.uniform(6.0, 12.0)
    depth = 5.0
    parts = [box((width, depth, height), (0.0, depth / 2, height / 2))]
    cols = max(1, int(width // 3))
    for row in range(int(height // 3)):
        z = 3.0 * row + 1.8
        for col in range(cols):
            x = (col + 0.5) / cols * width - width / 2
            parts += [box((1.2, 0.12, 0.1), (x, -0.06, z - 0.7)), box((1.2, 0.12, 0.1), (x, -0.06, z + 0.7)),
                      box((0.1, 0.12, 1.4), (x - 0.6, -0.06, z)), box((0.1, 0.12, 1.4), (x + 0.6, -0.06, z))]
    parts.append(box((1.2, 0.1, 2.2), (rng.uniform(-width / 3, width / 3), -0.05, 1.1)))
    return merge(parts)


def is_ground(labels: np.ndarray) -> np.ndarray:
    """(N,) bool: which semantic labels count as ground."""
    return np.isin(labels, GROUND_CLASSES)
