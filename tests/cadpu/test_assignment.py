import numpy as np
import pytest
import torch
from scipy.optimize import linear_sum_assignment

import cadpu.assignment as auction
from cadpu.assignment import auction_assignment, matched_cost
from cadpu.geometry import gather, knn
from cadpu.losses import _mean_abs_cosine, assignment, curvature_regularizer, emd, pred_target_distances


def _clouds(batch: int, n: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    target = rng.normal(size=(batch, n, 3)).astype(np.float32)
    pred = (target[:, rng.permutation(n)] + rng.normal(scale=0.3, size=(batch, n, 3))).astype(np.float32)
    return pred, target


@pytest.mark.parametrize("epsilon", [1e-2, 1e-3, 1e-4])
def test_the_auction_is_a_bijection_within_epsilon_of_the_exact_mean_cost(epsilon: float) -> None:
    pred, target = _clouds(3, 150, seed=int(epsilon * 1e4))
    cost = np.linalg.norm(pred[:, :, None] - target[:, None], axis=-1)
    columns = auction_assignment(cost, epsilon, threads=2)
    exact = np.stack([linear_sum_assignment(c.astype(np.float64))[1] for c in cost])
    for row in columns:
        assert sorted(row.tolist()) == list(range(150))
    gap = matched_cost(cost, columns) - matched_cost(cost, exact)
    assert (gap >= -1e-6).all() and (gap <= epsilon + 1e-6).all()


def test_the_auction_handles_duplicates_and_a_single_point() -> None:
    points = np.zeros((1, 6, 3), np.float32)
    cost = np.linalg.norm(points[:, :, None] - points[:, None], axis=-1)
    assert sorted(auction_assignment(cost, 1e-4)[0].tolist()) == list(range(6))
    assert auction_assignment(np.ones((2, 1, 1)), 1e-4).tolist() == [[0], [0]]
    with pytest.raises(ValueError, match="epsilon"):
        auction_assignment(cost, 0.0)
    with pytest.raises(ValueError, match="B, n, n"):
        auction_assignment(np.ones((2, 3)), 1e-4)


def test_the_approximate_emd_is_within_epsilon_and_has_gradients() -> None:
    pred, target = _clouds(2, 200, seed=3)
    pred_t = torch.from_numpy(pred).requires_grad_(True)
    target_t = torch.from_numpy(target)
    exact = emd(pred_t, target_t).item()
    approximate = emd(pred_t, target_t, epsilon=1e-3)
    assert exact - 1e-6 <= approximate.item() <= exact + 1e-3 + 1e-6
    approximate.backward()
    assert pred_t.grad is not None and pred_t.grad.abs().sum() > 0
    same = assignment(pred_t, target_t, 1e-3, pred_target_distances(pred_t, target_t))
    assert torch.equal(same, assignment(pred_t, target_t, 1e-3))


def _regularizer_before_sharing(pred: torch.Tensor, target: torch.Tensor, normals: torch.Tensor, k: int = 12
                                ) -> torch.Tensor:
    """The regularizer as written before the distances were shared (sorted kNN, self dropped first)."""
    own_index = knn(pred.detach(), pred.detach(), k + 1)[..., 1:]
    kappa = _mean_abs_cosine(gather(pred, own_index) - pred.unsqueeze(2),
                             gather(normals, knn(pred.detach(), target, 1)[..., 0]).unsqueeze(2))
    gt_index = knn(pred.detach(), target, k)
    kappa_gt = _mean_abs_cosine(gather(target, gt_index) - pred.unsqueeze(2), gather(normals, gt_index))
    return (kappa + kappa_gt).mean()


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])  # float32: the compiled distances
def test_the_regularizer_with_shared_distances_equals_the_one_before(dtype: torch.dtype) -> None:
    pred, target = (torch.from_numpy(a).to(dtype) for a in _clouds(2, 300, seed=5))
    normals = torch.nn.functional.normalize(torch.randn(2, 300, 3, dtype=dtype), dim=-1)
    pred.requires_grad_(True)
    before = _regularizer_before_sharing(pred, target, normals)
    (grad_before,) = torch.autograd.grad(before, pred)
    for shared in (pred_target_distances(pred, target), None):
        now = curvature_regularizer(pred, target, normals, distances=shared)
        (grad_now,) = torch.autograd.grad(now, pred)
        assert abs(now.item() - before.item()) < 1e-6
        assert torch.allclose(grad_now, grad_before, atol=1e-6 if dtype == torch.float64 else 1e-5)



@pytest.mark.parametrize("n", [5, 31, 1024, 1030])
def test_a_candidate_refresh_keeps_the_cheapest_columns_in_order(n: int) -> None:
    rng = np.random.default_rng(n)
    size = min(auction.CANDIDATES, n - 1)
    for trial in range(50):
        row = rng.random(n).astype(np.float32)
        prices = (rng.random(n) * rng.random() * 0.5).astype(np.float32)
        if trial % 5 == 0:
            row[rng.integers(n)] = row[rng.integers(n)]  # a tie
        columns = np.empty(size, np.int64)
        following = auction._refresh(row, prices, columns)
        values = row + prices
        expected = np.sort(values)
        assert np.array_equal(values[columns], expected[:size])  # the cheapest, cheapest first
        assert following == expected[size] and len(set(columns)) == size
        assert np.array_equal(columns, np.argsort(values, kind="stable")[:size])  # ties: the lower column first


def test_non_finite_costs_are_refused_not_bid_on_for_ever() -> None:
    cost = np.random.default_rng(0).random((1, 8, 8)).astype(np.float32)
    cost[0, 3, 4] = np.nan
    with pytest.raises(ValueError, match="1 costs are NaN or infinite"):
        auction_assignment(cost, 1e-4)


def test_costs_beyond_the_prices_resolution_are_refused_not_bid_on_for_ever() -> None:
    # a run diverging to distances of about 1e16 (finite) hung in the bidding, beyond any signal's
    # reach: a float32 price plus 1e-4 rounds back to itself there (a training user's trial)
    cost = np.random.default_rng(0).random((1, 8, 8)).astype(np.float32) * 1e16
    with pytest.raises(ValueError, match=r"costs up to 9.\d+e\+15, where epsilon \(0.0001\) is below float32's resolution"):
        auction_assignment(cost, 1e-4)
    assert len(set(auction_assignment(cost / 1e16 * 100, 1e-4)[0])) == 8  # distances far past a unit sphere's

