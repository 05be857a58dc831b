"""Approximate minimum-cost assignment for the EMD: Bertsekas' auction with epsilon scaling.

For an n x n cost matrix the auction ends with every row i assigned to a column j that is within
epsilon of i's best column at the final prices (epsilon complementary slackness), so the total
cost is at most n * epsilon above the optimum: the mean matched distance (the EMD) is at most
epsilon above the exact one. `tests/cadpu/test_assignment.py` checks the bound against scipy's exact
`linear_sum_assignment`; `bench/train.py` prints the measured gap on training batches.

Each bid needs the best and second-best column of a row at the current prices. Prices only rise,
so a row keeps a short list of its best columns and the value the next one had when the list was
made: while the list's second best stays below that value, the list alone gives an exact bid, and
the full row is scanned only when it does not.
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor

import numpy as np
import torch
from numba import njit

from .kernels import insert_sorted

#: The relative resolution of the float32 prices and costs the auction runs on.
PRICE_RESOLUTION = float(np.finfo(np.float32).eps)
#: Columns each row keeps as its candidate list.
CANDIDATES = 8
#: Epsilon is divided by this between scaling phases.
SCALING = 5.0

_POOLS: dict[int, ThreadPoolExecutor] = {}


#: Strided groups whose minima bound a row's cheapest values in `_refresh` (at least CANDIDATES + 1).
GROUPS = 32


@njit(cache=True, nogil=True)
def _refresh(row: np.ndarray, prices: np.ndarray, columns: np.ndarray) -> float:  # pragma: no cover
    """Fill `columns` with the row's len(columns) cheapest columns at `prices`; return the next value.

    In three passes, as `cadpu.kernels.smallest_k_indices` selects: the minima of GROUPS strided
    groups (entries j, j + GROUPS, ...; vector registers), whose size-th smallest bounds the size-th
    smallest value (size distinct entries are no larger); the entries within the bound, collected
    without branches; then the cheapest of those kept sorted by insertion. The scan it replaced
    inserted as it went and could not be vectorised."""
    size = columns.shape[0] + 1
    n = row.shape[0]
    kept_value = np.full(size, np.inf, np.float32)
    kept_index = np.zeros(size, np.int64)
    bound = np.inf
    if GROUPS >= size:
        minima = np.full(GROUPS, np.inf, np.float32)
        whole = (n // GROUPS) * GROUPS
        for start in range(0, whole, GROUPS):
            for g in range(GROUPS):
                minima[g] = min(minima[g], row[start + g] + prices[start + g])
        for j in range(whole, n):
            minima[0] = min(minima[0], row[j] + prices[j])
        for g in range(GROUPS):
            if minima[g] < kept_value[size - 1]:
                insert_sorted(kept_value, kept_index, size - 1, minima[g], g)
        bound = kept_value[size - 1]
        kept_value[:] = np.inf
    candidates = np.empty(n, np.int64)
    count = 0
    for j in range(n):
        candidates[count] = j
        count += (row[j] + prices[j]) <= bound
    for s in range(count):
        j = candidates[s]
        value = row[j] + prices[j]
        if value < kept_value[size - 1]:
            insert_sorted(kept_value, kept_index, size - 1, value, j)
    columns[:] = kept_index[:size - 1]
    return kept_value[size - 1]


@njit(cache=True, nogil=True)
def _best_two(row: np.ndarray, prices: np.ndarray, columns: np.ndarray) -> tuple:  # pragma: no cover
    best = np.inf
    second = np.inf
    best_column = columns[0]
    for j in columns:
        value = row[j] + prices[j]
        if value < second:
            if value < best:
                second = best
                best = value
                best_column = j
            else:
                second = value
    return best, second, best_column


@njit(cache=True, nogil=True)
def _auction(cost: np.ndarray, epsilon: float, candidates: int, scaling: float) -> np.ndarray:  # pragma: no cover
    n = cost.shape[0]
    m = min(candidates, n - 1) if n > 1 else 1
    prices = np.zeros(n, np.float32)
    owner = np.full(n, -1, np.int64)
    assigned = np.full(n, -1, np.int64)
    queue = np.empty(n, np.int64)
    lists = np.empty((n, m), np.int64)
    threshold = np.empty(n, np.float32)
    for i in range(n):
        threshold[i] = _refresh(cost[i], prices, lists[i])
    eps = max(float(cost.max()) / 4.0, epsilon)
    while True:
        owner[:] = -1
        assigned[:] = -1
        for i in range(n):
            queue[i] = n - 1 - i
        top = n
        while top > 0:
            top -= 1
            i = queue[top]
            best, second, column = _best_two(cost[i], prices, lists[i])
            if second > threshold[i]:  # a column off the list may now be second (or best)
                threshold[i] = _refresh(cost[i], prices, lists[i])
                best, second, column = _best_two(cost[i], prices, lists[i])
            if n == 1:
                second = best
            prices[column] += second - best + eps
            previous = owner[column]
            owner[column] = i
            assigned[i] = column
            if previous >= 0:
                assigned[previous] = -1
                queue[top] = previous
                top += 1
        if eps <= epsilon:
            return assigned
        eps = max(eps / scaling, epsilon)


def auction_assignment(cost: np.ndarray, epsilon: float, threads: int = 1) -> np.ndarray:
    """Near-optimal bijections for a batch of square cost matrices.

    Args:
        cost: (B, n, n) non-negative costs (float32 is used).
        epsilon: > 0; each item's total cost is at most n * epsilon above its optimum. Costs
            must not exceed `largest_cost(epsilon)` (ValueError).
        threads: items solved concurrently (the kernel releases the GIL).

    Returns:
        (B, n) int64: the column assigned to every row.
    """
    if cost.ndim != 3 or cost.shape[1] != cost.shape[2]:
        raise ValueError(f"auction_assignment: need (B, n, n) costs, got {cost.shape}")
    if not epsilon > 0:
        raise ValueError(f"auction_assignment: epsilon must be > 0, got {epsilon}")
    matrices = np.ascontiguousarray(cost, dtype=np.float32)
    largest = float(matrices.max()) if matrices.size else 0.0  # NaN when any cost is, inf when any is
    if not np.isfinite(largest):  # the bidding never ended on a NaN cost, beyond any signal's reach
        raise ValueError(f"auction_assignment: {int((~np.isfinite(matrices)).sum())} costs are NaN or infinite")
    if largest > largest_cost(epsilon):
        # prices rise to about the costs, where a float32 price plus epsilon rounds back to itself:
        # no bid then raises a price, and the bidding never ended (a run diverging to costs of 1e16)
        raise ValueError(f"auction_assignment: costs up to {largest:.3g}, where epsilon ({epsilon:g}) is below "
                         "float32's resolution: the bidding would never end")
    if threads <= 1 or len(matrices) == 1:
        return np.stack([_auction(c, epsilon, CANDIDATES, SCALING) for c in matrices])
    pool = _POOLS.setdefault(threads, ThreadPoolExecutor(max_workers=threads))
    return np.stack(list(pool.map(lambda c: _auction(c, epsilon, CANDIDATES, SCALING), matrices)))


def largest_cost(epsilon: float) -> float:
    """The largest cost `auction_assignment` takes at `epsilon`: beyond it a float32 price plus
    epsilon rounds back to the price (about 420 for 1e-4)."""
    return epsilon / (2 * PRICE_RESOLUTION)


def matched_cost(cost: torch.Tensor | np.ndarray, columns: torch.Tensor | np.ndarray) -> np.ndarray:
    """Mean cost of each item's assignment: (B, n, n) costs, (B, n) columns -> (B,) float64."""
    cost = np.asarray(cost, dtype=np.float64)
    columns = np.asarray(columns)
    return np.take_along_axis(cost, columns[..., None], axis=2)[..., 0].mean(-1)

