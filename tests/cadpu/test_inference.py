from pathlib import Path

import numpy as np
import pytest
import torch

from cadpu.baseline import upsample_patches as baseline_patches
from cadpu.geometry import normalize_to_unit_sphere
from cadpu.inference import (ADAPTIVE_OFFSET_SCALE, ADAPTIVE_OVERSAMPLE, DEFAULT_BATCH_SIZE, DEFAULT_CUDA_BATCH_SIZE,
                             MAX_OFFSET_SCALE, MAX_OVERSAMPLE, Upsampler, passes_for)
from cadpu.network import Generator
from cadpu.weights import (DEFAULT_WEIGHTS, LIDAR_UNIFORM_WEIGHTS, LIDAR_WEIGHTS, UNIFORM_WEIGHTS, WeightsError,
                           resolve, save, twin)


def _sphere_patches(count: int, seed: int = 0) -> tuple[np.ndarray, float]:
    """Patches of 256 points on a sphere of radius 1 cut into caps, normalised; returns the patches
    and each patch's scale so distances can be mapped back."""
    rng = np.random.default_rng(seed)
    patches = []
    for _ in range(count):
        centre = rng.normal(size=3)
        centre /= np.linalg.norm(centre)
        points = rng.normal(size=(2048, 3))  # caps of 1/8 of the sphere, like the test protocol
        points /= np.linalg.norm(points, axis=1, keepdims=True)
        cap = points[np.argsort(np.linalg.norm(points - centre, axis=1))[:256]]
        patches.append(cap)
    return np.stack(patches), 1.0


def _distance_to_sphere(patches: np.ndarray, outputs: np.ndarray) -> float:
    """Mean |‖p‖ - 1| of outputs mapped back from each input patch's normalisation."""
    total = []
    for patch, out in zip(patches, outputs):
        centroid = patch.mean(0)
        scale = np.linalg.norm(patch - centroid, axis=1).max()
        world = out * scale + centroid
        total.append(np.abs(np.linalg.norm(world, axis=1) - 1.0).mean())
    return float(np.mean(total))


def _normalized(patches: np.ndarray) -> np.ndarray:
    normalized, _, _ = normalize_to_unit_sphere(torch.from_numpy(patches))
    return normalized.numpy().astype(np.float32)


@pytest.mark.parametrize("path", [DEFAULT_WEIGHTS, UNIFORM_WEIGHTS, LIDAR_WEIGHTS, LIDAR_UNIFORM_WEIGHTS])
def test_shipped_weights_load_with_their_checksum(path: Path) -> None:
    upsampler = Upsampler(path)
    assert upsampler.ratio == 4
    assert len(upsampler.checksum) == 64
    assert upsampler.meta["steps"] > 0


def test_shipped_weights_upsample_a_sphere_closer_to_it_than_the_baseline() -> None:
    patches, _ = _sphere_patches(4)
    inputs = _normalized(patches)
    ours, parents = Upsampler().upsample_patches(inputs)
    theirs, _ = baseline_patches(inputs, 4)
    assert ours.shape == (4, 1024, 3) and parents.shape == (4, 1024)
    assert _distance_to_sphere(patches, ours) < _distance_to_sphere(patches, theirs)
    # and it fills the surface in: the patch area is nearer to the output than to the input alone
    from scipy.spatial import cKDTree

    dense = np.random.default_rng(1).uniform(-0.5, 0.5, size=(4000, 2))  # tangent-plane probes
    for patch, out in zip(inputs, ours):
        centre = patch.mean(0)
        _, _, axes = np.linalg.svd(patch - centre)
        probes = centre + dense @ axes[:2]
        assert cKDTree(out).query(probes)[0].mean() < cKDTree(patch).query(probes)[0].mean()


def test_fixed_seed_gives_identical_outputs() -> None:
    inputs = _normalized(_sphere_patches(2)[0])
    a = Upsampler(seed=3).upsample_patches(inputs)
    b = Upsampler(seed=3).upsample_patches(inputs)
    assert np.array_equal(a[0], b[0]) and np.array_equal(a[1], b[1])


