import itertools

import numpy as np
import pytest
import torch

from cadpu.losses import (chamfer, curvature_regularizer, discriminator_loss, emd, generator_adversarial,
                          snap_to_elevations, snapped_chamfer)


def _brute_force_emd(a: np.ndarray, b: np.ndarray) -> float:
    best = min(sum(np.linalg.norm(a[i] - b[j]) for i, j in enumerate(perm))
               for perm in itertools.permutations(range(len(a))))
    return best / len(a)


def test_emd_equals_the_exact_assignment_on_small_sets() -> None:
    rng = np.random.default_rng(0)
    for _ in range(5):
        a, b = rng.normal(size=(7, 3)), rng.normal(size=(7, 3))
        value = emd(torch.from_numpy(a)[None], torch.from_numpy(b)[None]).item()
        assert abs(value - _brute_force_emd(a, b)) < 1e-9


def test_emd_is_zero_for_a_permutation_and_has_gradients() -> None:
    target = torch.randn(2, 64, 3)
    pred = target[:, torch.randperm(64)].clone().requires_grad_(True)
    loss = emd(pred, target)
    assert loss.item() < 1e-6
    shifted = (pred + 0.1).detach().requires_grad_(True)
    emd(shifted, target).backward()
    assert shifted.grad is not None and shifted.grad.abs().sum() > 0


def test_regularizer_is_zero_on_a_plane_and_positive_off_it() -> None:
    rng = np.random.default_rng(1)
    plane = torch.from_numpy(np.c_[rng.uniform(-1, 1, (300, 2)), np.zeros(300)]).float()[None]
    normals = torch.tensor([0.0, 0.0, 1.0]).expand(1, 300, 3)
    pred = torch.from_numpy(np.c_[rng.uniform(-1, 1, (200, 2)), np.zeros(200)]).float()[None]
    assert curvature_regularizer(pred, plane, normals).item() < 1e-6
    noisy = pred + torch.randn_like(pred) * 0.05
    assert curvature_regularizer(noisy, plane, normals).item() > 0.1


def test_lsgan_terms() -> None:
    assert generator_adversarial(torch.ones(4)).item() == 0.0
    assert discriminator_loss(torch.ones(4), torch.zeros(4)).item() == 0.0
    assert discriminator_loss(torch.zeros(4), torch.ones(4)).item() == 1.0


def test_chamfer_of_identical_sets_is_zero() -> None:
    a = torch.randn(2, 50, 3)
    assert chamfer(a, a).abs().max().item() < 1e-3
    assert (chamfer(a, a + 1.0) > 0.5).all()


