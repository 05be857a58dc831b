"""Procedural scenes of several types, as labelled triangles (pure numpy, deterministic per seed).

Scene types (`SCENE_TYPES`, chosen by `make_scene(scene_type=...)`):
- "urban": the street of `cadpu.synthetic.street.make_street`, unchanged (facades 3 m behind a
  15 cm kerb, parked cars, poles, trees, bushes);
- "suburban": a street with parking lanes and raised sidewalks, then lawns (terrain) rising or
  falling gently and unevenly away from the sidewalk, houses set back 6-12 m behind them, hedges
  and shrubs on the lawns, trees, parked cars;
- "open": an open area: a two-lane road with a shoulder, a raised sidewalk on some sides (kerb
  10-18 cm), otherwise a grass verge; then 60 m of terrain sloping gently and unevenly away from
  the road (grade -3 % to +5 %, relief of 5-20 cm over 8-30 m, a rough grass surface), patches of
  low vegetation (shrubs and tall grass), few trees and few buildings far back;
- "rural": a country road without kerbs: a verge at road level, a drainage ditch 0.3-0.7 m deep
  1-2 m from the asphalt, then fields (rough terrain) with patches of crops and scrub, few trees,
  rare farm buildings;
- "residential": the residential streets of the KITTI odometry sequences, made to the class mix
  SemanticKITTI reports (docs/results.md, "Simulated against real scans"): a parking lane with few
  cars, sidewalks, front gardens behind hedges (on most plots), fences or nothing, houses 3-9 m
  back, street and garden trees, shrubs. Its vegetation is volumetric (`foliage`): leaves
  scattered in a shell around an opaque core, so a beam returns from a leaf at a random depth, as
  on real foliage, where the other types' vegetation is one closed surface.

So the non-urban types put ground-like surfaces a little above the road (sidewalks and terrain,
about 0.1-0.2 m up, and more where the terrain climbs) out to where a KITTI scan's rings are
sparse, beside rough low vegetation that is not ground.

World frame: x along the road, y to the left, z up, metres; the road surface is z = slope * x and
runs from x = -30 to x = `length_m`, as in `make_street`. Labels are the classes of
`cadpu.synthetic.street` (TERRAIN for grass and soil; `street.SEMANTIC_KITTI` maps them to
SemanticKITTI ids). The driving lanes (|y| < `LANE_HALF_WIDTH`) are kept free.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from .shapes import Mesh, merge, prism, rotation_z
from .shapes import box as _box
from .street import (BUILDING, FENCE, LANE_HALF_WIDTH, POLE, ROAD, SIDEWALK, SLAB, STREET_START, TERRAIN,
                     TRUNK, VEGETATION, Scene, _labelled, _parked_cars, displaced_icosphere, facade, make_street,
                     street_pole)

SCENE_TYPES = ("urban", "suburban", "open", "rural", "residential")
TERRAIN_STEP = 0.5  # grid spacing of the terrain mesh, metres


@dataclass(frozen=True)
class SceneLayout:
    """What a non-urban scene type holds. Metres unless stated; (low, high) pairs are drawn
    uniformly, once per side of the road unless stated.

    Attributes:
        road_half_width: asphalt from the centre line to the kerb or verge (lanes plus parking
            lane or shoulder).
        sidewalk_chance: probability that a side has a raised sidewalk (else a verge of terrain).
        sidewalk_width, kerb_height: of a raised sidewalk.
        terrain_width: terrain beyond the sidewalk (or the road edge).
        terrain_grade: cross slope of the terrain away from the road (positive: climbing).
        relief: amplitude of the terrain's low-frequency unevenness.
        roughness: standard deviation of the terrain's vertex heights about its smooth surface
            (grass, soil), at `TERRAIN_STEP` spacing.
        setback: distance from the terrain's near edge to building fronts; None: no buildings.
        building_chance: probability of a building on each plot along the road.
        shrubs_per_100m2: shrubs and tall-grass patches per 100 square metres of terrain.
        tree_spacing: distance along the road between trees.
        pole_spacing: distance along the road between poles.
        parked_cars: cars in a 2 m parking lane (road_half_width must include it).
        ditch: (depth low, depth high) of a drainage ditch along the verge; None: no ditch.
        parking_occupancy: the share of the parking lane's slots that hold a car.
        hedge_chance, fence_chance: probability that a plot's front (along the terrain's near edge,
            the sidewalk's back) is a hedge, or else a fence; plots are 6-15 m long, 0.5-3 m apart.
        foliage: vegetation as `foliage` volumes (leaves around a core) instead of closed blobs.
    """

    road_half_width: float
    sidewalk_chance: float
    sidewalk_width: tuple[float, float]
    kerb_height: tuple[float, float]
    terrain_width: float
    terrain_grade: tuple[float, float]
    relief: tuple[float, float]
    roughness: float
    setback: tuple[float, float] | None
    building_chance: float
    shrubs_per_100m2: float
    tree_spacing: tuple[float, float]
    pole_spacing: tuple[float, float]
    parked_cars: bool
    ditch: tuple[float, float] | None = None
    parking_occupancy: float = 0.65
    hedge_chance: float = 0.0
    fence_chance: float = 0.0
    foliage: bool = False


LAYOUTS = {
    "suburban": SceneLayout(
        road_half_width=5.5, sidewalk_chance=1.0, sidewalk_width=(1.5, 2.5), kerb_height=(0.12, 0.18),
        terrain_width=30.0, terrain_grade=(-0.02, 0.04), relief=(0.02, 0.08), roughness=0.015,
        setback=(6.0, 12.0), building_chance=0.8, shrubs_per_100m2=0.6, tree_spacing=(12.0, 30.0),
        pole_spacing=(20.0, 35.0), parked_cars=True),
    "open": SceneLayout(
        road_half_width=4.0, sidewalk_chance=0.6, sidewalk_width=(2.0, 3.5), kerb_height=(0.10, 0.18),
        terrain_width=60.0, terrain_grade=(-0.03, 0.05), relief=(0.05, 0.2), roughness=0.025,
        setback=(25.0, 45.0), building_chance=0.15, shrubs_per_100m2=0.8, tree_spacing=(30.0, 70.0),
        pole_spacing=(25.0, 45.0), parked_cars=False),
    "rural": SceneLayout(
        road_half_width=3.75, sidewalk_chance=0.0, sidewalk_width=(0.0, 0.0), kerb_height=(0.0, 0.0),
        terrain_width=60.0, terrain_grade=(-0.02, 0.03), relief=(0.05, 0.25), roughness=0.04,
        setback=(30.0, 55.0), building_chance=0.1, shrubs_per_100m2=1.2, tree_spacing=(20.0, 50.0),
        pole_spacing=(40.0, 60.0), parked_cars=False, ditch=(0.3, 0.7)),
    "residential": SceneLayout(
        road_half_width=5.5, sidewalk_chance=1.0, sidewalk_width=(1.8, 3.0), kerb_height=(0.10, 0.16),
        terrain_width=25.0, terrain_grade=(-0.01, 0.03), relief=(0.02, 0.06), roughness=0.015,
        setback=(3.0, 9.0), building_chance=0.8, shrubs_per_100m2=4.0, tree_spacing=(6.0, 15.0),
        pole_spacing=(20.0, 35.0), parked_cars=True, parking_occupancy=0.15, hedge_chance=0.85,
        fence_chance=0.5, foliage=True),
}


def make_scene(scene_type: str = "urban", seed: int = 0, length_m: float = 120.0, slope: float = 0.02) -> Scene:
    """Build the scene of `scene_type` and `seed` (types in the module docstring).

    Args:
        scene_type: one of `SCENE_TYPES`; "urban" is exactly `make_street(seed, length_m, slope)`.
        seed: layout seed; the same type and seed always give the same scene, bit for bit.
        length_m: the road runs from x = -30 m to x = `length_m` (must exceed -30 + 10).
        slope: road gradient dz/dx (0.02 = 2 %), applied to the whole scene.

    Returns:
        The `Scene` (world frame, metres).

    Raises:
        ValueError: unknown scene type (the message lists the known ones), too short a road, a
            negative or fractional seed, or a slope or length that is not finite.
    """
    if scene_type not in SCENE_TYPES:
        raise ValueError(f"make_scene: unknown scene type {scene_type!r}; known: {', '.join(SCENE_TYPES)}")
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise ValueError(f"make_scene: seed must be a whole number >= 0, got {seed!r}")
    if not (np.isfinite(slope) and np.isfinite(length_m)):
        raise ValueError(f"make_scene: slope and length_m must be finite, got {slope} and {length_m}")
    if scene_type == "urban":
        return make_street(seed, length_m, slope)
    if length_m <= STREET_START + 10.0:
        raise ValueError(f"make_scene: length_m must be above {STREET_START + 10.0} m, got {length_m}")
    layout = LAYOUTS[scene_type]
    rng = np.random.default_rng([seed, SCENE_TYPES.index(scene_type)])
    span = length_m - STREET_START
    centre_x = (STREET_START + length_m) / 2
    parts: list[tuple[Mesh, int]] = [(_box((span, 2 * layout.road_half_width, SLAB), (centre_x, 0.0, -SLAB / 2)),
                                      ROAD)]
    for side in (-1.0, 1.0):
        parts += _roadside(rng, layout, side, length_m)
        if layout.parked_cars:
            parts += _parked_cars(rng, side, length_m, layout.parking_occupancy)
    scene = _labelled(parts)
    vertices = scene.vertices.copy()
    vertices[:, 2] += slope * vertices[:, 0]
    return Scene(vertices, scene.triangles, scene.labels, float(slope))


@dataclass(frozen=True)
class Terrain:
    """The smooth terrain surface of one side of the road (roughness aside).

    Its near edge is the line |y| = `edge` (the sidewalk's back or the road's edge) at height
    `base`; with t = |y| - edge metres away from the road, its height is
    base + grade t + ramp(t) sum_k amplitude_k sin(wave_k . (x, t) + phase_k), where the relief
    ramps in over the first 4 m so the terrain meets the sidewalk or road edge cleanly; minus,
    where there is a ditch, depth sin^2(pi (t - ditch_start) / ditch_width) over
    ditch_start <= t <= ditch_start + ditch_width.
    """

    side: float
    edge: float
    base: float
    grade: float
    amplitude: np.ndarray
    wave: np.ndarray
    phase: np.ndarray
    ditch_depth: float = 0.0
    ditch_start: float = 0.0
    ditch_width: float = 1.0

    def height(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Height (world z before the road slope) of the smooth surface at (x, y), metres."""
        t = np.maximum(np.abs(y) - self.edge, 0.0)
        ramp = np.minimum(t / 4.0, 1.0) ** 2
        relief = (self.amplitude * np.sin(x[..., None] * self.wave[:, 0] + t[..., None] * self.wave[:, 1]
                                          + self.phase)).sum(axis=-1)
        across = np.clip((t - self.ditch_start) / self.ditch_width, 0.0, 1.0)
        return self.base + self.grade * t + ramp * relief - self.ditch_depth * np.sin(np.pi * across) ** 2


