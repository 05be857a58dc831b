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

from .kernels import UNFILLED_KEY, sort_key, keep_smallest

#: The relative resolution of the float32 prices and costs the auction runs on.
PRICE_RESOLUTION = float(np.finfo(np.float32).eps)
#: Columns each row keeps as its candidate list.
CANDIDATES = 8
#: Epsilon is divided by this between scaling phases.
SCALING = 5.0

_POOLS: dict[int, ThreadPoolExecutor] = {}


#: Contiguous entries of a row whose minimum `_refresh` takes at once (a block); a block whose
#: minimum is above the bound holds no candidate and is not read again.
BLOCK = 16


@njit(cache=True, nogil=True, fastmath=True)
def _block_minima(row: np.ndarray, prices: np.ndarray, minima: np.ndarray) -> None:  # pragma: no cover
    """minima[b] = the least row[j] + prices[j] over block b's BLOCK entries (whole blocks only).
    fastmath lets the minimum vectorise; it assumes finite values, which the auction's costs and
    prices are (`auction_assignment` refuses others), so no infinity starts the minimum either."""
    for b in range(minima.shape[0]):
        least = row[b * BLOCK] + prices[b * BLOCK]
        for j in range(1, BLOCK):
            least = min(least, row[b * BLOCK + j] + prices[b * BLOCK + j])
        minima[b] = least


@njit(cache=True, nogil=True)
def _refresh(row: np.ndarray, prices: np.ndarray, columns: np.ndarray) -> float:  # pragma: no cover
    """Fill `columns` with the row's len(columns) cheapest columns at `prices` (ties: the lower
    column first); return the next value (inf when the row has no more).

    The minima of the row's contiguous blocks of BLOCK entries bound the size-th cheapest value (the
    size-th smallest minimum: size distinct entries are no larger); only the blocks whose minimum is
    within that bound are read again, and their entries within it are kept as
    `cadpu.kernels.sort_key`s, each inserted by a min and a max per slot without branches. The
    insertion by comparison it replaced mispredicted a branch for most entries, as the network's
    selection did (docs/inference.md, "A branch-free selection")."""
    size = columns.shape[0] + 1
    n = row.shape[0]
    blocks = n // BLOCK
    kept = np.empty(size, np.int64)
    kept[:] = UNFILLED_KEY
    bound = np.float32(np.inf)
    minima = np.empty(blocks, np.float32)
    _block_minima(row, prices, minima)
    if blocks >= size:
        for b in range(blocks):
            keep_smallest(kept, sort_key(minima[b], b))
        bound = minima[kept[size - 1] & 0xFFFFFFFF]
        kept[:] = UNFILLED_KEY
    for b in range(blocks):
        if minima[b] <= bound:
            for j in range(b * BLOCK, b * BLOCK + BLOCK):
                value = row[j] + prices[j]
                if value <= bound:
                    keep_smallest(kept, sort_key(value, j))
    for j in range(blocks * BLOCK, n):  # the entries after the last whole block
        keep_smallest(kept, sort_key(row[j] + prices[j], j))
    for t in range(size - 1):
        columns[t] = kept[t] & 0xFFFFFFFF
    if kept[size - 1] == UNFILLED_KEY:
        return np.inf
    return row[kept[size - 1] & 0xFFFFFFFF] + prices[kept[size - 1] & 0xFFFFFFFF]


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

