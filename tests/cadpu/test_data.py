import numpy as np

from cadpu.data import DataSpec, build_patches, curvature_adaptive_subset, load_or_build, scanline_input
from cadpu.synthetic.shapes import FAMILIES, random_mesh, sample_surface


def test_every_family_gives_a_closed_sized_mesh() -> None:
    for family in FAMILIES:
        mesh = random_mesh(7, family)
        assert mesh.triangles.max() < len(mesh.vertices)
        assert mesh.triangle_areas().sum() > 0


def test_patches_are_deterministic_and_normalized(tmp_path) -> None:
    spec = DataSpec(meshes=2, patches_per_mesh=2, scanline_share=0.5)
    first = load_or_build(spec, tmp_path, progress=False)
    again = build_patches(spec)
    assert first.inputs.shape == (4, 256, 3) and first.truth.shape == (4, 1024, 3)
    np.testing.assert_array_equal(first.inputs, again.inputs)
    assert np.abs(np.linalg.norm(first.inputs, axis=2).max(axis=1) - 1).max() < 1e-5
    np.testing.assert_allclose(np.linalg.norm(first.truth_normals, axis=2), 1, atol=1e-4)
    assert (tmp_path / f"patches-{spec.key()}.npz").is_file()


def test_curvature_adaptive_subset_prefers_high_curvature() -> None:
    rng = np.random.default_rng(0)
    kappa = np.zeros(50_000)
    kappa[:5000] = 0.3  # a tenth of the points, each ~27x more likely to be drawn
    picked = curvature_adaptive_subset(kappa, 1024, rng)
    share_high = (picked < 5000).mean()
    expected = 5000 * np.log(1.31) / (5000 * np.log(1.31) + 45_000 * np.log(1.01))
    assert len(set(picked)) == 1024
    assert abs(share_high - expected) < 0.04


def _vertical_share_of_nearest_neighbour(points: np.ndarray) -> float:
    """Mean |dz| / |d| of each point's nearest-neighbour vector: ~0.6 when isotropic, low on rows."""
    from scipy.spatial import cKDTree

    _, index = cKDTree(points).query(points, k=2)
    offsets = points[index[:, 1]] - points
    return float(np.mean(np.abs(offsets[:, 2]) / np.linalg.norm(offsets, axis=1)))


def test_scanline_input_is_rows_of_points() -> None:
    scan_shares, uniform_shares = [], []
    for seed in range(6):
        rng = np.random.default_rng(seed)
        wall = np.c_[rng.uniform(0, 1, 10_000), np.zeros(10_000), rng.uniform(0, 1, 10_000)]
        scan_shares.append(_vertical_share_of_nearest_neighbour(scanline_input(wall, 256, rng)))
        uniform_shares.append(_vertical_share_of_nearest_neighbour(wall[rng.choice(10_000, 256, replace=False)]))
    assert np.mean(scan_shares) < np.mean(uniform_shares) - 0.15


def test_uniform_surface_samples_lie_on_the_mesh() -> None:
    mesh = random_mesh(3, "sharp")
    points, normals = sample_surface(mesh, 1000, np.random.default_rng(0))
    from cadpu.metrics import point_to_surface

    assert point_to_surface(points, mesh.vertices, mesh.triangles).max() < 1e-4


def test_street_scans_add_scan_line_patches() -> None:
    spec = DataSpec(meshes=1, patches_per_mesh=2, scanline_share=0.0, streets=1, scans_per_street=1,
                    patches_per_scan=3)
    patches = build_patches(spec)
    assert patches.inputs.shape == (5, 256, 3) and patches.truth.shape == (5, 1024, 3)
    assert patches.scanline.tolist() == [False, False, True, True, True]
    assert spec.key() != DataSpec(meshes=1, patches_per_mesh=2, scanline_share=0.0).key()