def _roadside(rng: np.random.Generator, layout: SceneLayout, side: float, length_m: float) -> list[tuple[Mesh, int]]:
    """One side of the road: sidewalk or verge, terrain, vegetation, trees, poles, buildings."""
    parts: list[tuple[Mesh, int]] = []
    span, centre_x = length_m - STREET_START, (STREET_START + length_m) / 2
    edge, base = layout.road_half_width, float(rng.uniform(-0.03, 0.06))  # a verge near road level
    if rng.random() < layout.sidewalk_chance:
        width, kerb = rng.uniform(*layout.sidewalk_width), rng.uniform(*layout.kerb_height)
        y = side * (edge + width / 2)
        parts.append((_box((span, width, SLAB + kerb), (centre_x, y, kerb - (SLAB + kerb) / 2)), SIDEWALK))
        edge, base = edge + width, kerb - 0.02  # the terrain starts just below the sidewalk's back
    waves = 3
    wavelength = rng.uniform(8.0, 30.0, waves)
    direction = rng.uniform(0.0, 2 * np.pi, waves)
    terrain = Terrain(side, edge, base, float(rng.uniform(*layout.terrain_grade)),
                      rng.uniform(*layout.relief, waves) / np.sqrt(waves),
                      np.c_[np.cos(direction), np.sin(direction)] * (2 * np.pi / wavelength)[:, None],
                      rng.uniform(0.0, 2 * np.pi, waves))
    if layout.ditch is not None:
        terrain = dataclasses.replace(terrain, ditch_depth=float(rng.uniform(*layout.ditch)),
                                      ditch_start=float(rng.uniform(1.0, 2.0)),
                                      ditch_width=float(rng.uniform(1.5, 3.0)))
    parts.append((_terrain_mesh(rng, terrain, layout, length_m), TERRAIN))
    parts += _low_vegetation(rng, terrain, layout, length_m)
    parts += _trees(rng, terrain, layout, length_m)
    parts += _poles(rng, terrain, layout, length_m)
    if layout.setback is not None:
        parts += _buildings(rng, terrain, layout, length_m)
    if layout.hedge_chance > 0.0 or layout.fence_chance > 0.0:
        parts += _plot_fronts(rng, terrain, layout, length_m)
    return parts


