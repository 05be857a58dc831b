"""A simulated Velodyne HDL-64E, storing its points in KITTI's order.

Sensor model (`HDL64E`, the default), measured on the six real scans of KITTI odometry sequence 00
by `bench/sim_vs_real.py` (the figures: docs/results.md, "Simulated against real scans"):
- 64 lasers in the HDL-64E's two blocks with their own, irregular elevations
  (`KITTI_ELEVATIONS_DEG`): the upper 32 about 1/3 degree apart, the lower 32 about 1/2 degree;
- each block fires from its own height on the sensor axis (`KITTI_BLOCK_OFFSETS_M`), so a ring is
  the cone z = h + rho tan(elevation) and its elevation seen from the origin changes with range;
- the car moves (`LidarModel.ego_speed`) and the scan is stored de-skewed as KITTI's are, so rings
  seen from the origin are not even cones: their elevation drifts with azimuth, most for the
  lower rings, which see the road close to the car;
- 2000 firings per revolution (0.18 degree, the median azimuth step of real scans), a share of
  them giving a second return half a firing later;
- Gaussian range noise growing with range, and dropouts growing with range;
- no returns where KITTI's car and sensor rack hide the ground from the lowest lasers
  (`KITTI_EGO_SHADOW`);
- returns up to 120 m; a reflectance in [0, 1] from the surface class (`street.REFLECTIVITY`) and
  the angle of incidence, rounded to KITTI's 0.01 steps.
Rays that hit nothing within range are dropped. `LidarModel.clean()` is the sensor as it was
before these measurements (evenly spaced blocks from one still origin, 2 cm noise, no dropouts, no
second returns, reflectance not rounded), bit for bit: training caches and weights made before were made with it.

Point order follows the real KITTI .bin files (checked on the six scans of odometry sequence 00):
ring by ring from the top laser (+2 degrees) down to the bottom one, and within a ring
counter-clockwise seen from above (azimuth atan2(y, x) increasing), starting just above 0,
through +-180 degrees behind the sensor, and ending just below 0. So a new ring starts where the
azimuth wraps from negative to non-negative, which is what `stages.rings.recover_rings` relies on.
Dropouts remove points without reordering; second returns follow their firing.

Frames: the sensor (Velodyne) frame has x forward, y left, z up, metres, like KITTI's.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .kitti_hdl64e import (KITTI_BLOCK_OFFSETS_M, KITTI_EGO_SHADOW, KITTI_EGO_SPEED, KITTI_ELEVATIONS_DEG,
                           KITTI_RANGE_BIAS_M, kitti_vertical_offsets)
from .street import LANE_HALF_WIDTH, REFLECTIVITY, Scene

MOUNT_HEIGHT = 1.73  # metres above the road, as on KITTI's car
#: The measured sensor's tables, re-exported: `cadpu.synthetic.kitti_hdl64e`.
__all__ = ["HDL64E", "KITTI_BLOCK_OFFSETS_M", "KITTI_EGO_SHADOW", "KITTI_EGO_SPEED", "KITTI_ELEVATIONS_DEG",
           "LidarModel", "MOUNT_HEIGHT", "ScanResult", "SceneCaster", "beam_directions", "firing_positions",
           "hdl64e_elevations", "in_shadow", "kitti_vertical_offsets", "mount_pose", "simulate_scan",
           "surface_reflectance", "with_second_returns"]


def hdl64e_elevations() -> np.ndarray:
    """(64,) laser elevation angles in degrees, top laser (ring 0) first, of the clean sensor
    (`LidarModel.clean()`): the HDL-64E's upper block +2.0 .. -8.33 and lower block -8.83 .. -24.8,
    each 32 lasers evenly spaced."""
    return np.concatenate([np.linspace(2.0, -8.33, 32), np.linspace(-8.83, -24.8, 32)])


@dataclass(frozen=True)
class LidarModel:
    """A rotating multi-beam LiDAR. The defaults are the HDL-64E of KITTI's car as measured on real
    scans (module docstring); `LidarModel.clean()` is the idealised sensor used before.

    Attributes:
        elevations_deg: (B,) laser elevations in degrees, ring 0 (stored first) first.
        vertical_offsets_m: (B,) height of each laser's origin above the scan's origin, on the
            sensor's z axis, metres.
        azimuth_steps: firings per revolution.
        max_range: returns beyond this many metres are dropped.
        range_noise: standard deviation of the Gaussian range noise at zero range, metres.
        range_noise_quadratic: growth of that standard deviation with range r: sigma = range_noise
            + range_noise_quadratic * r^2 (metres, r in metres).
        dropout: probability that a return within `dropout_start` metres is lost.
        dropout_growth: growth of that probability per metre of range from `dropout_start` to
            `dropout_end` metres; constant beyond.
        second_return_share: share of firings that give a second return half a firing later.
        ego_speed: forward (+x) speed of the car carrying the sensor, m/s. The scan is stored
            de-skewed, as KITTI's are: every return in the frame the sensor had when it faced
            forward (azimuth 0), fired from where the sensor was at its firing time; the sweep
            turns clockwise seen from above, so a firing at azimuth phi (radians) happens
            -phi / (2 pi) * `sweep_period` seconds from that moment.
        sweep_period: seconds per revolution.
        ego_shadow: sectors where the car carrying the sensor hides everything below an elevation:
            (azimuth from, azimuth to, elevation below) in degrees (see `KITTI_EGO_SHADOW`).
        reflectance_noise: standard deviation of the reflectance noise (reflectance is in [0, 1]).
        reflectance_step: reflectance is rounded to multiples of this (0: not rounded).
        range_bias_m: (B,) each laser's constant range bias, metres, added along its beams (the
            calibration residual of a real unit; `KITTI_RANGE_BIAS_M`, as `HDL64E_RANGE_BIASED`
            has it), or None for none (`HDL64E`, whose scans and training data predate it).
    """

    elevations_deg: np.ndarray = field(default_factory=lambda: KITTI_ELEVATIONS_DEG.copy())
    vertical_offsets_m: np.ndarray = field(default_factory=kitti_vertical_offsets)
    azimuth_steps: int = 2000
    max_range: float = 120.0
    range_noise: float = 0.008
    range_noise_quadratic: float = 5.3e-6
    dropout: float = 0.004
    dropout_growth: float = 0.0009
    dropout_start: float = 10.0
    dropout_end: float = 40.0
    second_return_share: float = 0.075
    ego_speed: float = KITTI_EGO_SPEED
    sweep_period: float = 0.1
    ego_shadow: tuple[tuple[float, float, float], ...] = KITTI_EGO_SHADOW
    reflectance_noise: float = 0.02
    reflectance_step: float = 0.01
    range_bias_m: np.ndarray | None = None

    def __post_init__(self) -> None:
        if len(self.vertical_offsets_m) != len(self.elevations_deg):
            raise ValueError(f"LidarModel: {len(self.elevations_deg)} elevations but "
                             f"{len(self.vertical_offsets_m)} vertical offsets; give one offset per laser")
        if self.range_bias_m is not None and len(self.range_bias_m) != len(self.elevations_deg):
            raise ValueError(f"LidarModel: {len(self.elevations_deg)} elevations but "
                             f"{len(self.range_bias_m)} range biases; give one per laser, or None")
        if not (0.0 <= self.second_return_share < 1.0 and 0.0 <= self.dropout <= 1.0 and self.dropout_growth >= 0
                and self.dropout_end >= self.dropout_start):
            raise ValueError("LidarModel: second_return_share must be in [0, 1), dropout in [0, 1], "
                             "dropout_growth >= 0 and dropout_end >= dropout_start")

    @classmethod
    def clean(cls, **changes) -> LidarModel:
        """The idealised sensor of earlier versions (same output bit for bit for the same seed):
        evenly spaced blocks (`hdl64e_elevations`) firing from one origin that stands still, 2 cm
        range noise, no dropouts, no second returns, reflectance not rounded. `changes` override
        fields."""
        fields = dict(elevations_deg=hdl64e_elevations(), vertical_offsets_m=np.zeros(64), range_noise=0.02,
                      range_noise_quadratic=0.0, dropout=0.0, dropout_growth=0.0, second_return_share=0.0,
                      ego_speed=0.0, ego_shadow=(), reflectance_step=0.0)
        return cls(**(fields | changes))

    @property
    def beams(self) -> int:
        """Number of lasers (rings)."""
        return len(self.elevations_deg)

    @property
    def is_clean(self) -> bool:
        """True when no effect beyond the clean sensor's is on (simulation then draws exactly as before)."""
        return (self.range_noise_quadratic == 0 and self.dropout == 0 and self.dropout_growth == 0
                and self.second_return_share == 0 and not np.any(self.vertical_offsets_m) and self.ego_speed == 0
                and not self.ego_shadow
                and self.reflectance_step == 0 and self.range_bias_m is None)


