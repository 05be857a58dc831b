"""Stage 2, ground: label every point of a scan ground or not.

Reads `Frame.points`; adds `Frame.ground` ((N,) bool). Stand-alone use: `segment(points)` on any
(N, 3+) float array.

Methods, chosen by name (`segment(points, method, params)`, `ground.method` in the config):
- "patchwork" (default): zone-based local plane fitting over a concentric polar grid, in the
  Patchwork family (Lim et al. 2021; Lee et al. 2022), pure numpy and vectorised over all bins;
  see `stages.ground_patchwork` for the algorithm;
- "ransac": the single largest plane, through Open3D's RANSAC `segment_plane` (the optional
  `open3d` extra: `pip install "kitti-pu[open3d]"`); good enough on flat open roads, wrong on
  slopes, kerbs and beside large walls;
- "patchworkpp": Patchwork++ itself through the optional `pypatchworkpp` package
  (`pip install "kitti-pu[patchwork]"`).

Assumptions shared by all methods: points are in the sensor frame (x forward, y left, z up,
metres) and the sensor is roughly level, mounted above the ground it drives on (KITTI: 1.73 m;
"patchwork" estimates the height from each scan). Ground is what a vehicle could drive or walk on:
road, parking, lane markings, sidewalks and kerbs, terrain (SemanticKITTI classes 40, 44, 48, 49,
60, 72). Low obstacles and points below the road surface (multi-path reflections) are not ground.
"""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np
import pydantic
from pydantic import Field, model_validator

from .errors import InputError, StageError
from .frame import Frame, looks_transposed, stage_inputs
from .ground_patchwork import PatchworkParams, estimate
from .options import StageOptions
from .wording import counted

__all__ = ["GROUND_METHODS", "GroundResult", "Options", "PatchworkParams", "PatchworkppParams", "RansacParams",
           "params_class", "run", "segment"]

GROUND_METHODS = ("patchwork", "ransac", "patchworkpp")


@dataclass(frozen=True)
class RansacParams:
    """Parameters of the single-plane RANSAC method (Open3D `PointCloud.segment_plane`).

    Attributes:
        distance_threshold: largest point-to-plane distance of a ground point, metres.
        ransac_n: points drawn per plane hypothesis.
        num_iterations: plane hypotheses tried.
        seed: seed of Open3D's random generator. Open3D samples in parallel threads, so runs
            with the same seed can still differ by a few points.
    """

    distance_threshold: float = 0.2
    ransac_n: int = 3
    num_iterations: int = 200
    seed: int = 0

    def __post_init__(self) -> None:
        # Open3D raised a coloured RuntimeError for ransac_n < 3, and a threshold <= 0 or no
        # iterations labelled no point ground, silently
        if not self.distance_threshold > 0:
            raise ValueError(f"distance_threshold must be > 0 (metres), got {self.distance_threshold}")
        if self.ransac_n < 3:
            raise ValueError(f"ransac_n must be at least 3 (points that span a plane), got {self.ransac_n}")
        if self.num_iterations < 1:
            raise ValueError(f"num_iterations must be at least 1, got {self.num_iterations}")


@dataclass(frozen=True)
class PatchworkppParams:
    """Parameters passed to Patchwork++ (`pypatchworkpp.Parameters`); the rest keep its defaults.

    Attributes:
        sensor_height: sensor height above the ground, metres.
        th_dist: largest point-to-plane distance of a ground point, metres.
        min_range, max_range: horizontal range of the zone model, metres.
    """

    sensor_height: float = 1.723
    th_dist: float = 0.125
    min_range: float = 2.7
    max_range: float = 80.0

    def __post_init__(self) -> None:
        if not self.th_dist > 0:
            raise ValueError(f"th_dist must be > 0 (metres), got {self.th_dist}")
        if not 0 <= self.min_range < self.max_range:
            raise ValueError(f"min_range and max_range must satisfy 0 <= min_range < max_range (metres), "
                             f"got {self.min_range} and {self.max_range}")


@dataclass(frozen=True)
class GroundResult:
    """What a ground method found.

    Attributes:
        mask: (N,) bool, True for ground.
        planes: (Z, 4) float64 plane coefficients [a, b, c, d] (a x + b y + c z + d = 0, unit
            normal with c > 0) of each ground bin (one row for ransac; empty for patchworkpp).
        sensor_height: metres above the ground, as estimated; the method's assumed height
            (`PatchworkParams.sensor_height`) when the scan's near points give no estimate within
            its bounds, as with too few points or coordinates not in metres; None when the method
            has none.
        elapsed_s: seconds spent.
        method: the method's name.
    """

    mask: np.ndarray
    planes: np.ndarray
    sensor_height: float | None
    elapsed_s: float
    method: str