def _terrain_mesh(rng: np.random.Generator, terrain: Terrain, layout: SceneLayout, length_m: float) -> Mesh:
    """The terrain of one side as a height field on a `TERRAIN_STEP` grid, its vertices jittered
    in height by `layout.roughness` (kept 0 on the near edge, where it meets the sidewalk)."""
    xs = np.arange(STREET_START, length_m + TERRAIN_STEP / 2, TERRAIN_STEP)
    ts = np.arange(0.0, layout.terrain_width + TERRAIN_STEP / 2, TERRAIN_STEP)
    xx, tt = np.meshgrid(xs, ts, indexing="ij")
    yy = terrain.side * (terrain.edge + tt)
    zz = terrain.height(xx, yy) + rng.normal(scale=layout.roughness, size=xx.shape) * (tt > 0)
    vertices = np.stack([xx, yy, zz], axis=-1).reshape(-1, 3)
    rows, cols = xx.shape
    i, j = (a.ravel() for a in np.meshgrid(np.arange(rows - 1), np.arange(cols - 1), indexing="ij"))
    a, b, c, d = i * cols + j, (i + 1) * cols + j, (i + 1) * cols + j + 1, i * cols + j + 1
    # Counter-clockwise seen from above on the left side (t grows with y); flipped on the right.
    first, second = (np.stack([a, b, c], 1), np.stack([a, c, d], 1))
    if terrain.side < 0:
        first, second = first[:, ::-1], second[:, ::-1]
    return Mesh(vertices, np.concatenate([first, second]))