def test_cache_names_change_with_the_simulated_sensor_only_where_it_is_used() -> None:
    long_run = dict(meshes=0, streets=100, scans_per_street=4, patches_per_scan=20, scan_vertical_scale=0.15)
    # names of caches made before DataSpec.sensor existed (commit 38c710c): kept for meshes and the clean sensor
    assert DataSpec().key() == DataSpec(sensor="clean").key() == "6b88b7916764"
    assert DataSpec(**long_run, sensor="clean").key() == "1daeb472d506"
    assert DataSpec(**long_run).key() not in ("1daeb472d506", DataSpec(**long_run, sensor="clean").key())
    try:
        DataSpec(sensor="ideal")
    except ValueError as error:
        assert "sensor" in str(error)
    else:
        raise AssertionError("an unknown sensor was accepted")


def test_street_patches_differ_between_the_measured_and_the_clean_sensor() -> None:
    spec = dict(meshes=0, streets=1, scans_per_street=1, patches_per_scan=2)
    measured, clean = build_patches(DataSpec(**spec)), build_patches(DataSpec(**spec, sensor="clean"))
    assert measured.inputs.shape == clean.inputs.shape == (2, 256, 3)
    assert not np.array_equal(measured.inputs, clean.inputs)


def test_streets_cycle_through_the_scene_types_and_urban_alone_keeps_its_names() -> None:
    spec = dict(meshes=0, streets=2, scans_per_street=1, patches_per_scan=2, first_seed=7)
    urban = DataSpec(**spec)
    assert DataSpec(**spec, scene_types=["urban"]).key() == urban.key()  # YAML gives lists
    mixed = DataSpec(**spec, scene_types=["urban", "open"])
    assert mixed.key() != urban.key() and mixed.scene_types == ("urban", "open")
    # street 0 (seed 7) is urban in both sets; street 1 (seed 8) is an open area in the mixed one
    alone, with_types = build_patches(urban), build_patches(mixed)
    assert np.array_equal(alone.inputs[:2], with_types.inputs[:2])
    assert not np.array_equal(alone.inputs[2:], with_types.inputs[2:len(alone)])
    for bad in ([], ["forest"]):
        try:
            DataSpec(**spec, scene_types=bad)
        except ValueError as error:
            assert "scene_types" in str(error)
        else:
            raise AssertionError(f"scene_types {bad} were accepted")


def test_the_set_is_the_same_whatever_the_number_of_processes() -> None:
    spec = DataSpec(meshes=3, patches_per_mesh=4, streets=2, scans_per_street=1, patches_per_scan=5,
                    scan_vertical_scale=0.15)
    alone, shared = build_patches(spec), build_patches(spec, workers=2)
    assert len(alone) == 3 * 4 + 2 * 5
    for name in ("inputs", "truth", "truth_normals", "scanline"):
        assert np.array_equal(getattr(alone, name), getattr(shared, name)), name


def test_street_sets_keep_their_frames_and_a_cache_made_without_them_is_made_again(tmp_path) -> None:
    spec = DataSpec(meshes=0, streets=1, scans_per_street=1, patches_per_scan=3, scan_vertical_scale=0.15)
    made = load_or_build(spec, tmp_path, progress=False)
    assert made.frames is not None and len(made.frames) == len(made) == 3
    read = load_or_build(spec, tmp_path, progress=False)
    for name in ("centroid", "truth_ring", "ring_elevations"):
        np.testing.assert_array_equal(getattr(read.frames, name), getattr(made.frames, name))
    # a cache written before the frames were kept: its pairs, and now their frames
    path = tmp_path / f"patches-{spec.key()}.npz"
    np.savez(path, inputs=made.inputs, truth=made.truth, truth_normals=made.truth_normals, scanline=made.scanline)
    again = load_or_build(spec, tmp_path, progress=False)
    assert again.frames is not None
    np.testing.assert_array_equal(again.truth, made.truth)
    # mesh sets have none
    assert load_or_build(DataSpec(meshes=1, patches_per_mesh=2), tmp_path, progress=False).frames is None