def _ring_patch(vertical_scale: float = 0.15) -> dict[str, torch.Tensor]:
    """One patch of 8 rings (cones of fixed elevation) crossing a wall 12-13 m out, 128 points each,
    as `cadpu.scan_data.thinned_scan_pairs` frames it: rings 0 and 4 are the input's, the six
    others the truth's rings between (places 0-5 of `ring_elevations`)."""
    elevation = np.deg2rad(-2.0 + 0.4 * np.arange(8))
    azimuth = np.linspace(-0.05, 0.05, 128)
    el, az = np.meshgrid(elevation, azimuth, indexing="ij")
    distance = 12.0 + 0.5 * (az + 0.05) / 0.1 + 0.1 * np.sin(8 * el)
    metres = np.stack([distance * np.cos(el) * np.cos(az), distance * np.cos(el) * np.sin(az),
                       distance * np.sin(el)], axis=-1).reshape(-1, 3)
    tiled = metres * [1.0, 1.0, vertical_scale]
    centroid = tiled.mean(0)
    scale = np.linalg.norm(tiled - centroid, axis=1).max()
    ring = np.repeat(np.arange(8), 128)
    between = ring % 4 != 0
    place = np.where(between, ring - 1 - ring // 4, -1)  # rings 1-3, 5-7 -> places 0-5
    elevations = np.full(48, np.nan)
    elevations[:6] = elevation[[1, 2, 3, 5, 6, 7]]
    return {"truth": torch.tensor((tiled - centroid) / scale, dtype=torch.float32)[None],
            "frames": [torch.eye(3)[None], torch.ones(1), torch.tensor(centroid, dtype=torch.float32)[None],
                       torch.tensor([scale], dtype=torch.float32), torch.tensor([vertical_scale]),
                       torch.tensor(place)[None], torch.tensor(elevations, dtype=torch.float32)[None]],
            "metres": torch.tensor(metres, dtype=torch.float32)[None], "between": torch.tensor(between)}


def _normalised(patch: dict, metres: torch.Tensor) -> torch.Tensor:
    centroid, scale, vertical_scale = patch["frames"][2], patch["frames"][3], patch["frames"][4]
    return (metres * torch.stack([torch.ones(1), torch.ones(1), vertical_scale], 1) - centroid) / scale


def _moved(metres: torch.Tensor, d_elevation: float = 0.0, d_range: float = 0.0) -> torch.Tensor:
    distance = metres.norm(dim=-1)
    azimuth = torch.atan2(metres[..., 1], metres[..., 0])
    elevation = torch.asin(metres[..., 2] / distance) + d_elevation
    distance = distance + d_range
    return torch.stack([distance * torch.cos(elevation) * torch.cos(azimuth),
                        distance * torch.cos(elevation) * torch.sin(azimuth), distance * torch.sin(elevation)], -1)


def test_snapping_keeps_range_and_azimuth_and_takes_the_nearest_ring() -> None:
    patch = _ring_patch()
    metres = _moved(patch["metres"], d_elevation=np.deg2rad(0.15))  # within half a ring spacing (0.2 deg) of its own
    snapped = snap_to_elevations(metres, patch["frames"][6])
    torch.testing.assert_close(snapped.norm(dim=-1), metres.norm(dim=-1))
    torch.testing.assert_close(torch.atan2(snapped[..., 1], snapped[..., 0]), torch.atan2(metres[..., 1], metres[..., 0]))
    # rings 1-3 and 5-7 go back to their own elevation; 0 and 4 to the nearest ring between (4: ring 5)
    torch.testing.assert_close(snapped[0, patch["between"]], patch["metres"][0, patch["between"]], atol=2e-5, rtol=0)
    ring4 = torch.asin(snapped[0, 512:640, 2] / snapped[0, 512:640].norm(dim=-1))
    torch.testing.assert_close(ring4, torch.zeros(128), atol=1e-5, rtol=0)  # ring 5, 0.15 deg away


def test_the_snapped_chamfer_scores_range_and_ring_not_height_within_a_ring() -> None:
    patch = _ring_patch()
    truth, frames = patch["truth"], patch["frames"]
    own = patch["metres"][:, patch["between"]]
    def score(metres: torch.Tensor) -> float:
        return snapped_chamfer(_normalised(patch, metres), truth, *frames).item()
    assert score(own) < 1e-5
    # a prediction anywhere in its ring's band scores as the ring itself
    assert score(_moved(own, d_elevation=np.deg2rad(0.15))) < 1e-5
    # a range error of 5 cm costs 5 cm each way, over the patch radius, less where the wall slants
    # away from the ray (0.5 m of range over 1.2 m: the nearest point is 5 cm x cos 22 deg away)
    assert score(_moved(own, d_range=0.05)) == pytest.approx(2 * 0.05 * np.cos(np.arctan(0.5 / 1.2)) / frames[3].item(),
                                                             rel=0.02)
    # points on one ring only leave the others uncovered
    assert score(own[:, :128]) > 10 * score(_moved(own, d_range=0.01))


def test_the_snapped_chamfer_undoes_the_augmentation_and_has_gradients() -> None:
    patch = _ring_patch()
    truth, frames = patch["truth"], patch["frames"]
    pred = _normalised(patch, _moved(patch["metres"][:, patch["between"]], d_range=0.03))
    plain = snapped_chamfer(pred, truth, *frames)
    angle = 0.7
    rotation = torch.tensor([[np.cos(angle), -np.sin(angle), 0.0], [np.sin(angle), np.cos(angle), 0.0],
                             [0.0, 0.0, 1.0]], dtype=torch.float32)[None]
    scale = torch.tensor([0.85])
    turned = (scale[:, None, None] * torch.einsum("bij,bnj->bni", rotation, pred)).requires_grad_(True)
    augmented = snapped_chamfer(turned, scale[:, None, None] * torch.einsum("bij,bnj->bni", rotation, truth),
                                rotation, scale, *frames[2:])
    assert augmented.item() == pytest.approx(plain.item(), rel=1e-4)
    augmented.backward()
    assert torch.isfinite(turned.grad).all() and turned.grad.abs().sum() > 0