def _spot(rng: np.random.Generator, terrain: Terrain, near: float, far: float, length_m: float,
          x: float | None = None) -> tuple[float, float, float]:
    """A random (x, y, z) on the smooth terrain, between `near` and `far` metres from its edge."""
    x = float(rng.uniform(STREET_START, length_m)) if x is None else x
    y = terrain.side * (terrain.edge + float(rng.uniform(near, far)))
    return x, y, float(terrain.height(np.array(x), np.array(y)))


def _low_vegetation(rng: np.random.Generator, terrain: Terrain, layout: SceneLayout,
                    length_m: float) -> list[tuple[Mesh, int]]:
    """Shrubs (0.3-1.2 m wide, 0.25-0.7 m high) and tall-grass patches (1.5-4 m wide, their tops
    0.1-0.3 m above the terrain) scattered over the terrain."""
    area = (length_m - STREET_START) * layout.terrain_width
    parts = []
    for _ in range(int(rng.poisson(layout.shrubs_per_100m2 * area / 100.0))):
        if rng.random() < 0.5:
            radius, top = rng.uniform(0.3, 1.2), rng.uniform(0.25, 0.7)
            shape = np.array([radius * rng.uniform(1.0, 2.0), radius, top / 1.6])
        else:  # tall grass: a wide, flat and rough blob, mostly sunk into the ground
            radius, top = rng.uniform(0.75, 2.0), rng.uniform(0.1, 0.3)
            shape = np.array([radius * rng.uniform(1.0, 2.0), radius, 0.35])
        reach = 1.6 * shape[0]  # beyond the blob's widest lobe: it stays off the road
        x, y, z = _spot(rng, terrain, reach, max(layout.terrain_width - reach, reach), length_m)
        if layout.foliage:
            turn = rotation_z(rng.uniform(0.0, np.pi))
            blob = foliage(rng, shape).transformed(turn, 1.0, (x, y, z + top - shape[2]))
        else:  # the blob's draws come before the turn's, as they always have for these types
            blob = displaced_icosphere(rng).transformed(rotation_z(rng.uniform(0.0, np.pi)), shape,
                                                        (x, y, z + top - shape[2]))
        parts.append((blob, VEGETATION))
    return parts