def test_corrupt_or_mismatched_weights_are_refused(tmp_path: Path) -> None:
    path = tmp_path / "w.pt"
    save(Generator(), path)
    Path(f"{path}.sha256").write_text("0" * 64 + "  w.pt\n")
    with pytest.raises(WeightsError, match="checksum"):
        Upsampler(path)
    garbage = tmp_path / "garbage.pt"
    garbage.write_bytes(b"not a model")
    with pytest.raises(WeightsError, match="garbage.pt"):
        Upsampler(garbage)
    with pytest.raises(WeightsError, match="not found"):
        Upsampler(tmp_path / "missing.pt")


def test_ratios_are_powers_of_the_trained_one(tmp_path: Path) -> None:
    assert passes_for(4, 4) == 1 and passes_for(16, 4) == 2
    with pytest.raises(ValueError, match="power"):
        passes_for(8, 4)
    path = tmp_path / "w.pt"
    save(Generator(), path)
    sixteen = Upsampler(path, ratio=16)
    points, parents = sixteen.upsample_patches(_normalized(_sphere_patches(1)[0]))
    assert points.shape == (1, 256 * 16, 3)
    assert parents.min() >= 0 and parents.max() < 256


@pytest.mark.parametrize("oversample", [1, 2])
def test_whole_object_gets_r_times_its_points(tmp_path: Path, oversample: int) -> None:
    path = tmp_path / "w.pt"
    save(Generator(), path)
    rng = np.random.default_rng(0)
    cloud = rng.normal(size=(1000, 3))
    cloud /= np.linalg.norm(cloud, axis=1, keepdims=True)
    points, source = Upsampler(path, oversample=oversample).upsample_object(cloud)
    assert len(points) == 4 * 1000  # about it before: 3.95x of a PU-GAN mesh (a library user's trial)
    assert source.min() >= 0 and source.max() < 1000
    if oversample == 1:  # every input point has descendants (a selection may leave one without)
        assert set(np.unique(source)) == set(range(1000))


def test_the_frame_neighbourhood_travels_with_the_weights(tmp_path: Path) -> None:
    torch.manual_seed(3)
    wide = Generator(frame_k=24)
    path = tmp_path / "wide.pt"
    save(wide, path)
    loaded = Upsampler(path, device="cpu")
    assert loaded.generator.frame_k == 24
    patches, _ = _sphere_patches(2)
    reference = Upsampler(path, device="cpu").upsample_patches(patches)[0]
    np.testing.assert_array_equal(loaded.upsample_patches(patches)[0], reference)
    narrow = Generator(frame_k=12)
    narrow.load_state_dict(wide.state_dict())
    with torch.no_grad():
        tensor = torch.from_numpy(patches).float()
        out_wide = wide.eval()(tensor, generator=torch.Generator().manual_seed(0))[0]
        out_narrow = narrow.eval()(tensor, generator=torch.Generator().manual_seed(0))[0]
    assert not torch.allclose(out_wide, out_narrow)  # the option changes the frames the offsets use