def params_class(method: str) -> type | None:
    """The parameter dataclass of a ground method (None for a method without parameters).

    Raises:
        ValueError: `method` is not one of `GROUND_METHODS`; the message lists the known ones.
    """
    classes: dict[str, type | None] = {
        "patchwork": PatchworkParams, "ransac": RansacParams, "patchworkpp": PatchworkppParams}
    if method not in classes:
        raise ValueError(f"unknown ground method {method!r}; known: {', '.join(GROUND_METHODS)}")
    return classes[method]


def _check_points(points: Any) -> np.ndarray:
    """The (N, 3+) input as a real array; raises InputError for a wrong shape, dtype or non-finite xyz."""
    array = np.asarray(points)
    if array.ndim != 2 or array.shape[1] < 3:
        raise InputError("ground", "points", f"expected an (N, 3+) array of x, y, z, ..., got shape {array.shape}")
    if looks_transposed(array.shape):
        # a (4, N) scan passed for an (N, 4) one gave a mask of 4 points (a trial)
        raise InputError("ground", "points", f"expected an (N, 3+) array of x, y, z, ... (one row per point), got "
                                             f"shape {array.shape}: transposed? (give points.T)")
    if array.dtype == bool or not (np.issubdtype(array.dtype, np.floating) or np.issubdtype(array.dtype, np.integer)):
        raise InputError("ground", "points", f"expected real numbers, got dtype {array.dtype}")
    if not np.isfinite(array[:, :3]).all():
        bad = ~np.isfinite(array[:, :3]).all(axis=1)
        raise InputError("ground", "points", f"{int(bad.sum())} point(s) with NaN or infinite coordinates, "
                                             f"first at row {int(np.argmax(bad))}")
    return array


def _check_params(method: str, params: object | None) -> object | None:
    """The method's parameters: defaults for None; raises TypeError for another class's object."""
    cls = params_class(method)
    if params is None:
        return cls() if cls is not None else None
    if cls is None or not isinstance(params, cls):
        expected = cls.__name__ if cls is not None else "None"
        raise TypeError(f"ground method {method!r} takes {expected} parameters, got {type(params).__name__}")
    return params


def segment(points: np.ndarray, method: str = "patchwork", params: object | None = None) -> GroundResult:
    """Label the ground points of one scan.

    Args:
        points: (N, 3+) real array, x, y, z in the sensor frame (z up, metres); further columns
            are ignored except by "patchworkpp", which reads column 3 as reflectance.
        method: one of `GROUND_METHODS`.
        params: the method's parameter dataclass (`params_class(method)`); None for its defaults.

    Returns:
        The `GroundResult`: (N,) mask, fitted planes, sensor height, seconds spent. N == 0 gives
        an empty mask.

    Raises:
        InputError: wrong shape or dtype, NaN or infinite coordinates.
        ValueError: unknown method. TypeError: parameters of another method.
        StageError: "patchworkpp" without `pypatchworkpp` installed, "ransac" without Open3D.
    """
    params = _check_params(method, params)
    array = _check_points(points)
    started = time.perf_counter()
    if len(array) == 0:
        return GroundResult(np.zeros(0, dtype=bool), np.zeros((0, 4)), None, 0.0, method)
    if method == "patchwork":
        mask, planes, height = estimate(array, params)  # type: ignore[arg-type]
    elif method == "ransac":
        mask, planes, height = _ransac(array[:, :3].astype(np.float64), params)  # type: ignore[arg-type]
    else:
        mask, planes, height = _patchworkpp(array, params)  # type: ignore[arg-type]
    return GroundResult(mask, planes, height, time.perf_counter() - started, method)


class Options(StageOptions):
    """Ground removal: the method and its parameters (keys of `params_class(method)`; the
    method's own defaults for keys not given)."""

    method: Literal["patchwork", "ransac", "patchworkpp"] = "patchwork"
    params: dict[str, Any] = Field(default_factory=dict)

    @model_validator(mode="after")
    def _check_params(self) -> "Options":
        self.method_params()
        return self

    def method_params(self) -> object | None:
        """The method's parameter object built from `params` (None for a method without any).

        Raises:
            ValueError: naming an unknown key or a bad value (as `ground.params.KEY`).
        """
        params_type = params_class(self.method)
        if params_type is None:
            if self.params:
                raise ValueError(f"ground.params: method {self.method!r} takes no parameters, got {sorted(self.params)}")
            return None
        known = {f.name for f in dataclasses.fields(params_type)}
        unknown = sorted(set(self.params) - known)
        if unknown:
            raise ValueError(f"ground.params: unknown key(s) {unknown} for method {self.method!r}; "
                             f"known: {sorted(known)}")
        try:
            return pydantic.TypeAdapter(params_type).validate_python(self.params)
        except pydantic.ValidationError as error:
            first = error.errors()[0]
            # a check of the parameter class's own (__post_init__) has no key in its location, and
            # names the key in its message: "ground.params.: Value error, distance_threshold ..."
            where = ".".join(["ground.params", *(str(part) for part in first["loc"])])
            message = first["msg"].removeprefix("Value error, ")
            raise ValueError(f"{where}: {message}") from None


