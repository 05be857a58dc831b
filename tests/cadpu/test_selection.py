"""cadpu.selection: the compiled k-smallest selection picks the same sets as torch.topk."""

from __future__ import annotations

import pytest
import torch

from cadpu.selection import smallest_k_indices


@pytest.mark.parametrize("shape, k", [((3, 50, 256), 16), ((7, 12), 12), ((4, 9), 1)])
def test_same_sets_as_topk(shape: tuple[int, ...], k: int) -> None:
    scores = torch.randn(*shape, generator=torch.Generator().manual_seed(0))
    picked = smallest_k_indices(scores, k)
    expected = scores.topk(k, dim=-1, largest=False).indices
    assert picked.shape == expected.shape and picked.dtype == torch.int64
    assert torch.equal(picked.sort(dim=-1).values, expected.sort(dim=-1).values)


def test_float64_non_contiguous_and_grad_inputs() -> None:
    base = torch.randn(20, 40, dtype=torch.float64, requires_grad=True)
    scores = base.t()  # (40, 20), not contiguous, tracked by autograd
    picked = smallest_k_indices(scores, 5)
    expected = scores.topk(5, dim=-1, largest=False).indices
    assert torch.equal(picked.sort(dim=-1).values, expected.sort(dim=-1).values)


def test_rejects_bad_k() -> None:
    with pytest.raises(ValueError, match="1 <= k <= 8"):
        smallest_k_indices(torch.zeros(2, 8), 9)