def test_shipped_weights_can_be_named(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    assert resolve("cadpu_r4_alpha1") == UNIFORM_WEIGHTS
    assert resolve(None) == DEFAULT_WEIGHTS
    assert Upsampler("cadpu_r4_alpha1").checksum == Upsampler(UNIFORM_WEIGHTS).checksum
    # a file of that name in the working directory is taken as the path it is
    monkeypatch.chdir(tmp_path)
    (tmp_path / "cadpu_r4").write_bytes(b"not weights")
    assert resolve("cadpu_r4") == Path("cadpu_r4")
    with pytest.raises(WeightsError, match="shipped names: .*cadpu_r4_alpha1"):
        Upsampler("no_such_model")


def test_each_shipped_file_names_its_twin_of_the_other_alpha(tmp_path: Path) -> None:
    assert twin(None) == twin("cadpu_r4") == UNIFORM_WEIGHTS
    assert twin("cadpu_r4_lidar") == LIDAR_UNIFORM_WEIGHTS
    # an alpha = 1.0 file's twin is the alpha = 0.5 file of the same data, not itself
    assert twin(LIDAR_UNIFORM_WEIGHTS) == LIDAR_WEIGHTS
    assert twin("cadpu_r4_alpha1") == DEFAULT_WEIGHTS
    for path in (DEFAULT_WEIGHTS, UNIFORM_WEIGHTS, LIDAR_WEIGHTS, LIDAR_UNIFORM_WEIGHTS):
        pair = {Upsampler(path).generator.alpha, Upsampler(twin(path)).generator.alpha}
        assert pair == {0.5, 1.0}
        assert twin(twin(path)) == path
    # a file of one's own has no twin (eval-kitti chooses what to compare it with)
    assert twin(tmp_path / "mine.pt") is None


@pytest.mark.parametrize("weights", [DEFAULT_WEIGHTS, LIDAR_UNIFORM_WEIGHTS])
def test_compiled_inference_kernels_give_the_torch_paths_points(weights: Path, monkeypatch) -> None:
    """A whole upsampling with the compiled inference kernels equals one without them, bit for bit
    (the network's EdgeConv and decoder; the shipped weights of both offset frames)."""
    import cadpu.network

    patches, _ = _sphere_patches(6, seed=3)
    upsampler = Upsampler(weights, device="cpu", batch_size=4)
    compiled_points, compiled_parents = upsampler.upsample_patches(patches)
    monkeypatch.setattr(cadpu.network, "compiled_inference", lambda activations: False)
    torch_points, torch_parents = upsampler.upsample_patches(patches)
    assert np.array_equal(compiled_parents, torch_parents)
    assert np.array_equal(compiled_points, torch_points)


def test_bad_points_are_refused_with_the_call_and_the_reason() -> None:
    upsampler = Upsampler(device="cpu")
    patches = _normalized(_sphere_patches(1)[0])
    broken = patches.copy()
    broken[0, 5, 1] = np.nan
    with pytest.raises(ValueError, match="upsample_patches: 1 point with NaN"):
        upsampler.upsample_patches(broken)
    with pytest.raises(ValueError, match="normalised to the unit sphere.*lies 100 from the origin"):
        upsampler.upsample_patches(patches * 100)
    with pytest.raises(ValueError, match=r"upsample_object: points must be an \(M, 3\) array"):
        upsampler.upsample_object(np.zeros((1024, 4)))
    with pytest.raises(ValueError, match="upsample_object: 1 point with NaN"):
        upsampler.upsample_object(np.where(np.arange(3 * 512).reshape(512, 3) == 4, np.inf, 1.0))

    class PointCloud:  # what an Open3D cloud looks like to numpy: an object holding `points`
        points = np.zeros((512, 3))

    # numpy's "float() argument must be a string or a real number, not 'PointCloud'" (a trial)
    with pytest.raises(ValueError, match=r"upsample_object: points must be an array of x, y, z numbers \(an "
                                         r"Open3D point cloud: np.asarray\(cloud.points\)\), got PointCloud"):
        upsampler.upsample_object(PointCloud())
    with pytest.raises(ValueError, match="upsample_patches: points must be an array of x, y, z numbers, got str"):
        upsampler.upsample_patches("patches")


@pytest.mark.parametrize("argument, value", [("batch_size", -1), ("batch_size", 0), ("batch_size", 2.5),
                                             ("num_threads", -1), ("ratio", "4"), ("ratio", 4.0), ("ratio", True),
                                             # refused by torch or numpy at the first upsampling, before
                                             ("seed", -1), ("seed", 1.5), ("seed", None), ("seed", "x")])
def test_sizes_that_are_not_whole_numbers_of_at_least_one_are_refused(argument: str, value: object) -> None:
    with pytest.raises(ValueError, match=f"Upsampler: {argument} must be a whole number"):
        Upsampler(**{argument: value})


def test_numpy_integers_are_whole_numbers() -> None:
    upsampler = Upsampler(ratio=np.int64(4), batch_size=np.int32(2), seed=np.int64(3))
    assert upsampler.ratio == 4 and upsampler.batch_size == 2
    points = np.random.default_rng(0).normal(size=(300, 3))
    # a numpy seed failed in torch's manual_seed ("an integer is required")
    assert np.array_equal(upsampler.upsample_object(points)[0], Upsampler(seed=3).upsample_object(points)[0])


def test_a_ratio_of_zero_is_refused_and_none_is_the_trained_one() -> None:
    with pytest.raises(ValueError, match="ratio 0 is not the trained ratio 4 or a power of it"):
        Upsampler(ratio=0)
    assert Upsampler(ratio=None).ratio == 4


@pytest.mark.parametrize("weights, fewest", [(DEFAULT_WEIGHTS, 16), (LIDAR_UNIFORM_WEIGHTS, 24)])
def test_patches_smaller_than_the_networks_neighbourhoods_are_refused(weights: Path, fewest: int) -> None:
    upsampler = Upsampler(weights)
    patches = _normalized(_sphere_patches(1)[0])
    with pytest.raises(ValueError, match=f"patches of {fewest - 1} points; this network needs at least {fewest}"):
        upsampler.upsample_patches(_normalized(patches[:, :fewest - 1]))
    points, _ = upsampler.upsample_patches(_normalized(patches[:, :fewest]))
    assert points.shape == (1, 4 * fewest, 3)


@pytest.mark.parametrize("device, message", [("gpu", "device 'gpu' is not one of 'auto', 'cpu', 'cuda', 'cuda:N'"),
                                             ("cuda", "device 'cuda': this torch has no CUDA device")])
def test_a_device_torch_cannot_use_is_refused_as_a_value_error(device: str, message: str) -> None:
    if device == "cuda" and torch.cuda.is_available():
        pytest.skip("this machine has CUDA")
    with pytest.raises(ValueError, match=message):  # a bare AssertionError / RuntimeError from torch before
        Upsampler(device=device)


def test_a_cuda_device_number_the_machine_lacks_is_refused_as_a_value_error(monkeypatch: pytest.MonkeyPatch) -> None:
    # a one-GPU machine, told without one: the check comes before torch touches a device
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(torch.cuda, "device_count", lambda: 1)
    with pytest.raises(ValueError, match=r"device 'cuda:1': this machine has 1 CUDA device\(s\), numbered from 0"):
        Upsampler(device="cuda:1")


def test_a_shipped_name_may_carry_its_file_extension() -> None:
    assert resolve("cadpu_r4_lidar.pt") == LIDAR_WEIGHTS == resolve("cadpu_r4_lidar")
    assert Upsampler("cadpu_r4_lidar.pt").checksum == Upsampler(LIDAR_WEIGHTS).checksum


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_on_cuda_the_output_follows_neither_the_batch_size_nor_the_device() -> None:
    # the expansion draws come from a CPU generator: a CUDA one advanced per kernel launch, and
    # outputs then moved by up to 1.5 in the unit sphere with the batch size
    patches = _normalized(_sphere_patches(6)[0])
    # the network alone (oversample 1): with the selection, float rounding may swap a pick
    reference, parents = Upsampler(device="cpu", batch_size=4, oversample=1).upsample_patches(patches)
    for batch in (1, 5):
        points, cuda_parents = Upsampler(device="cuda", batch_size=batch, oversample=1).upsample_patches(patches)
        assert np.array_equal(cuda_parents, parents) and np.abs(points - reference).max() < 1e-5
    selected, selected_parents = Upsampler(device="cpu").upsample_patches(patches)
    on_cuda, on_cuda_parents = Upsampler(device="cuda").upsample_patches(patches)
    assert np.mean(on_cuda_parents == selected_parents) > 0.99
    assert np.mean(np.abs(on_cuda - selected).max(axis=2) < 1e-5) > 0.99


def test_patch_sizes_a_ratio_of_several_passes_cannot_split_are_named_before_any_pass() -> None:
    upsampler = Upsampler(ratio=16)
    # a ValueError of the clustering ("need a power-of-two number of parts dividing 800") and a
    # ZeroDivisionError before
    for k in (200, 30):
        with pytest.raises(ValueError, match=rf"ratio 16 upsamples each patch's {k} \* 4 points again in clusters "
                                             r"of 256.*patches of 64, 128, 256, 512, \.\.\. points, not"):
            upsampler.upsample_patches(np.zeros((1, k, 3), np.float32))
    points, parents = upsampler.upsample_patches(np.zeros((0, 256, 3), np.float32))  # np.stack of nothing before
    assert points.shape == (0, 4096, 3) and parents.shape == (0, 4096)


def test_the_default_batch_size_follows_the_device() -> None:
    assert Upsampler(device="cpu").batch_size == DEFAULT_BATCH_SIZE
    assert Upsampler(device="cpu", batch_size=7).batch_size == 7


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_on_cuda_the_default_batch_is_larger_and_batches_of_256_patches_work() -> None:
    # 256 patches are 65,536 curvature matrices: a cuSOLVER batched eigen-decomposition failed on
    # them (CUSOLVER_STATUS_INTERNAL_ERROR on an H100) before cadpu.geometry.jacobi_eigh_3x3
    assert Upsampler(device="cuda").batch_size == DEFAULT_CUDA_BATCH_SIZE
    six = _normalized(_sphere_patches(6)[0])
    jitter = np.random.default_rng(1).normal(scale=1e-3, size=(43, *six.shape))
    patches = _normalized((six[None] + jitter).reshape(-1, *six.shape[1:])[:256])
    reference, parents = Upsampler(device="cpu", oversample=1).upsample_patches(patches)
    points, cuda_parents = Upsampler(device="cuda", batch_size=256, oversample=1).upsample_patches(patches)
    assert np.array_equal(cuda_parents, parents) and np.abs(points - reference).max() < 1e-5


def _sphere_points(count: int) -> np.ndarray:
    """(count, 3) points on the unit sphere (seed 0)."""
    points = np.random.default_rng(0).normal(size=(count, 3))
    return points / np.linalg.norm(points, axis=1, keepdims=True)


@pytest.mark.parametrize("scale", [1e154, 1e-20])
def test_an_object_upsamples_the_same_at_any_scale(scale: float) -> None:
    # coordinates near 1e154 overflowed the tiling's squared distances (an IndexError), and those
    # near 1e-20 underflowed into another tiling
    points = _sphere_points(600)
    upsampler = Upsampler()
    reference, source = upsampler.upsample_object(points)
    scaled, scaled_source = upsampler.upsample_object(points * scale)
    assert np.array_equal(scaled_source, source)
    np.testing.assert_allclose(scaled / scale, reference, rtol=0, atol=1e-12)


def test_one_stray_point_far_away_leaves_the_others_upsampled_where_they_are() -> None:
    # centred on the mean, a point 1e12 away left the others 1e-12 apart about a far centre: one
    # float32 value in the tiling, and output points 229 units off a unit sphere (a trial). (The
    # patch the stray point falls in still spans it and its nearest 255: with few points, those
    # can be many of the sphere's, and they come out as badly.)
    sphere = _sphere_points(2048)
    upsampler = Upsampler(oversample=1)
    reference, _ = upsampler.upsample_object(sphere)
    points, source = upsampler.upsample_object(np.vstack([sphere, [[1e12, 0.0, 0.0]]]))
    on_sphere = points[source < len(sphere)]
    assert len(on_sphere) >= 0.99 * len(reference)
    assert np.abs(np.linalg.norm(on_sphere, axis=1) - 1.0).max() < 0.02


@pytest.mark.parametrize("copies", [3, 12])
def test_an_object_given_with_repeated_points_upsamples_as_its_distinct_points(copies: int) -> None:
    # with the oversampling's selection each point in came out about 5.5 times, and at 12 copies
    # every output point sat on its parent (a trial)
    points = _sphere_points(600)
    upsampler = Upsampler()
    reference, source = upsampler.upsample_object(points)
    repeated, repeated_source = upsampler.upsample_object(np.repeat(points, copies, axis=0))
    assert np.array_equal(repeated, reference)
    assert np.array_equal(repeated_source, source * copies)  # each point's first copy
    with pytest.raises(ValueError, match="upsample_object: 100 distinct points among the 1200 given; needs at least 256"):
        upsampler.upsample_object(np.repeat(points[:100], 12, axis=0))


def test_the_patch_sizes_a_multi_pass_ratio_names_are_sizes_it_takes() -> None:
    # it named 256, 512, 1024, 2048 for ratio 16, while 64 and 128 work
    upsampler = Upsampler(ratio=16)

    def patch(k: int) -> np.ndarray:
        points = np.random.default_rng(0).normal(size=(1, k, 3))
        points -= points.mean(axis=1, keepdims=True)
        return (points / np.linalg.norm(points, axis=2).max()).astype(np.float32)

    with pytest.raises(ValueError, match=r"patches of 64, 128, 256, 512, \.\.\. points, not 96"):
        upsampler.upsample_patches(patch(96))
    assert upsampler.upsample_patches(patch(64))[0].shape == (1, 1024, 3)


def test_oversampling_is_on_for_curvature_adaptive_weights_only() -> None:
    assert Upsampler(DEFAULT_WEIGHTS).oversample == ADAPTIVE_OVERSAMPLE > 1  # alpha 0.5
    assert Upsampler(UNIFORM_WEIGHTS).oversample == 1  # alpha 1: its extra grid codes were never trained
    assert Upsampler(UNIFORM_WEIGHTS, oversample=2).oversample == 2


def test_offsets_are_scaled_for_curvature_adaptive_weights_only() -> None:
    assert Upsampler(DEFAULT_WEIGHTS).offset_scale == ADAPTIVE_OFFSET_SCALE > 1  # alpha 0.5
    assert Upsampler(UNIFORM_WEIGHTS).offset_scale == 1.0  # alpha 1, as the pipeline's file is
    assert Upsampler(LIDAR_UNIFORM_WEIGHTS).offset_scale == 1.0
    assert Upsampler(UNIFORM_WEIGHTS, offset_scale=1.2).offset_scale == 1.2


def test_weights_that_learned_from_scans_keep_the_pipelines_placement_whatever_their_alpha() -> None:
    from cadpu.inference import learned_from_scans

    # the alpha 0.5 LiDAR file got the objects' oversampling and offset scale, which the pipeline and
    # eval-kitti do not give it: a library user could not make the "CAD-PU twin" row (a researcher's trial)
    twin = Upsampler("cadpu_r4_lidar")
    assert twin.generator.alpha < 1 and (twin.oversample, twin.offset_scale) == (1, 1.0)
    assert learned_from_scans(twin.meta) and not learned_from_scans(Upsampler(DEFAULT_WEIGHTS).meta)
    assert learned_from_scans({"finetuned_from": {"weights": "cadpu_r4_lidar"}})  # a user's fine-tuned file
    assert Upsampler("cadpu_r4_lidar", oversample=2, offset_scale=1.4).offset_scale == 1.4


@pytest.mark.parametrize("oversample", [1, 2])
def test_a_scaled_offset_moves_each_point_along_the_line_from_its_parent(oversample: int) -> None:
    inputs = _normalized(_sphere_patches(2)[0])
    as_made, made_parents = Upsampler(oversample=1, offset_scale=1).upsample_patches(inputs)
    points, parents = Upsampler(oversample=oversample, offset_scale=1.5).upsample_patches(inputs)
    origin = np.take_along_axis(inputs, parents[..., None], axis=1)
    if oversample == 1:  # the same points, each 1.5 times as far from the same parent
        assert np.array_equal(parents, made_parents)
        np.testing.assert_allclose(points - origin, 1.5 * (as_made - origin), atol=1e-6)
    # scaled before the selection: the kept points are scaled candidates, further from their parents
    distance = np.linalg.norm(points - origin, axis=2).mean()
    made_distance = np.linalg.norm(as_made - np.take_along_axis(inputs, made_parents[..., None], axis=1), axis=2).mean()
    assert distance > 1.3 * made_distance


@pytest.mark.parametrize("value", [0, -0.5, True, "2", float("nan"), MAX_OFFSET_SCALE + 0.5])
def test_an_offset_scale_out_of_range_is_refused(value: object) -> None:
    with pytest.raises(ValueError, match=f"Upsampler: offset_scale must be a number above 0 and at most "
                                         f"{MAX_OFFSET_SCALE:g}"):
        Upsampler(offset_scale=value)


def test_oversampling_keeps_the_farthest_spread_share_of_more_candidates() -> None:
    inputs = _normalized(_sphere_patches(2)[0])
    plain = Upsampler(oversample=1, offset_scale=1)
    points, parents = Upsampler(oversample=2, offset_scale=1).upsample_patches(inputs)
    assert points.shape == (2, 1024, 3) and parents.shape == (2, 1024)
    # the kept points are candidates of a pass that makes twice as many, picked with their parents
    with torch.inference_mode():
        candidates, candidate_parents = plain.generator(torch.from_numpy(inputs), torch.Generator().manual_seed(0),
                                                        ratio=8)
    for b in range(2):
        rows = {tuple(row): parent for row, parent in zip(candidates[b].numpy(), candidate_parents[b].numpy())}
        assert all(rows.get(tuple(row)) == parent for row, parent in zip(points[b], parents[b]))
        assert (np.diff(parents[b]) >= 0).all()  # in the order made: a parent's copies side by side
    # and they are more evenly spread than a plain pass's: a larger smallest gap between points
    from scipy.spatial import cKDTree

    def closest_pair(cloud: np.ndarray) -> float:
        return float(cKDTree(cloud).query(cloud, k=2)[0][:, 1].min())

    single, _ = plain.upsample_patches(inputs)
    assert all(closest_pair(points[b]) > closest_pair(single[b]) for b in range(2))


@pytest.mark.parametrize("value", [0, -1, 1.5, True, "2", MAX_OVERSAMPLE + 1])
def test_an_oversample_that_is_not_a_whole_number_in_range_is_refused(value: object) -> None:
    with pytest.raises(ValueError, match=f"Upsampler: oversample must be a whole number from 1 to {MAX_OVERSAMPLE}"):
        Upsampler(oversample=value)


def test_oversampled_patches_match_across_batch_sizes_and_an_exported_engine() -> None:
    inputs = _normalized(_sphere_patches(3)[0])
    reference, parents = Upsampler(batch_size=1).upsample_patches(inputs)
    batched = Upsampler(batch_size=3).upsample_patches(inputs)
    assert np.array_equal(reference, batched[0]) and np.array_equal(parents, batched[1])
    pytest.importorskip("onnxruntime")
    exported, exported_parents = Upsampler(engine="onnxruntime").upsample_patches(inputs)
    # float rounding may swap a pick between two candidates at almost the same distance; kept in
    # the order made, a swap moves that one point only
    assert np.mean(exported_parents == parents) > 0.99
    assert np.mean(np.abs(exported - reference).max(axis=2) < 1e-4) > 0.99


@pytest.mark.parametrize("weights", [None, "cadpu_r4_alpha1"])
def test_an_object_upsamples_to_the_same_points_in_any_order(weights: str | None) -> None:
    # the tiling's first seed and the network's draws followed the input's order: a shuffled
    # PU-GAN mesh moved 90% of the output points by up to a point spacing (a library user's trial)
    points = _sphere_points(700)
    upsampler = Upsampler(weights)
    reference, source = upsampler.upsample_object(points)
    order = np.random.default_rng(5).permutation(len(points))
    shuffled, shuffled_source = upsampler.upsample_object(points[order])
    assert len(reference) == 4 * len(points)
    by_row = np.lexsort(reference.T)
    by_row_shuffled = np.lexsort(shuffled.T)
    assert np.array_equal(reference[by_row], shuffled[by_row_shuffled])
    assert np.array_equal(source[by_row], order[shuffled_source[by_row_shuffled]])