def _trees(rng: np.random.Generator, terrain: Terrain, layout: SceneLayout, length_m: float) -> list[tuple[Mesh, int]]:
    """Trees (trunk and crown) on the terrain, their crowns clear of its edge and up to 12 m beyond."""
    parts = []
    x = STREET_START + rng.uniform(0.0, layout.tree_spacing[0])
    while x < length_m:
        trunk_h, crown = rng.uniform(2.0, 3.5), rng.uniform(1.5, 3.0)
        _, y, z = _spot(rng, terrain, 1.6 * crown, 12.0 + crown, length_m, x)
        trunk = prism(12, rng.uniform(0.12, 0.25), trunk_h + crown * 0.5 + 0.2).transformed(
            np.eye(3), 1.0, (x, y, z - 0.2 + (trunk_h + crown * 0.5 + 0.2) / 2))
        crown_axes = np.array([1.0, 1.0, 0.85]) * crown
        if layout.foliage:
            top = foliage(rng, crown_axes, free_path=CROWN_FREE_PATH).transformed(
                np.eye(3), 1.0, (x, y, z + trunk_h + crown * 0.8))
        else:
            top = displaced_icosphere(rng).transformed(np.eye(3), crown_axes, (x, y, z + trunk_h + crown * 0.8))
        parts += [(trunk, TRUNK), (top, VEGETATION)]
        x += rng.uniform(*layout.tree_spacing)
    return parts


def _poles(rng: np.random.Generator, terrain: Terrain, layout: SceneLayout, length_m: float) -> list[tuple[Mesh, int]]:
    """Lamp and sign posts 1.2 m behind the road's edge (on the sidewalk or verge), so that a lamp's
    head, reaching 1.2 m towards the road, stays clear of the driving lanes."""
    parts = []
    y = terrain.side * (layout.road_half_width + 1.2)
    x = STREET_START + rng.uniform(0.0, layout.pole_spacing[0])
    while x < length_m:
        foot = float(terrain.height(np.array(x), np.array(y)))
        facing = rotation_z(0.0 if terrain.side > 0 else np.pi)
        parts.append((street_pole(rng).transformed(facing, 1.0, (x, y, foot - 0.05)), POLE))
        x += rng.uniform(*layout.pole_spacing)
    return parts


def _buildings(rng: np.random.Generator, terrain: Terrain, layout: SceneLayout,
               length_m: float) -> list[tuple[Mesh, int]]:
    """Buildings facing the road, `layout.setback` behind the terrain's edge, one plot at a time;
    each sunk 0.3 m into the terrain so that no gap opens under it."""
    assert layout.setback is not None
    parts = []
    x = STREET_START
    while x < length_m:
        width = rng.uniform(8.0, 16.0)
        if rng.random() < layout.building_chance:
            offset = rng.uniform(*layout.setback)
            y = terrain.side * (terrain.edge + offset)
            foot = float(terrain.height(np.array(x + width / 2), np.array(y))) - 0.3
            facing = rotation_z(0.0 if terrain.side > 0 else np.pi)
            parts.append((facade(rng, width).transformed(facing, 1.0, (x + width / 2, y, foot)), BUILDING))
        x += width + rng.uniform(3.0, 12.0)
    return parts


#: Foliage (`foliage`): the side of a leaf (m), and the mean distance a beam travels into a hedge or
#: shrub and into a tree's crown before it meets a leaf (m). KITTI's vegetation returns scatter in
#: depth: 72% of the vegetation points of the labelled real scan 000000 within 30 m have a surface
#: variation above 0.05, against 7-9% on the closed blobs of the other scene types
#: (docs/results.md, "Simulated against real scans").
LEAF_SIZE = 0.12
HEDGE_FREE_PATH = 0.15
CROWN_FREE_PATH = 0.4