HDL64E = LidarModel()
#: `HDL64E` with KITTI's per-laser range biases (`KITTI_RANGE_BIAS_M`): the sensor of the
#: scene-statistics table (docs/results.md), opt-in so that `HDL64E`'s scans stay as they were.
HDL64E_RANGE_BIASED = LidarModel(range_bias_m=KITTI_RANGE_BIAS_M.copy())


@dataclass(frozen=True)
class ScanResult:
    """One simulated scan, in KITTI point order.

    Attributes:
        points: (N, 4) float32 x, y, z (sensor frame, metres), reflectance in [0, 1].
        ring: (N,) int16 laser index of each point, 0 = top laser.
        labels: (N,) int32 semantic class of the surface each point lies on (`cadpu.synthetic.street`).
        normals: (N, 3) float32 unit normal of the triangle each point lies on, sensor frame,
            facing the sensor.
    """

    points: np.ndarray
    ring: np.ndarray
    labels: np.ndarray
    normals: np.ndarray


class SceneCaster:
    """A `Scene` loaded into Open3D's ray-casting scene (Embree BVH), built once and reused for
    many scans of the same scene."""

    def __init__(self, scene: Scene) -> None:
        """Build the acceleration structure over `scene`'s triangles (world frame, metres).

        Raises:
            ImportError: Open3D is not installed (the message names the `open3d` extra).
        """
        from ..o3d import o3d

        self.scene = scene
        self._o3d = o3d
        self._raycaster = o3d.t.geometry.RaycastingScene()
        self._raycaster.add_triangles(o3d.core.Tensor(np.ascontiguousarray(scene.vertices, dtype=np.float32)),
                                      o3d.core.Tensor(np.ascontiguousarray(scene.triangles, dtype=np.uint32)))

    def cast(self, origin: np.ndarray, directions: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Cast rays into the scene.

        Args:
            origin: (3,) world position of every ray, or (R, 3) one per ray, metres.
            directions: (R, 3) unit ray directions in the world frame.

        Returns:
            distance (R,) float64 metres (inf for a miss), triangle (R,) int64 index of the
            triangle hit (meaningless for a miss), normal (R, 3) float64 unit normal of that triangle.
        """
        rays = np.empty((len(directions), 6), dtype=np.float32)
        rays[:, :3] = origin
        rays[:, 3:] = directions
        hits = self._raycaster.cast_rays(self._o3d.core.Tensor(rays))
        distance = hits["t_hit"].numpy().astype(np.float64)
        triangle = hits["primitive_ids"].numpy().astype(np.int64)
        normal = hits["primitive_normals"].numpy().astype(np.float64)
        return distance, triangle, normal


def beam_directions(model: LidarModel, start_azimuth: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unit ray directions of one revolution in the sensor frame, in KITTI order.

    Args:
        model: the sensor.
        start_azimuth: (B,) azimuth of each ring's first firing, radians in [0, 2 pi / steps).

    Returns:
        directions (B * steps, 3) float64, ring after ring, azimuth increasing from the ring's start
        (wrapped into (-pi, pi]); ring (B * steps,) int16.
    """
    steps = model.azimuth_steps
    elevation = np.radians(np.asarray(model.elevations_deg, dtype=np.float64))
    azimuth = start_azimuth[:, None] + np.arange(steps)[None, :] * (2 * np.pi / steps)
    azimuth = np.where(azimuth > np.pi, azimuth - 2 * np.pi, azimuth)
    cos_el = np.cos(elevation)[:, None]
    directions = np.stack([cos_el * np.cos(azimuth), cos_el * np.sin(azimuth),
                           np.broadcast_to(np.sin(elevation)[:, None], azimuth.shape)], axis=-1)
    ring = np.repeat(np.arange(model.beams, dtype=np.int16), steps)
    return directions.reshape(-1, 3), ring


def simulate_scan(scene: Scene | SceneCaster, pose: np.ndarray, seed: int = 0,
                  model: LidarModel = HDL64E) -> ScanResult:
    """One revolution of the simulated sensor at `pose`, ray-cast into `scene`.

    Args:
        scene: the world (metres), or a `SceneCaster` built from it to reuse across scans.
        pose: (4, 4) sensor-to-world rigid transform (sensor frame: x forward, y left, z up).
        seed: seed of the range and reflectance noise and of each ring's start azimuth; the
            dropouts and second returns draw from a second stream of the same seed, so
            `LidarModel.clean()` gives the same scan as before they existed.
        model: the sensor; `HDL64E` by default.

    Returns:
        The `ScanResult`, points in the SENSOR frame and in KITTI order (see the module docstring);
        rays that hit nothing within `model.max_range`, and dropouts, are left out.
    """
    pose = np.asarray(pose, dtype=np.float64)
    if pose.shape != (4, 4) or not np.all(np.isfinite(pose)):
        raise ValueError(f"simulate_scan: pose must be a finite (4, 4) matrix, got shape {pose.shape}")
    caster = scene if isinstance(scene, SceneCaster) else SceneCaster(scene)
    rng = np.random.default_rng(seed)
    effects = np.random.default_rng([seed, 1])  # the measured sensor's extra draws
    start = rng.uniform(0.0, 2 * np.pi / model.azimuth_steps, model.beams)
    directions, ring = beam_directions(model, start)
    if model.second_return_share > 0:
        directions, ring = with_second_returns(model, directions, ring, effects)
    rotation, origin = pose[:3, :3], pose[:3, 3]
    world_directions = directions @ rotation.T
    laser_origin = firing_positions(model, directions, ring)  # (R, 3) sensor frame at azimuth 0
    lifted = bool(np.any(laser_origin))
    distance, triangle, normal = caster.cast(origin + laser_origin @ rotation.T if lifted else origin,
                                             world_directions)
    keep = np.isfinite(distance) & (distance < model.max_range)
    if model.ego_shadow:
        keep &= ~in_shadow(model.ego_shadow, directions)
    if model.dropout > 0 or model.dropout_growth > 0:
        beyond = np.clip(np.where(keep, distance, 0.0) - model.dropout_start, 0.0, model.dropout_end - model.dropout_start)
        lost = model.dropout + model.dropout_growth * beyond
        keep &= effects.random(len(distance)) >= lost
    sigma = model.range_noise if model.range_noise_quadratic == 0 else (
        model.range_noise + model.range_noise_quadratic * distance[keep] ** 2)
    measured = distance[keep] + rng.normal(scale=sigma, size=int(keep.sum()))
    if model.range_bias_m is not None:
        measured += np.asarray(model.range_bias_m, dtype=np.float64)[ring[keep]]
    labels = caster.scene.labels[triangle[keep]].astype(np.int32)
    cos_incidence = np.abs(np.einsum("ij,ij->i", normal[keep], world_directions[keep]))
    reflectance = surface_reflectance(labels, cos_incidence, rng, model.reflectance_noise, model.reflectance_step)
    points = np.empty((len(measured), 4), dtype=np.float32)
    xyz = directions[keep] * measured[:, None]
    points[:, :3] = laser_origin[keep] + xyz if lifted else xyz
    points[:, 3] = reflectance
    normals = normal[keep] @ rotation  # world -> sensor frame
    normals *= np.where(np.einsum("ij,ij->i", normals, directions[keep]) > 0, -1.0, 1.0)[:, None]
    return ScanResult(points, ring[keep], labels, normals.astype(np.float32))


def firing_positions(model: LidarModel, directions: np.ndarray, ring: np.ndarray) -> np.ndarray:
    """(R, 3) where each ray leaves from, metres, in the sensor frame of the moment the sensor faces
    forward: its laser's height on the axis (`vertical_offsets_m`) plus the car's travel
    (`ego_speed`) between that moment and the firing (see `LidarModel`).

    Args:
        directions: (R, 3) unit ray directions in the sensor frame. ring: (R,) laser of each ray.
    """
    position = np.zeros((len(directions), 3))
    position[:, 2] = np.asarray(model.vertical_offsets_m, dtype=np.float64)[ring]
    if model.ego_speed:
        azimuth = np.arctan2(directions[:, 1], directions[:, 0])
        position[:, 0] = model.ego_speed * (-azimuth / (2 * np.pi) * model.sweep_period)
    return position


def in_shadow(shadow: tuple[tuple[float, float, float], ...], directions: np.ndarray) -> np.ndarray:
    """(R,) True for the rays of `directions` (R, 3, sensor frame) that a `LidarModel.ego_shadow` hides."""
    azimuth = np.mod(np.degrees(np.arctan2(directions[:, 1], directions[:, 0])), 360.0)
    elevation = np.degrees(np.arcsin(np.clip(directions[:, 2], -1.0, 1.0)))
    hidden = np.zeros(len(directions), dtype=bool)
    for start, end, below in shadow:
        hidden |= (azimuth >= start) & (azimuth < end) & (elevation < below)
    return hidden


def with_second_returns(model: LidarModel, directions: np.ndarray, ring: np.ndarray, rng: np.random.Generator
                        ) -> tuple[np.ndarray, np.ndarray]:
    """The rays of `beam_directions` with a second ray, half a firing later, right after each of a
    random `model.second_return_share` of the firings (never after a ring's last firing, so the
    azimuth still wraps only between rings).

    Args:
        directions: (B * steps, 3) unit directions in KITTI order. ring: (B * steps,) int16.

    Returns:
        directions (R, 3) and ring (R,), R >= B * steps, still in KITTI order.
    """
    steps = model.azimuth_steps
    chosen = rng.random(len(directions)) < model.second_return_share
    chosen[steps - 1::steps] = False
    index = np.flatnonzero(chosen)
    half = np.pi / steps
    c, s = np.cos(half), np.sin(half)
    d = directions[index]
    extra = np.stack([c * d[:, 0] - s * d[:, 1], s * d[:, 0] + c * d[:, 1], d[:, 2]], axis=1)  # turned about z
    return np.insert(directions, index + 1, extra, axis=0), np.insert(ring, index + 1, ring[index])


def surface_reflectance(labels: np.ndarray, cos_incidence: np.ndarray, rng: np.random.Generator,
                        noise: float = 0.02, step: float = 0.0) -> np.ndarray:
    """(N,) reflectance in [0, 1]: the class's base reflectivity, weakened at grazing incidence (a
    Lambertian-like 0.3 + 0.7 cos term), plus Gaussian noise, rounded to multiples of `step` (0: not
    rounded, as in the clean sensor; KITTI's are multiples of 0.01).

    Args:
        labels: (N,) semantic classes of `cadpu.synthetic.street`. cos_incidence: (N,) |cos| of the angle
        between ray and surface normal. rng: noise source. noise: noise standard deviation.
    """
    base = REFLECTIVITY[labels] * (0.3 + 0.7 * cos_incidence)
    reflectance = np.clip(base + rng.normal(scale=noise, size=len(labels)), 0.0, 1.0)
    return np.round(reflectance / step) * step if step > 0 else reflectance


def mount_pose(scene: Scene, x: float, y: float = -LANE_HALF_WIDTH / 2, yaw: float = 0.0,
               height: float = MOUNT_HEIGHT) -> np.ndarray:
    """(4, 4) sensor-to-world pose of a sensor on a car standing on the road of `scene`.

    The car is at street position `x`, lateral offset `y` (default: the centre of the right-hand
    lane), heading `yaw` radians from +x, pitched with the road's slope; the sensor sits `height`
    metres above the road along the car's up axis, so the road under it is at z = -height in the
    sensor frame.
    """
    pitch = -np.arctan(scene.slope * np.cos(yaw))  # nose up when driving uphill
    cy, sy, cp, sp = np.cos(yaw), np.sin(yaw), np.cos(pitch), np.sin(pitch)
    yaw_rotation = np.array([[cy, -sy, 0.0], [sy, cy, 0.0], [0.0, 0.0, 1.0]])
    pitch_rotation = np.array([[cp, 0.0, sp], [0.0, 1.0, 0.0], [-sp, 0.0, cp]])
    pose = np.eye(4)
    pose[:3, :3] = yaw_rotation @ pitch_rotation
    ground = np.array([x, y, scene.slope * x])
    pose[:3, 3] = ground + pose[:3, :3] @ np.array([0.0, 0.0, height])
    return pose
