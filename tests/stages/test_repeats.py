"""stages.repeats: rows that repeat an earlier row's x, y, z."""

from __future__ import annotations

import numpy as np
import pytest

from stages.repeats import repeated_rows


def test_every_copy_after_the_first_is_found_as_numpy_finds_them() -> None:
    rng = np.random.default_rng(0)
    xyz = rng.integers(0, 6, size=(2_000, 3)).astype(np.float32)  # 216 places, many copies of each
    repeated = repeated_rows(xyz)
    _, first = np.unique(xyz, axis=0, return_index=True)
    assert set(np.flatnonzero(~repeated)) == set(first.tolist())


def test_a_scan_without_copies_has_none_and_zero_signs_do_not_matter() -> None:
    xyz = np.random.default_rng(1).normal(size=(10_000, 3)).astype(np.float32)
    assert not repeated_rows(xyz).any()
    assert repeated_rows(np.array([[0.0, 1, 2], [-0.0, 1, 2], [0.0, -1, 2]], np.float32)).tolist() == [False, True, False]
    assert repeated_rows(np.zeros((0, 3), np.float32)).shape == (0,)
    with pytest.raises(ValueError, match=r"must be \(N, 3\)"):
        repeated_rows(np.zeros((4, 4), np.float32))