def foliage(rng: np.random.Generator, semi_axes: np.ndarray, free_path: float = HEDGE_FREE_PATH,
            shell: float = 0.5, leaf_size: float = LEAF_SIZE) -> Mesh:
    """A volume of foliage about the origin: an opaque core (a displaced icosphere) inside a shell
    of leaves (single triangles of side `leaf_size`, randomly placed and turned).

    The leaves fill the ellipsoid of `semi_axes` outside the core (the ellipsoid shrunk by
    `shell` metres, at most 60% of its smallest semi-axis) at the density that makes `free_path`
    the mean distance a beam travels between leaves (a randomly turned flat leaf shows half its
    area on average), so a beam returns from a leaf at a random depth, or from the core.

    Args:
        semi_axes: (3,) metres. free_path, shell, leaf_size: metres.

    Returns:
        The `Mesh`, about 1 / (free_path * leaf area / 2) triangles per cubic metre of shell.
    """
    semi_axes = np.asarray(semi_axes, dtype=np.float64)
    depth = min(shell, 0.6 * float(semi_axes.min()))
    core_axes = semi_axes - depth
    shell_volume = 4.0 / 3.0 * np.pi * (np.prod(semi_axes) - np.prod(core_axes))
    leaf_area = np.sqrt(3.0) / 4.0 * leaf_size**2
    count = int(rng.poisson(shell_volume / (free_path * leaf_area / 2.0)))
    # Uniform in the shell: directions on the sphere, radius fraction with density ~ r^2 between
    # the core's and the outer ellipsoid's (exact for a shell of constant proportion).
    direction = rng.normal(size=(count, 3))
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    inner = float(np.cbrt(np.prod(core_axes) / np.prod(semi_axes)))
    fraction = np.cbrt(rng.uniform(inner**3, 1.0, count))
    centres = direction * fraction[:, None] * semi_axes
    # An equilateral leaf in a random plane: two orthonormal in-plane axes per leaf.
    normal = rng.normal(size=(count, 3))
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    helper = np.where(np.abs(normal[:, :1]) < 0.9, np.array([[1.0, 0.0, 0.0]]), np.array([[0.0, 1.0, 0.0]]))
    u = np.cross(normal, helper)
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    v = np.cross(normal, u)
    angles = rng.uniform(0.0, 2 * np.pi, count)[:, None] + np.array([0.0, 2.0, 4.0]) * np.pi / 3
    radius = leaf_size / np.sqrt(3.0)
    corners = centres[:, None, :] + radius * (np.cos(angles)[..., None] * u[:, None, :]
                                              + np.sin(angles)[..., None] * v[:, None, :])
    leaves = Mesh(corners.reshape(-1, 3), np.arange(3 * count, dtype=np.int64).reshape(count, 3))
    core = displaced_icosphere(rng).transformed(np.eye(3), core_axes)
    return merge([core, leaves])


def _plot_fronts(rng: np.random.Generator, terrain: Terrain, layout: SceneLayout,
                 length_m: float) -> list[tuple[Mesh, int]]:
    """Hedges and fences along the terrain's near edge (the sidewalk's back), plot by plot: plots
    6-15 m long with 0.5-3 m between them (gates, drives); each a hedge with probability
    `layout.hedge_chance`, else a fence with probability `layout.fence_chance`, else open."""
    parts: list[tuple[Mesh, int]] = []
    facing = rotation_z(0.0 if terrain.side > 0 else np.pi)
    x = STREET_START + rng.uniform(0.0, 3.0)
    while x < length_m:
        length = rng.uniform(6.0, 15.0)
        end = min(x + length, length_m)
        draw = rng.random()
        if draw < layout.hedge_chance:
            height, thickness = rng.uniform(1.0, 2.2), rng.uniform(0.6, 1.2)
            y = terrain.side * (terrain.edge + 0.1 + thickness / 2)
            pieces = max(1, int(np.ceil((end - x) / 2.5)))
            step = (end - x) / pieces
            for i in range(pieces):  # overlapping lobes, so the hedge's top and face undulate
                cx = x + (i + 0.5) * step
                foot = float(terrain.height(np.array(cx), np.array(y)))
                axes = np.array([0.6 * step, thickness / 2, height / 2]) * rng.uniform(0.9, 1.1, 3)
                parts.append((foliage(rng, axes).transformed(np.eye(3), 1.0, (cx, y, foot + axes[2] - 0.1)),
                              VEGETATION))
        elif draw < layout.hedge_chance + (1.0 - layout.hedge_chance) * layout.fence_chance:
            height = rng.uniform(0.8, 1.6)
            y = terrain.side * (terrain.edge + 0.15)
            foot = float(terrain.height(np.array((x + end) / 2), np.array(y)))
            parts.append((_picket_fence(end - x, height).transformed(facing, 1.0, ((x + end) / 2, y, foot - 0.05)),
                          FENCE))
        x = end + rng.uniform(0.5, 3.0)
    return parts


def _picket_fence(length: float, height: float, picket: float = 0.08, gap: float = 0.06) -> Mesh:
    """A picket fence of `length` along x about the origin, standing on z = 0: pickets `picket`
    wide with `gap` between them, on two rails behind them (facing -y)."""
    count = max(1, int(length // (picket + gap)))
    xs = -length / 2 + (np.arange(count) + 0.5) * length / count
    parts = [_box((picket, 0.02, height), (px, 0.0, height / 2)) for px in xs]
    parts += [_box((length, 0.05, 0.08), (0.0, 0.035, z)) for z in (0.25 * height, 0.8 * height)]
    return merge(parts)