#: A frame of at least this many points in which no ground is found gets a note (`run`): a scan of
#: a street always holds ground, and points not in the sensor frame (its origin moved to the ground
#: or into a map, or millimetres) gave none without a word (a library user's trial).
NO_GROUND_NOTE_POINTS = 1000


def run(frame: Frame, options: Options = Options()) -> Frame:
    """The ground stage: label the frame's ground points with `segment`.

    Reads: points (N, 4), sensor frame. Adds: ground ((N,) bool), and a note when a frame of at
    least `NO_GROUND_NOTE_POINTS` points has none.

    Raises:
        InputError: bad points, naming the frame's source file.
    """
    frame, options = stage_inputs(frame, options, Options, "ground")
    try:
        result = segment(frame.points, options.method, options.method_params())
    except InputError as error:
        raise InputError("ground", frame.source or frame.key, error.reason) from None
    frame = frame.with_stage_result(ground=result.mask)
    if len(result.mask) >= NO_GROUND_NOTE_POINTS and not result.mask.any():
        frame = frame.with_note(f"ground: no ground found among {counted(len(result.mask), 'point')}, so none is "
                                "filled and ring snapping keeps fewer new points; the ground methods take points "
                                "in the sensor frame (origin at the sensor, z up, metres, the ground below it): were "
                                "they moved into another frame or scaled?")
    return frame


def _ransac(xyz: np.ndarray, p: RansacParams) -> tuple[np.ndarray, np.ndarray, float | None]:
    """Inliers of the largest plane (Open3D RANSAC); returns mask, its plane (1, 4) with unit
    normal, c >= 0, and the sensor height above it (None for too few points)."""
    try:
        from cadpu.o3d import o3d
    except ImportError:
        raise StageError("ground", "ransac", "the ground method 'ransac' needs Open3D, the optional "
                                             'open3d extra: pip install "kitti-pu[open3d]"') from None

    mask = np.zeros(len(xyz), dtype=bool)
    if len(xyz) < max(p.ransac_n, 3):
        return mask, np.zeros((0, 4)), None
    o3d.utility.random.seed(p.seed)
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(xyz))
    plane, inliers = cloud.segment_plane(p.distance_threshold, p.ransac_n, p.num_iterations)
    plane = np.asarray(plane, dtype=np.float64)
    length = float(np.linalg.norm(plane[:3]))
    if not np.isfinite(plane).all() or length == 0.0:  # degenerate points (all one, or on a line): no plane
        return mask, np.zeros((0, 4)), None
    plane /= length * (1.0 if plane[2] >= 0 else -1.0)
    mask[np.asarray(inliers, dtype=np.int64)] = True
    # Distance of the sensor (the origin) above the plane, with the normal pointing up.
    return mask, plane[None], float(plane[3])


def _patchworkpp(points: np.ndarray, p: PatchworkppParams) -> tuple[np.ndarray, np.ndarray, float | None]:
    """Patchwork++'s ground mask of (N, 3+) points (column 3, when present, is reflectance); no
    planes; its sensor height (the configured one).

    A fresh estimator per call: Patchwork++ adapts its thresholds from frame to frame, which would
    make a frame's labels depend on which frames the same worker saw before, and it is not safe to
    share between threads.
    """
    try:
        import pypatchworkpp
    except ImportError:
        raise StageError("ground", "patchworkpp", "the ground method 'patchworkpp' needs the optional package "
                                                  'pypatchworkpp: pip install "kitti-pu[patchwork]"') from None
    parameters = pypatchworkpp.Parameters()
    parameters.sensor_height = p.sensor_height
    parameters.th_dist = p.th_dist
    parameters.min_range = p.min_range
    parameters.max_range = p.max_range
    parameters.verbose = False
    estimator = pypatchworkpp.patchworkpp(parameters)
    cloud = np.zeros((len(points), 4), dtype=np.float32)
    cloud[:, : min(points.shape[1], 4)] = points[:, :4]
    estimator.estimateGround(cloud)
    mask = np.zeros(len(points), dtype=bool)
    mask[np.asarray(estimator.getGroundIndices(), dtype=np.int64)] = True
    return mask, np.zeros((0, 4)), float(estimator.getHeight())
