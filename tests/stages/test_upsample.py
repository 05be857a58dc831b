"""stages.upsample: a frame's patches go through a real `cadpu.inference.Upsampler` (a small,
untrained generator saved here) and come back with the shapes the stitch stage expects."""

from __future__ import annotations


import numpy as np
import pytest
import torch

from cadpu import weights
from cadpu.inference import Upsampler
from cadpu.network import Generator
from stages import stitch, tile, upsample
from stages.frame import Frame


@pytest.fixture(scope="module")
def upsampler(tmp_path_factory: pytest.TempPathFactory) -> Upsampler:
    torch.manual_seed(0)
    path = tmp_path_factory.mktemp("weights") / "untrained_r4.pt"
    weights.save(Generator(ratio=4), path)
    return Upsampler(weights=path, ratio=4, device="cpu", batch_size=4, seed=0)


def _frame(n: int, seed: int = 0) -> Frame:
    rng = np.random.default_rng(seed)
    points = np.column_stack([rng.normal(size=(n, 3)) * 5, rng.uniform(0, 1, n)]).astype(np.float32)
    ground = points[:, 2] < -6  # a few points
    return Frame(points=points, dataset="bin", sequence="s", index=1, ground=ground)


def test_upsample_fills_points_parent_slots_and_ratio(upsampler: Upsampler) -> None:
    frame = tile.run(_frame(700), tile.Options(vertical_scale=1.0))
    p = frame.tiling.num_patches
    result = upsample.run(frame, upsampler=upsampler)
    assert result.upsampled.shape == (p, 256 * 4, 3) and result.upsampled.dtype == np.float32
    assert result.parent_slots.shape == (p, 256 * 4) and result.parent_slots.dtype == np.int64
    assert result.parent_slots.min() >= 0 and result.parent_slots.max() < 256
    assert np.isfinite(result.upsampled).all()
    assert result.tiling is frame.tiling and result.ratio == upsampler.ratio
    cloud = stitch.stitch(result, keep_ground=False, keep_input=False)
    assert cloud.generated.all() and not result.ground[cloud.parent].any()


def test_frame_without_tiling_is_returned_unchanged(upsampler: Upsampler) -> None:
    frame = tile.run(_frame(100), tile.Options(vertical_scale=1.0))
    result = upsample.run(frame, upsampler=upsampler)
    assert result.upsampled is None and result.parent_slots is None
    assert result.points is frame.points and result.ratio == upsampler.ratio


@pytest.mark.parametrize("value", [None, ""])
def test_weights_null_is_refused_not_read_as_the_object_trained_default(value: object) -> None:
    # Upsampler(weights=None) is the object-trained cadpu_r4; the pipeline's default is another file
    with pytest.raises(ValueError, match=r"leave the key out for the pipeline's default \(cadpu_r4_lidar_alpha1\)"):
        upsample.Options(weights=value)


def test_a_seed_torch_cannot_take_is_refused_with_the_options() -> None:
    # 2**70 passed every check, then failed every frame ("Overflow when unpacking long long")
    from pydantic import ValidationError

    from cadpu.inference import MAX_SEED

    assert upsample.MAX_SEED == MAX_SEED
    with pytest.raises(ValidationError, match="less than or equal to 9223372036854775807"):
        upsample.Options(seed=2**70)
    with pytest.raises(ValueError, match="seed must be a whole number from 0 to 9223372036854775807"):
        Upsampler(seed=2**63)


def test_a_ratio_the_weights_cannot_make_is_a_stage_error_naming_the_scan() -> None:
    # a bare ValueError, which the chain takes for a bug of its own (a review)
    from stages import ground, load
    from stages.errors import StageError

    rng = np.random.default_rng(0)
    points = np.column_stack([rng.normal(size=(900, 3)) * [8, 8, 1], rng.uniform(size=900)]).astype(np.float32)
    frame = tile.run(ground.run(load.frame_from_points(points, source="/data/000003.bin")))
    # the ratio said once ("ratio 8: ratio 8 is not ...", a library user's trial)
    with pytest.raises(StageError, match=r"\[upsample\] /data/000003.bin: ratio 8 is not the trained ratio 4 or a power"):
        upsample.run(frame, {"ratio": 8})


def test_the_stage_oversamples_as_its_options_say_whatever_the_weights() -> None:
    from pydantic import ValidationError

    # cadpu_r4 is the alpha 0.5 object file, which Upsampler() alone oversamples
    assert Upsampler("cadpu_r4").oversample > 1
    assert upsample.model(upsample.Options(weights="cadpu_r4")).oversample == 1
    assert upsample.model(upsample.Options(weights="cadpu_r4", oversample=2)).oversample == 2
    with pytest.raises(ValidationError, match="greater than or equal to 1"):
        upsample.Options(oversample=0)
    from cadpu.inference import MAX_OVERSAMPLE

    assert upsample.MAX_OVERSAMPLE == MAX_OVERSAMPLE
    with pytest.raises(ValidationError, match="less than or equal to 8"):
        upsample.Options(oversample=MAX_OVERSAMPLE + 1)


def test_the_stage_scales_offsets_as_its_options_say_whatever_the_weights() -> None:
    from pydantic import ValidationError

    from cadpu.inference import MAX_OFFSET_SCALE

    # the alpha 0.5 object file, whose offsets Upsampler() alone scales: the pipeline's settings were
    # chosen with the network's own placement
    assert Upsampler("cadpu_r4").offset_scale > 1
    assert upsample.model(upsample.Options(weights="cadpu_r4")).offset_scale == 1.0
    assert upsample.model(upsample.Options(weights="cadpu_r4", offset_scale=1.2)).offset_scale == 1.2
    assert upsample.MAX_OFFSET_SCALE == MAX_OFFSET_SCALE
    for value in (0, MAX_OFFSET_SCALE + 1):
        with pytest.raises(ValidationError, match="offset_scale"):
            upsample.Options(offset_scale=value)
