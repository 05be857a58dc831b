"""A simulated Velodyne HDL-64E, storing its points in KITTI's order.

Sensor model (`HDL64E`): 64 lasers in the HDL-64E's two blocks, upper 32 evenly from +2.0 to
-8.33 degrees (1/3 degree apart), lower 32 evenly from -8.83 to -24.8 degrees (about 0.52 degree
apart), so the vertical field of view is +2 to -24.8 degrees as KITTI documents it;
2000 firings per revolution (0.18 degree, the median azimuth step between consecutive points of
real KITTI scans: docs/results.md); returns up to 120 m with Gaussian
range noise of 2 cm; a reflectance in [0, 1] from the surface class and the angle of incidence.
Rays that hit nothing within range are dropped. All lasers fire from the sensor origin.

Point order follows the real KITTI .bin files (checked on the six scans of odometry sequence 00):
ring by ring from the top laser (+2 degrees) down to the bottom one, and within a ring
counter-clockwise seen from above (azimuth atan2(y, x) increasing), starting just above 0,
through +-180 degrees behind the sensor, and ending just below 0. So a new ring starts where the
azimuth wraps from negative to non-negative, which is what `stages.rings.recover_rings` relies on.

Frames: the sensor (Velodyne) frame has x forward, y left, z up, metres, like KITTI's.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .street import LANE_HALF_WIDTH, REFLECTIVITY, Scene

MOUNT_HEIGHT = 1.73  # metres above the road, as on KITTI's car


def hdl64e_elevations() -> np.ndarray:
    """(64,) laser elevation angles in degrees, top laser (ring 0) first: the HDL-64E's upper block
    +2.0 .. -8.33 and lower block -8.83 .. -24.8, each 32 lasers evenly spaced."""
    return np.concatenate([np.linspace(2.0, -8.33, 32), np.linspace(-8.83, -24.8, 32)])


@dataclass(frozen=True)
class LidarModel:
    """A rotating multi-beam LiDAR.

    Attributes:
        elevations_deg: (B,) laser elevations in degrees, ring 0 (stored first) first.
        azimuth_steps: firings per revolution.
        max_range: returns beyond this many metres are dropped.
        range_noise: standard deviation of the Gaussian range noise, metres.
        reflectance_noise: standard deviation of the reflectance noise (reflectance is in [0, 1]).
    """

    elevations_deg: np.ndarray = field(default_factory=hdl64e_elevations)
    azimuth_steps: int = 2000
    max_range: float = 120.0
    range_noise: float = 0.02
    reflectance_noise: float = 0.02

    @property
    def beams(self) -> int:
        """Number of lasers (rings)."""
        return len(self.elevations_deg)


HDL64E = LidarModel()


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
        seed: seed of the range and reflectance noise and of each ring's start azimuth.
        model: the sensor; `HDL64E` by default.

    Returns:
        The `ScanResult`, points in the SENSOR frame and in KITTI order (see the module docstring);
        rays that hit nothing within `model.max_range` are dropped.
    """
    pose = np.asarray(pose, dtype=np.float64)
    if pose.shape != (4, 4) or not np.all(np.isfinite(pose)):
        raise ValueError(f"simulate_scan: pose must be a finite (4, 4) matrix, got shape {pose.shape}")
    caster = scene if isinstance(scene, SceneCaster) else SceneCaster(scene)
    rng = np.random.default_rng(seed)
    start = rng.uniform(0.0, 2 * np.pi / model.azimuth_steps, model.beams)
    directions, ring = beam_directions(model, start)
    rotation, origin = pose[:3, :3], pose[:3, 3]
    world_directions = directions @ rotation.T
    distance, triangle, normal = caster.cast(origin, world_directions)
    keep = np.isfinite(distance) & (distance < model.max_range)
    measured = distance[keep] + rng.normal(scale=model.range_noise, size=int(keep.sum()))
    labels = caster.scene.labels[triangle[keep]].astype(np.int32)
    cos_incidence = np.abs(np.einsum("ij,ij->i", normal[keep], world_directions[keep]))
    reflectance = surface_reflectance(labels, cos_incidence, rng, model.reflectance_noise)
    points = np.empty((len(measured), 4), dtype=np.float32)
    points[:, :3] = directions[keep] * measured[:, None]
    points[:, 3] = reflectance
    normals = normal[keep] @ rotation  # world -> sensor frame
    normals *= np.where(np.einsum("ij,ij->i", normals, directions[keep]) > 0, -1.0, 1.0)[:, None]
    return ScanResult(points, ring[keep], labels, normals.astype(np.float32))


def surface_reflectance(labels: np.ndarray, cos_incidence: np.ndarray, rng: np.random.Generator,
                        noise: float = 0.02) -> np.ndarray:
    """(N,) reflectance in [0, 1]: the class's base reflectivity, weakened at grazing incidence
    (a Lambertian-like 0.3 + 0.7 cos term), plus Gaussian noise.

    Args:
        labels: (N,) semantic classes of `cadpu.synthetic.street`. cos_incidence: (N,) |cos| of the angle
        between ray and surface normal. rng: noise source. noise: noise standard deviation.
    """
    base = REFLECTIVITY[labels] * (0.3 + 0.7 * cos_incidence)
    return np.clip(base + rng.normal(scale=noise, size=len(labels)), 0.0, 1.0)


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
