import itertools

import numpy as np
import torch

from cadpu.losses import chamfer, curvature_regularizer, discriminator_loss, emd, generator_adversarial


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
