"""Tests of stages.ground on synthetic scans whose ground is known point by point."""

from __future__ import annotations

import sys
from typing import Callable

import numpy as np
import pytest

from stages import ground
from stages.errors import InputError, StageError
from stages.frame import Frame
from stages.ground import GroundResult, PatchworkParams, PatchworkppParams, RansacParams

HEIGHT = 1.73
Surface = Callable[[np.ndarray, np.ndarray], np.ndarray]


def flat(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """The road plane under a KITTI sensor: z = -1.73 m everywhere."""
    return np.full_like(x, -HEIGHT)


def ring_scan(surface: Surface = flat, height: float = HEIGHT, beams: int = 48, azimuths: int = 720,
              seed: int = 0) -> np.ndarray:
    """Ground returns of a spinning LiDAR: beams at elevations -24.8..-1.5 degrees hit a level ground
    at ranges height / tan(-elevation) (3.7 m to 66 m for 1.73 m); each ring is sampled at
    `azimuths` angles and its points are lifted onto `surface(x, y)` with 1 cm noise.

    Returns:
        (beams * azimuths, 3) float64 points in the sensor frame, metres.
    """
    rng = np.random.default_rng(seed)
    elevation = np.radians(np.linspace(-24.8, -1.5, beams))
    radius = np.repeat(height / np.tan(-elevation), azimuths)
    angle = np.tile(np.linspace(-np.pi, np.pi, azimuths, endpoint=False), beams)
    angle = angle + rng.uniform(0, 2 * np.pi / azimuths, angle.shape)
    x, y = radius * np.cos(angle), radius * np.sin(angle)
    return np.c_[x, y, surface(x, y) + rng.normal(0, 0.01, x.shape)]


def box_faces(low: tuple[float, float, float], high: tuple[float, float, float], per_m2: float,
              seed: int = 1) -> np.ndarray:
    """Random points on the faces of an axis-aligned box (a car, a planter, a wall) that a sensor at
    the origin sees: the vertical faces turned towards it and the top; `per_m2` points per square
    metre; (M, 3)."""
    rng = np.random.default_rng(seed)
    spans = list(zip(low, high))
    faces = []
    for axis in range(3):
        (start, stop) = spans[axis]
        for value, visible in ((start, start > 0), (stop, stop < 0)):
            if not visible:
                continue
            face = [s if a != axis else (value, value) for a, s in enumerate(spans)]
            area = np.prod([b - a for a, b in face if b != a])
            count = max(int(area * per_m2), 1)
            faces.append(np.stack([rng.uniform(a, b, count) for a, b in face], axis=1))
    return np.concatenate(faces)


def outside_box(points: np.ndarray, low: tuple[float, float, float], high: tuple[float, float, float],
                margin: float = 0.0) -> np.ndarray:
    """(N,) bool: points whose x, y lie outside the box's footprint grown by `margin` metres."""
    inside = ((points[:, 0] > low[0] - margin) & (points[:, 0] < high[0] + margin)
              & (points[:, 1] > low[1] - margin) & (points[:, 1] < high[1] + margin))
    return ~inside


def precision_recall(mask: np.ndarray, truth: np.ndarray) -> tuple[float, float]:
    """Precision and recall (fractions) of a predicted ground mask against the true one."""
    hits = float((mask & truth).sum())
    return hits / max(int(mask.sum()), 1), hits / max(int(truth.sum()), 1)


def scan_with(ground_points: np.ndarray, *others: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Stack ground and non-ground points; returns (N, 4) float32 points (reflectance 0.5) and the
    (N,) true ground mask."""
    rest = np.concatenate(others) if others else np.zeros((0, 3))
    xyz = np.concatenate([ground_points, rest])
    truth = np.r_[np.ones(len(ground_points), bool), np.zeros(len(rest), bool)]
    return np.c_[xyz, np.full(len(xyz), 0.5)].astype(np.float32), truth


def assert_quality(points: np.ndarray, truth: np.ndarray, method: str = "patchwork",
                   floor: float = 0.97) -> GroundResult:
    """Segment and check precision and recall of the ground label (only points the zone model
    covers count: nearer than 2.7 m is the ego vehicle, farther than 80 m is never ground)."""
    result = ground.segment(points, method)
    assert result.mask.shape == (len(points),) and result.mask.dtype == bool
    precision, recall = precision_recall(result.mask, truth)
    assert precision >= floor, f"precision {precision:.3f}"
    assert recall >= floor, f"recall {recall:.3f}"
    return result


# --- the default method on street scenes --------------------------------------------------------


def test_flat_road_is_ground_and_its_planes_and_height_are_found() -> None:
    points, truth = scan_with(ring_scan())
    result = assert_quality(points, truth, floor=0.995)
    assert result.method == "patchwork" and result.elapsed_s > 0
    assert result.sensor_height == pytest.approx(HEIGHT, abs=0.03)
    assert result.planes.shape[1] == 4 and len(result.planes) > 100
    # Level planes 1.73 m below the sensor; a far bin crossed by one ring may tilt a little.
    assert (result.planes[:, 2] > 0.995).all()
    assert np.median(result.planes[:, 2]) > 0.9999
    assert np.median(result.planes[:, 3]) == pytest.approx(HEIGHT, abs=0.01)


def test_sensor_height_is_estimated_from_the_scan() -> None:
    def low_road(x: np.ndarray, y: np.ndarray) -> np.ndarray:
        return np.full_like(x, -2.2)

    points, truth = scan_with(ring_scan(low_road, height=2.2))
    result = assert_quality(points, truth)
    assert result.sensor_height == pytest.approx(2.2, abs=0.03)


def test_ramp_of_ten_percent_is_ground() -> None:
    def ramp(x: np.ndarray, y: np.ndarray) -> np.ndarray:
        return -HEIGHT + 0.1 * np.clip(x - 8.0, 0.0, None)  # climbs 10 cm per metre beyond x = 8 m

    points, truth = scan_with(ring_scan(ramp))
    assert points[:, 2].max() > 3.0  # the ramp rises far above the sensor's own height
    assert_quality(points, truth)


def test_sidewalk_behind_a_15_cm_kerb_is_ground() -> None:
    def kerb(x: np.ndarray, y: np.ndarray) -> np.ndarray:
        return -HEIGHT + np.where(y > 4.0, 0.15, 0.0)  # sidewalk on the left from y = 4 m

    points, truth = scan_with(ring_scan(kerb))
    result = assert_quality(points, truth)
    sidewalk = points[:, 1] > 4.0
    assert result.mask[sidewalk].mean() >= 0.97


def test_car_and_wall_standing_on_the_road_are_not_ground() -> None:
    car_low, car_high = (8.0, -3.0, -HEIGHT + 0.25), (12.5, -1.2, -HEIGHT + 1.5)
    wall_low, wall_high = (20.0, -10.0, -HEIGHT), (20.5, 10.0, -HEIGHT + 3.0)
    road = ring_scan()
    # No ground returns under the car and the wall, nor in the wall's shadow.
    shadow = (road[:, 0] > 20.0) & (np.abs(road[:, 1]) < 10.0 * road[:, 0] / 20.0)
    road = road[outside_box(road, car_low, car_high) & outside_box(road, wall_low, wall_high) & ~shadow]
    car = box_faces(car_low, car_high, per_m2=400)
    wall = box_faces(wall_low, wall_high, per_m2=100)
    points, truth = scan_with(road, car, wall)
    result = assert_quality(points, truth)
    n_road = len(road)
    car_mask = result.mask[n_road:n_road + len(car)]
    wall_mask = result.mask[n_road + len(car):]
    assert car_mask.mean() < 0.02
    assert wall_mask.mean() < 0.05  # only the wall's foot, within about 12.5 cm of the road
    # Its plane fit tilts up towards the wall; the vertical-structure check drops what it lifts.
    assert wall_mask[wall[:, 2] > -HEIGHT + 0.15].mean() < 0.012


def test_low_obstacle_is_not_ground() -> None:
    low, high = (6.0, 1.0, -HEIGHT), (7.0, 3.0, -HEIGHT + 0.4)  # a 40 cm planter box
    road = ring_scan()
    road = road[outside_box(road, low, high)]
    planter = box_faces(low, high, per_m2=1500)
    points, truth = scan_with(road, planter)
    result = assert_quality(points, truth)
    top = result.mask[len(road):][planter[:, 2] > -HEIGHT + 0.2]
    assert top.mean() < 0.02


def test_reflections_below_the_road_are_not_ground() -> None:
    rng = np.random.default_rng(5)
    count = 600
    radius, angle = rng.uniform(4.0, 40.0, count), rng.uniform(-np.pi, np.pi, count)
    depth = rng.uniform(0.4, 2.5, count)  # multi-path returns appear below the road surface
    below = np.c_[radius * np.cos(angle), radius * np.sin(angle), -HEIGHT - depth]
    points, truth = scan_with(ring_scan(), below)
    result = assert_quality(points, truth)
    assert not result.mask[-count:].any()
    assert result.sensor_height == pytest.approx(HEIGHT, abs=0.05)


def test_points_outside_the_zone_model_are_never_ground() -> None:
    near = np.c_[np.full(50, 1.0), np.linspace(-1, 1, 50), np.full(50, -HEIGHT)]  # on the ego car's roof line
    far = np.c_[np.full(50, 95.0), np.linspace(-5, 5, 50), np.full(50, -HEIGHT)]
    points, _ = scan_with(ring_scan(), near, far)
    mask = ground.segment(points).mask
    assert not mask[-100:].any()


def test_empty_and_tiny_scans() -> None:
    for method in ("patchwork", "ransac"):
        result = ground.segment(np.zeros((0, 4), np.float32), method)
        assert result.mask.shape == (0,) and result.planes.shape == (0, 4) and result.method == method
    one = ground.segment(np.array([[5.0, 0.0, -HEIGHT]]))
    assert one.mask.shape == (1,)
    assert one.sensor_height == PatchworkParams().sensor_height  # too few points: the prior


def test_extra_columns_and_dtypes_do_not_change_the_result() -> None:
    xyz = ring_scan(azimuths=360)
    with_reflectance = np.c_[xyz, np.linspace(0, 1, len(xyz)), np.ones(len(xyz))]
    np.testing.assert_array_equal(ground.segment(xyz).mask, ground.segment(with_reflectance).mask)
    assert ground.segment(xyz.astype(np.float32)).mask.mean() > 0.99


def test_parameters_change_the_outcome() -> None:
    def kerb(x: np.ndarray, y: np.ndarray) -> np.ndarray:
        return -HEIGHT + np.where(y > 4.0, 0.6, 0.0)  # a 60 cm step: a wall top, not a kerb

    points, _ = scan_with(ring_scan(kerb))
    raised = points[:, 1] > 8.0
    assert ground.segment(points).mask[raised].mean() < 0.1
    lenient = PatchworkParams(max_step=1.0, seed_margin=0.8, distance_threshold=0.125)
    assert ground.segment(points, "patchwork", lenient).mask[raised].mean() > 0.9


# --- input checks, parameters, the other methods -------------------------------------------------


@pytest.mark.parametrize("bad", [np.zeros((10, 2)), np.zeros(30), np.zeros((2, 3, 3)), np.array([["a", "b", "c"]])])
def test_wrong_shapes_and_dtypes_raise_input_error(bad: np.ndarray) -> None:
    with pytest.raises(InputError) as error:
        ground.segment(bad)
    assert error.value.stage == "ground"


def test_a_transposed_scan_is_refused_not_labelled_as_a_few_points() -> None:
    points = ring_scan(azimuths=36)
    with pytest.raises(InputError, match=r"got shape \(3, \d+\): transposed\? \(give points.T\)"):
        ground.segment(points.T.copy())
    assert len(ground.segment(points[:5, :]).mask) == 5  # a tiny scan is not taken for a transposed one
    assert len(ground.segment(np.zeros((20, 18))).mask) == 20  # nor one with many attribute columns


def test_non_finite_points_raise_input_error_naming_the_row() -> None:
    points = ring_scan(azimuths=36)
    points[7, 2] = np.nan
    with pytest.raises(InputError, match="row 7"):
        ground.segment(points)


def test_params_class() -> None:
    assert ground.params_class("patchwork") is PatchworkParams
    assert ground.params_class("ransac") is RansacParams
    assert ground.params_class("patchworkpp") is PatchworkppParams
    assert set(ground.GROUND_METHODS) == {"patchwork", "ransac", "patchworkpp"}
    with pytest.raises(ValueError, match="'nope'.*patchwork, ransac, patchworkpp"):
        ground.params_class("nope")
    with pytest.raises(ValueError):
        ground.segment(ring_scan(azimuths=36), "nope")
    with pytest.raises(TypeError, match="RansacParams"):
        ground.segment(ring_scan(azimuths=36), "ransac", PatchworkParams())


def test_params_validate_from_plain_dicts() -> None:
    pydantic = pytest.importorskip("pydantic")
    params = pydantic.TypeAdapter(PatchworkParams).validate_python({"max_step": 0.3, "zone_edges": [2.7, 30, 80],
                                                                    "rings_per_zone": [3, 3],
                                                                    "sectors_per_zone": [16, 32]})
    assert params.max_step == 0.3 and params.zone_edges == (2.7, 30.0, 80.0)
    with pytest.raises(ValueError):
        PatchworkParams(zone_edges=(2.7, 80.0), rings_per_zone=(2, 2), sectors_per_zone=(16,))
    with pytest.raises(ValueError):
        PatchworkParams(zone_edges=(10.0, 5.0), rings_per_zone=(2,), sectors_per_zone=(16,))


def test_a_bad_ground_parameter_is_named_with_its_method_s_own_check() -> None:
    # the parameter class's own check has no key in pydantic's location: "ground.params.: Value error, ..."
    with pytest.raises(ValueError, match=r"ground\.params: distance_threshold must be > 0") as raised:
        ground.Options(method="ransac", params={"distance_threshold": -1})
    assert "ground.params.:" not in str(raised.value) and "Value error, ground" in str(raised.value)
    with pytest.raises(ValueError, match=r"ground\.params\.distance_threshold: Input should be a valid number"):
        ground.Options(method="ransac", params={"distance_threshold": "x"})


def test_custom_zone_layout_still_finds_the_road() -> None:
    params = PatchworkParams(zone_edges=(2.7, 30.0, 80.0), rings_per_zone=(6, 5), sectors_per_zone=(24, 48))
    points, truth = scan_with(ring_scan())
    precision, recall = precision_recall(ground.segment(points, "patchwork", params).mask, truth)
    assert precision >= 0.99 and recall >= 0.99


def test_ransac_finds_the_single_road_plane() -> None:
    car_low, car_high = (8.0, -3.0, -HEIGHT + 0.25), (12.5, -1.2, -HEIGHT + 1.5)
    road = ring_scan(beams=24, azimuths=240)
    road = road[outside_box(road, car_low, car_high)]
    points, truth = scan_with(road, box_faces(car_low, car_high, per_m2=100))
    result = assert_quality(points, truth, method="ransac", floor=0.95)
    assert result.planes.shape == (1, 4)
    np.testing.assert_allclose(result.planes[0, :3], [0, 0, 1], atol=0.01)
    assert result.sensor_height == pytest.approx(HEIGHT, abs=0.05)
    strict = ground.segment(points, "ransac", RansacParams(distance_threshold=0.005))
    assert strict.mask.sum() < 0.6 * result.mask.sum()  # 1 cm noise: a 5 mm band holds fewer


def test_patchworkpp_labels_a_flat_road() -> None:
    pytest.importorskip("pypatchworkpp")
    points, truth = scan_with(ring_scan())
    result = ground.segment(points, "patchworkpp")
    precision, recall = precision_recall(result.mask, truth)
    assert precision >= 0.97 and recall >= 0.9
    assert result.method == "patchworkpp" and result.planes.shape == (0, 4)


def test_patchworkpp_missing_package_names_the_extra(monkeypatch: pytest.MonkeyPatch) -> None:
    import builtins

    real_import = builtins.__import__

    def no_patchwork(name: str, *args: object, **kwargs: object) -> object:
        if name == "pypatchworkpp":
            raise ImportError(name)
        return real_import(name, *args, **kwargs)

    monkeypatch.setattr(builtins, "__import__", no_patchwork)
    with pytest.raises(StageError, match=r'pip install "kitti-pu\[patchwork\]"'):
        ground.segment(ring_scan(azimuths=36), "patchworkpp")


def test_run_fills_the_frame() -> None:
    points, truth = scan_with(ring_scan(azimuths=360))
    frame = Frame(points=points, dataset="bin", sequence="demo", index=3, source="demo/000003.bin",
                  timings={"load": 0.5})
    out = ground.run(frame, ground.Options(method="patchwork"))
    assert out.ground is not None and out.ground.shape == (len(points),)
    assert precision_recall(out.ground, truth) >= (0.97, 0.97)
    assert out.timings == {"load": 0.5}
    assert frame.ground is None  # the input frame is left as it was


def test_run_notes_a_frame_without_ground_and_says_what_the_methods_expect() -> None:
    # a scan with its origin moved to the road (z + 1.73, as in a vehicle's base frame) gave no
    # ground, no fill and most of the network's points dropped, without a note (a library user's trial)
    points, _ = scan_with(ring_scan(azimuths=360))
    def frame(xyz: np.ndarray) -> Frame:
        return Frame(points=xyz, dataset="bin", sequence="lifted", index=0, source="lifted/000000.bin")

    assert not any(note.startswith("ground:") for note in ground.run(frame(points)).notes)
    lifted = points.copy()
    lifted[:, 2] += HEIGHT
    out = ground.run(frame(lifted))
    assert not out.ground.any()
    assert [note for note in out.notes if note.startswith("ground:")] == [
        f"ground: no ground found among {len(points)} points, so none is filled and ring snapping keeps fewer new "
        "points; the ground methods take points in the sensor frame (origin at the sensor, z up, metres, the "
        "ground below it): were they moved into another frame or scaled?"]
    few = lifted[:ground.NO_GROUND_NOTE_POINTS - 1]  # a fragment (a crop, a test scene) is not noted
    assert not ground.run(frame(few)).notes


def test_run_names_the_frame_file_on_bad_points() -> None:
    points = np.c_[ring_scan(azimuths=36), np.zeros(48 * 36)].astype(np.float32)
    points[3, 0] = np.inf
    frame = Frame(points=points, dataset="bin", sequence="demo", index=0, source="demo/000000.bin")
    with pytest.raises(InputError) as error:
        ground.run(frame)
    assert error.value.source == "demo/000000.bin" and error.value.stage == "ground"


def test_ransac_without_open3d_names_the_extra(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setitem(sys.modules, "cadpu.o3d", None)  # how Python marks a module that cannot be imported
    with pytest.raises(StageError, match=r'ransac.*pip install "kitti-pu\[open3d\]"'):
        ground.segment(ring_scan(azimuths=36), "ransac")


@pytest.mark.parametrize("points", [np.zeros((100, 3)), np.column_stack([np.arange(100.0), np.zeros(100), np.zeros(100)])])
def test_ransac_on_points_without_a_plane_finds_none(points: np.ndarray) -> None:
    # a NaN plane and a NaN sensor height, with a RuntimeWarning (a review)
    result = ground.segment(points, method="ransac")
    assert result.planes.shape == (0, 4) and result.sensor_height is None and not result.mask.any()


@pytest.mark.parametrize("params, message", [
    (lambda: RansacParams(ransac_n=0), "ransac_n must be at least 3"),  # Open3D's coloured RuntimeError before
    (lambda: RansacParams(distance_threshold=-0.2), "distance_threshold must be > 0"),  # no ground, silently
    (lambda: RansacParams(num_iterations=0), "num_iterations must be at least 1"),
    (lambda: PatchworkppParams(th_dist=0.0), "th_dist must be > 0"),
    (lambda: PatchworkppParams(min_range=90.0), "min_range < max_range"),
])
def test_ground_parameters_that_cannot_work_are_refused(params: Callable[[], object], message: str) -> None:
    with pytest.raises(ValueError, match=message):
        params()
