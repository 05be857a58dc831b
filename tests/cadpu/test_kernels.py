"""cadpu.kernels: the compiled k-smallest selection, 3x3 eigen-decomposition and farthest point
sampling agree with torch."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from cadpu.geometry import farthest_point_sampling, pairwise_sq_dist
from cadpu.kernels import (_smallest_k, _smallest_k_float32, distances_3d, farthest_point_picks, smallest_k_indices,
                           symmetric_eigh_3x3)


@pytest.mark.parametrize("shape, k", [((3, 50, 256), 16), ((7, 12), 12), ((4, 9), 1)])
def test_same_sets_as_topk(shape: tuple[int, ...], k: int) -> None:
    scores = torch.randn(*shape, generator=torch.Generator().manual_seed(0))
    picked = smallest_k_indices(scores, k)
    expected = scores.topk(k, dim=-1, largest=False).indices
    assert picked.shape == expected.shape and picked.dtype == torch.int64
    assert torch.equal(picked.sort(dim=-1).values, expected.sort(dim=-1).values)


def test_same_sets_on_scan_ordered_rows_ties_and_short_rows() -> None:
    """Rows whose nearest entries sit at nearby indices (points in scan order), rows of repeated
    values, infinities, and rows shorter than 2k: the strided bound must never drop an entry."""
    generator = torch.Generator().manual_seed(1)
    line = torch.cumsum(torch.rand(6, 256, generator=generator), dim=1)
    scan_ordered = (line - line[:, 100:101]).abs()  # nearest entries around index 100
    repeated = torch.randint(0, 5, (6, 256), generator=generator).float()
    with_inf = torch.randn(6, 256, generator=generator)
    with_inf[:, ::3] = float("inf")
    short = torch.randn(6, 20, generator=generator)
    for scores, k in ((scan_ordered, 16), (scan_ordered, 24), (with_inf, 16), (short, 16), (short, 11)):
        picked = smallest_k_indices(scores, k)
        expected = scores.topk(k, dim=-1, largest=False).indices
        assert torch.equal(picked.sort(dim=-1).values, expected.sort(dim=-1).values)
        assert torch.equal(scores.gather(-1, picked), scores.gather(-1, expected))  # smallest first
    picked = smallest_k_indices(repeated, 16)  # ties: any k indices holding the k smallest values
    assert torch.equal(repeated.gather(-1, picked).sort(dim=-1).values,
                       repeated.topk(16, dim=-1, largest=False).values.sort(dim=-1).values)
    assert all(len(set(row.tolist())) == 16 for row in picked)


def test_nan_rows_give_valid_distinct_indices() -> None:
    scores = torch.randn(8, 64, generator=torch.Generator().manual_seed(2))
    scores[0, 0] = scores[1, 5] = scores[2, 63] = float("nan")
    scores[3] = float("nan")
    picked = smallest_k_indices(scores, 16)
    assert int(picked.min()) >= 0 and int(picked.max()) < 64
    assert all(len(set(row.tolist())) == 16 for row in picked)


@pytest.mark.parametrize("k", [1, 5, 8, 12, 16, 24, 30])
def test_float32_selection_gives_the_general_selections_indices_in_its_order(k: int) -> None:
    """The keyed float32 kernel against the general one: the same indices in the same order, ties
    (-0.0 and 0.0 among them) broken by the lower index, on rows of every sign, with infinities,
    in scan order, of repeated values, and shorter than its bound's groups."""
    rng = np.random.default_rng(k)
    line = np.cumsum(rng.random((5, 256)), axis=1)
    scan_ordered = np.abs(line - line[:, 120:121])
    signed = rng.normal(size=(5, 256)) * 10.0 ** rng.integers(-30, 30, size=(5, 1))
    repeated = rng.integers(-3, 3, size=(5, 256)).astype(np.float64)
    repeated[:, ::7] = -0.0
    with_inf = rng.normal(size=(5, 256))
    with_inf[:, ::3] = np.inf
    with_inf[:, 1::5] = -np.inf
    short = rng.normal(size=(5, max(k, 9)))
    for rows in (scan_ordered, signed, repeated, with_inf, short):
        rows = rows.astype(np.float32)
        np.testing.assert_array_equal(_smallest_k_float32(rows, k), _smallest_k(rows, k))


def test_float32_selection_orders_nan_last() -> None:
    rows = np.arange(40, dtype=np.float32)[::-1].reshape(2, 20).copy()
    rows[0, 19] = rows[1, :15] = np.nan  # row 0: its smallest is NaN; row 1: 5 numbers only
    picked = _smallest_k_float32(rows, 8)
    assert picked[0].tolist() == [18, 17, 16, 15, 14, 13, 12, 11]
    assert picked[1, :5].tolist() == [19, 18, 17, 16, 15] and sorted(picked[1, 5:].tolist()) == [0, 1, 2]


def test_float64_non_contiguous_and_grad_inputs() -> None:
    base = torch.randn(20, 40, dtype=torch.float64, requires_grad=True)
    scores = base.t()  # (40, 20), not contiguous, tracked by autograd
    picked = smallest_k_indices(scores, 5)
    expected = scores.topk(5, dim=-1, largest=False).indices
    assert torch.equal(picked.sort(dim=-1).values, expected.sort(dim=-1).values)


def test_rejects_bad_k() -> None:
    with pytest.raises(ValueError, match="1 <= k <= 8"):
        smallest_k_indices(torch.zeros(2, 8), 9)


def _check_eigh(matrices: torch.Tensor) -> None:
    values, vectors = symmetric_eigh_3x3(matrices)
    expected_values, _ = torch.linalg.eigh(matrices)
    scale = matrices.abs().amax(dim=(-1, -2)).clamp_min(1e-12)
    assert torch.allclose(values, expected_values, atol=1e-10 * scale.max().item() + 1e-300)
    # A V = V diag(values), V orthonormal.
    assert torch.allclose(matrices @ vectors, vectors * values.unsqueeze(-2), atol=1e-9 * scale.max().item())
    eye = torch.eye(3, dtype=torch.float64).expand_as(matrices)
    assert torch.allclose(vectors.transpose(-1, -2) @ vectors, eye, atol=1e-10)


def test_eigh_matches_torch_on_random_covariances() -> None:
    points = torch.randn(500, 12, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(1))
    points = points * torch.tensor([3.0, 1.0, 0.01], dtype=torch.float64)  # plane-like, like surfaces
    centred = points - points.mean(dim=1, keepdim=True)
    _check_eigh(centred.transpose(-1, -2) @ centred / 12)


@pytest.mark.parametrize("diagonal", [(0.0, 0.0, 0.0), (1.0, 1.0, 1.0), (2.0, 2.0, 0.0), (5.0, 0.0, 0.0)])
def test_eigh_handles_degenerate_spectra(diagonal: tuple[float, float, float]) -> None:
    rotation, _ = torch.linalg.qr(torch.randn(3, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(2)))
    matrix = rotation @ torch.diag(torch.tensor(diagonal, dtype=torch.float64)) @ rotation.T
    _check_eigh(matrix.expand(4, 3, 3).contiguous())


def test_local_geometry_ranks_each_set_by_distance() -> None:
    """Neighbour sets given in any order: the curvature is that of the k nearest, the frame and
    radius those of the frame_k nearest."""
    from cadpu.kernels import local_geometry

    # Point 0's four nearest (itself included) lie in the plane z = 0; the fifth is far above it.
    points = torch.tensor([[[0.0, 0, 0], [1.0, 0, 0], [0, 1.0, 0], [1.0, 1.0, 0], [0, 0, 5.0]]],
                          dtype=torch.float64)
    index = torch.tensor([[[4, 3, 2, 1, 0]] * 5])  # listed far-to-near for point 0
    kappa, frames, radius = local_geometry(points, index, 4, 5)
    assert kappa[0, 0].item() == pytest.approx(0.0, abs=1e-12)  # the four nearest: flat
    centred = points[0] - points[0].mean(0)
    assert radius[0, 0].item() == pytest.approx(float(centred.pow(2).sum(1).mean().sqrt()))
    kappa_all, frames_near, _ = local_geometry(points, index[..., :5], 5, 4)
    assert kappa_all[0, 0].item() > 0.01  # all five: not flat
    assert torch.allclose(frames_near[0, 0, :, 2], torch.tensor([0.0, 0, 1], dtype=torch.float64))
    with pytest.raises(ValueError, match="max"):
        local_geometry(points, index, 3, 4)


def test_distances_3d_match_torch_and_are_exact_at_zero() -> None:
    torch.manual_seed(0)
    a, b = torch.randn(3, 50, 3), torch.randn(3, 70, 3) * 2.0
    got = distances_3d(a, b)
    assert got.shape == (3, 50, 70) and got.dtype == torch.float32
    assert torch.allclose(got, torch.cdist(a.double(), b.double()).float(), atol=1e-6)
    assert torch.allclose(got ** 2, pairwise_sq_dist(a, b), atol=1e-4)
    assert torch.equal(distances_3d(a, a).diagonal(dim1=1, dim2=2), torch.zeros(3, 50))
    # a non-contiguous view and a tensor with a gradient are read as they are
    tracked = b.clone().requires_grad_(True)
    assert torch.equal(distances_3d(a.transpose(0, 1).contiguous().transpose(0, 1), tracked), got)


def test_farthest_point_picks_are_torchs_greedy_picks() -> None:
    points = np.random.default_rng(4).normal(size=(3, 500, 3)).astype(np.float32)
    picks = farthest_point_picks(points, 200)
    assert np.array_equal(picks, farthest_point_sampling(torch.from_numpy(points), 200).numpy())


def test_farthest_point_picks_start_where_asked() -> None:
    points = np.random.default_rng(6).normal(size=(2, 300, 3)).astype(np.float32)
    for start in (17, np.array([5, 250])):
        picks = farthest_point_picks(points, 50, start)
        assert np.array_equal(picks[:, 0], np.broadcast_to(start, (2,)))
        for b in range(2):  # each set from its own start: the greedy picks of torch's loop from there
            expected = farthest_point_sampling(torch.from_numpy(points[b:b + 1]), 50, start=int(picks[b, 0]))
            assert np.array_equal(picks[b], expected[0].numpy())
    with pytest.raises(ValueError, match="start must index"):
        farthest_point_picks(points, 5, 300)


def test_farthest_point_picks_stay_distinct_among_copies() -> None:
    # ten distinct points, each three times: after the ten, the greedy pick of a distance of 0
    # would pick point 0 again and again
    distinct = np.random.default_rng(5).normal(size=(1, 10, 3)).astype(np.float32)
    copies = np.repeat(distinct, 3, axis=1)
    picks = farthest_point_picks(copies, 25)[0]
    assert len(set(picks.tolist())) == 25
    assert len({tuple(p) for p in copies[0, picks[:10]]}) == 10  # every distinct point before any copy


@pytest.mark.parametrize("count", [0, 11])
def test_farthest_point_picks_refuse_a_count_out_of_range(count: int) -> None:
    with pytest.raises(ValueError, match="1 <= count <= M"):
        farthest_point_picks(np.zeros((1, 10, 3), np.float32), count)
