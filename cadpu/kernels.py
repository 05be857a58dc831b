"""Hot loops of the network, compiled with Numba, for CPU tensors (what each replaced and how much
it saves: docs/inference.md, "Compiled inference kernels").

- `smallest_k_indices`: the k smallest entries of every row, nearest first (the kNN searches),
  several times faster than torch.topk on a CPU; float32 rows by `_smallest_k_float32`, whose
  selection compares single integer keys without branches.
- `local_geometry`: each point's curvature, local frame and radius from its neighbour set in one
  pass (two covariances, two 3x3 eigen-decompositions), without gathering every neighbourhood.
- `edge_terms`: a dense EdgeConv block's per-edge inputs gathered and added in one pass, where
  torch needs a gather and an add per layer.
- `expansion_hidden`, `placed_points`: the generator's expansion and its last step (offsets in
  the parents' frames) without materialising the gathered per-output tensors.
- `symmetric_eigh_3x3`: eigen-decomposition of many 3x3 covariance matrices by cyclic Jacobi
  rotations; torch.linalg.eigh goes through LAPACK per matrix at about 1.6 us each.
- `farthest_point_picks`: greedy farthest point sampling in each of a batch of point sets, in one
  pass per pick (the oversampled upsampling's selection, `cadpu.inference.Upsampler`), where
  torch's loop makes four tensor calls per pick.
- `distances_3d`: all distances between two batched 3-D point sets, from the coordinate
  differences in one pass, where torch's expansion |a|^2 + |b|^2 - 2 a.b and a square root make
  five passes over the (B, N, M) result (the training losses' distances, `cadpu.losses`).
"""

from __future__ import annotations

import numpy as np
import torch
from numba import njit


#: Entries of a row whose minima `_candidates` takes at once: a 256-bit vector of float32, the width
#: LLVM vectorises to on AVX2 and AVX-512 CPUs alike. The loops over them must have this constant
#: trip count to be vectorised: with a trip count known only at run time (k) they were not.
BOUND_LANES = 8
#: A `sort_key` slot not yet filled: larger than every key.
UNFILLED_KEY = np.int64(0x7FFFFFFFFFFFFFFF)
#: The value half of a NaN entry's `sort_key`: above every float32's, +inf's included.
NAN_VALUE_BITS = 0x7FFFFFFF


@njit(cache=True, nogil=True, inline="always")
def _candidates(row: np.ndarray, k: int, minima: np.ndarray, candidates: np.ndarray) -> int:  # pragma: no cover
    """Write into `candidates` the indices of the row's entries within a bound on its k-th smallest
    (in index order) and return their count, at least k: all of the row's when NaN entries spoil
    the bound or the row is shorter than len(minima) groups.

    The bound: the largest of the minima of len(minima) >= k disjoint groups (entries j, j + G,
    j + 2G, ...: k distinct entries are no larger). The groups' minima are taken BOUND_LANES at a
    time (vector registers), and on rows where near points sit at nearby indices (scan order) the
    bound stays tight: about 40 of 256 entries pass it for k = 16. The collection has no branch."""
    m = row.shape[0]
    groups = minima.shape[0]
    whole = (m // groups) * groups
    if whole < groups:
        minima[0] = np.inf  # the bound in the minima's own type, as below
        bound = minima[0]
    else:
        for g in range(groups):
            minima[g] = row[g]
        for start in range(groups, whole, groups):
            for b in range(groups // BOUND_LANES):
                for j in range(BOUND_LANES):
                    value = row[start + b * BOUND_LANES + j]
                    least = minima[b * BOUND_LANES + j]
                    minima[b * BOUND_LANES + j] = value if value < least else least
        bound = minima[0]
        for g in range(1, groups):
            bound = max(bound, minima[g])
    count = 0
    for j in range(m):
        candidates[count] = j
        count += row[j] <= bound
    if count < k:
        for j in range(m):
            candidates[j] = j
        count = m
    return count


@njit(cache=True, nogil=True)
def _smallest_k(scores: np.ndarray, k: int) -> np.ndarray:  # pragma: no cover - compiled
    """Indices of the k smallest entries of every row, smallest first, ties by the lower index: the
    `_candidates` of each row kept sorted by insertion (any float type; float32 rows take
    `_smallest_k_float32`, the same indices faster)."""
    rows, m = scores.shape
    out = np.empty((rows, k), np.int64)
    minima = np.empty(-(-k // BOUND_LANES) * BOUND_LANES, scores.dtype)
    candidates = np.empty(m, np.int64)
    kept = np.empty(k, scores.dtype)
    for r in range(rows):
        row = scores[r]
        count = _candidates(row, k, minima, candidates)
        # the first k, sorted by insertion, then each smaller one inserted in its place (the
        # largest kept drops out)
        for s in range(k):
            insert_sorted(kept, out[r], s, row[candidates[s]], candidates[s])
        for s in range(k, count):
            value = row[candidates[s]]
            if value < kept[k - 1]:
                insert_sorted(kept, out[r], k - 1, value, candidates[s])
    return out


@njit(cache=True, nogil=True, inline="always")
def sort_key(value: float, index: int) -> int:  # pragma: no cover - compiled
    """One int64 that orders (float32 value, index) pairs as the values and then the indices order
    them: the value's bits made monotone (negative floats' magnitude bits flipped, -0.0 as 0.0, NaN
    above +inf) in the high half, the index (0 <= index < 2**32) in the low half."""
    if value != value:
        bits = np.int64(NAN_VALUE_BITS)
    elif value == 0.0:
        bits = np.int64(0)
    else:
        bits = np.int64(np.float32(value).view(np.int32))
        if bits < 0:
            bits = bits ^ 0x7FFFFFFF
    return (bits << 32) | index


@njit(cache=True, nogil=True, inline="always")
def keep_smallest(kept: np.ndarray, key: int) -> None:  # pragma: no cover - compiled
    """Insert `key` into the ascending int64 keys `kept` (the largest drops out) without a branch:
    slot t keeps its key, takes the new one, or takes slot t - 1's, by a min and a max."""
    for t in range(kept.shape[0] - 1, 0, -1):
        kept[t] = min(kept[t], max(kept[t - 1], key))
    kept[0] = min(kept[0], key)


@njit(cache=True, nogil=True)
def _smallest_k_float32(scores: np.ndarray, k: int) -> np.ndarray:  # pragma: no cover - compiled
    """`_smallest_k` of float32 rows: the same indices in the same order (on rows without NaN).

    The candidates are kept as `sort_key`s, and each is inserted into the ascending k kept keys by
    a min and a max per slot, without branches: the insertion loop of `_smallest_k` mispredicted a
    branch for most candidates, and was two thirds of its time."""
    rows, m = scores.shape
    out = np.empty((rows, k), np.int64)
    minima = np.empty(-(-k // BOUND_LANES) * BOUND_LANES, np.float32)
    candidates = np.empty(m, np.int64)
    kept = np.empty(k, np.int64)
    for r in range(rows):
        row = scores[r]
        count = _candidates(row, k, minima, candidates)
        for t in range(k):
            kept[t] = UNFILLED_KEY
        for s in range(count):
            keep_smallest(kept, sort_key(row[candidates[s]], candidates[s]))
        for t in range(k):
            out[r, t] = kept[t] & 0xFFFFFFFF
    return out


@njit(cache=True, nogil=True, inline="always")
def insert_sorted(values: np.ndarray, labels: np.ndarray, free: int, value: float,
                  label: int) -> None:  # pragma: no cover - compiled
    """Insert `value` (with `label`) into ascending values[:free], which has room at `free` (the
    entry there is overwritten): larger entries shift up one place; equal ones stay before it."""
    t = free
    while t > 0 and values[t - 1] > value:
        values[t] = values[t - 1]
        labels[t] = labels[t - 1]
        t -= 1
    values[t] = value
    labels[t] = label


def smallest_k_indices(scores: torch.Tensor, k: int) -> torch.Tensor:
    """Indices of the k smallest entries along the last axis, smallest first.

    As `scores.topk(k, largest=False).indices` (ties may pick different indices, and keep the
    lower index first).

    Args:
        scores: (..., M) floating-point CPU tensor (bfloat16 and float16 are widened to float32),
            1 <= k <= M; gradients are not followed.

    Returns:
        (..., k) int64 CPU tensor.
    """
    m = scores.shape[-1]
    if not 1 <= k <= m:
        raise ValueError(f"need 1 <= k <= {m}, got k = {k}")
    if scores.dtype in (torch.bfloat16, torch.float16):  # numpy has no bfloat16
        scores = scores.float()
    rows = scores.detach().reshape(-1, m).contiguous().numpy()
    select = _smallest_k_float32 if rows.dtype == np.float32 and m < 2**32 else _smallest_k
    return torch.from_numpy(select(rows, k)).reshape(*scores.shape[:-1], k)


def _arrays(*tensors: torch.Tensor):  # -> np.ndarray | tuple[np.ndarray, ...]
    """C-contiguous numpy views (copies where needed) of CPU tensors, gradients not followed: what
    the compiled loops take. One tensor gives one array, several a tuple."""
    arrays = tuple(t.detach().contiguous().numpy() for t in tensors)
    return arrays[0] if len(arrays) == 1 else arrays


@njit(cache=True, nogil=True)
def _edge_terms(neighbour: np.ndarray, own: np.ndarray, index: np.ndarray,
                edges: np.ndarray) -> None:  # pragma: no cover - compiled
    points = own.shape[0]
    layers, _, width = edges.shape
    for e in range(index.shape[0]):
        j = index[e]
        p = e % points
        for layer in range(layers):
            offset = layer * width
            for c in range(width):
                edges[layer, e, c] = neighbour[j, offset + c] + own[p, offset + c]


def edge_terms(neighbour: torch.Tensor, own: torch.Tensor, index: torch.Tensor, layers: int) -> torch.Tensor:
    """The per-edge inputs of a dense EdgeConv block's layers, gathered and added in one pass.

    Args:
        neighbour: (P, layers * g) float32, each point's term as a neighbour j, layer by layer.
        own: (P, layers * g) float32, each point's term as the centre i.
        index: (K * P,) int64, neighbour-major: entry k * P + i is the k-th neighbour of point i.
        layers: how many layers the columns hold.

    Returns:
        (layers, K * P, g) float32: edges[l, k * P + i] = neighbour[index[k * P + i], l] + own[i, l].
    """
    columns = own.shape[1]
    edges = torch.empty(layers, index.shape[0], columns // layers, dtype=torch.float32)
    _edge_terms(_arrays(neighbour), _arrays(own), _arrays(index), edges.numpy())
    return edges


@njit(cache=True, nogil=True)
def _expansion_hidden(projected: np.ndarray, table: np.ndarray, parents: np.ndarray, rank: np.ndarray,
                      out: np.ndarray) -> None:  # pragma: no cover - compiled
    batch, m = parents.shape
    width = table.shape[1]
    for b in range(batch):
        for i in range(m):
            parent, code = parents[b, i], rank[b, i]
            for c in range(width):
                out[b, i, c] = max(projected[b, parent, c] + table[code, c], 0.0)


def expansion_hidden(projected: torch.Tensor, table: torch.Tensor, parents: torch.Tensor,
                     rank: torch.Tensor) -> torch.Tensor:
    """The expansion MLP's first hidden layer, gathered, added and ReLU'd in one pass.

    Args:
        projected: (B, N, W) float32, each input point's feature term. table: (R, W) float32, each
            grid code's term. parents, rank: (B, M) int64, each output's parent point and code.

    Returns:
        (B, M, W) float32: relu(projected[b, parents[b, i]] + table[rank[b, i]]).
    """
    out = torch.empty(*parents.shape, table.shape[1], dtype=torch.float32)
    _expansion_hidden(*_arrays(projected, table, parents, rank), out.numpy())
    return out


@njit(cache=True, nogil=True)
def _placed_points(points: np.ndarray, frames: np.ndarray, radius: np.ndarray, parents: np.ndarray,
                   rank: np.ndarray, learned: np.ndarray, skip: np.ndarray, local: bool,
                   out: np.ndarray) -> None:  # pragma: no cover - compiled
    batch, m = parents.shape
    in_frame = np.empty(3, np.float32)
    for b in range(batch):
        for i in range(m):
            parent, code = parents[b, i], rank[b, i]
            for a in range(3):
                in_frame[a] = learned[b, i, a] + skip[code, a] if local else skip[code, a]
            for a in range(3):
                offset = (frames[b, parent, a, 0] * in_frame[0] + frames[b, parent, a, 1] * in_frame[1]
                          + frames[b, parent, a, 2] * in_frame[2])
                if not local:
                    offset += learned[b, i, a]
                out[b, i, a] = points[b, parent, a] + offset * radius[b, parent]


def placed_points(points: torch.Tensor, frames: torch.Tensor, radius: torch.Tensor, parents: torch.Tensor,
                  rank: torch.Tensor, learned: torch.Tensor, skip: torch.Tensor, local: bool) -> torch.Tensor:
    """Generated points from their offsets, in one pass (`cadpu.network.Generator.decode`'s last step).

    Args:
        points: (B, N, 3) float32 input patch. frames: (B, N, 3, 3) local frames (columns: axes).
        radius: (B, N) neighbourhood radii. parents, rank: (B, M) int64. learned: (B, M, 3) the
        regressed offsets. skip: (R, 3) each grid code's offset in the local frame. local: whether
        `learned` is in the local frame (else in the patch's axes).

    Returns:
        (B, M, 3) float32: points[parent] + radius[parent] * (frame[parent] @ (learned + skip[code]))
        (local), or + radius[parent] * (frame[parent] @ skip[code] + learned) (global).
    """
    out = torch.empty(*parents.shape, 3, dtype=torch.float32)
    _placed_points(*_arrays(points, frames, radius, parents, rank, learned, skip), local, out.numpy())
    return out


@njit(cache=True, nogil=True)
def _local_geometry(points: np.ndarray, index: np.ndarray, k: int, frame_k: int, kappa: np.ndarray,
                    frames: np.ndarray, radius: np.ndarray) -> None:  # pragma: no cover - compiled
    batch, n, size = index.shape
    distance = np.empty(size)
    order = np.empty(size, np.int64)
    covariance = np.empty((3, 3))
    a = np.empty((3, 3))
    v = np.empty((3, 3))
    values = np.empty(3)
    vectors = np.empty((3, 3))
    for b in range(batch):
        for i in range(n):
            # The neighbours in ascending distance (insertion sort: `size` is a few dozen at most).
            for s in range(size):
                j = index[b, i, s]
                dx = points[b, j, 0] - points[b, i, 0]
                dy = points[b, j, 1] - points[b, i, 1]
                dz = points[b, j, 2] - points[b, i, 2]
                insert_sorted(distance, order, s, dx * dx + dy * dy + dz * dz, j)
            # Surface variation of the k nearest; frame and radius of the frame_k nearest.
            _covariance_of(points, b, order, k, covariance)
            _clamped_eigh(covariance, a, v, values, vectors)
            kappa[b, i] = values[0] / max(values[0] + values[1] + values[2], 1e-30)
            if frame_k != k:
                _covariance_of(points, b, order, frame_k, covariance)
                _clamped_eigh(covariance, a, v, values, vectors)
            radius[b, i] = np.sqrt(values[0] + values[1] + values[2])
            # Signs by a global rule: major tangent towards +x, normal towards +z; minor = normal x major.
            major_sign = -1.0 if vectors[0, 2] < 0 else 1.0
            normal_sign = -1.0 if vectors[2, 0] < 0 else 1.0
            mx, my, mz = vectors[0, 2] * major_sign, vectors[1, 2] * major_sign, vectors[2, 2] * major_sign
            nx, ny, nz = vectors[0, 0] * normal_sign, vectors[1, 0] * normal_sign, vectors[2, 0] * normal_sign
            frames[b, i, 0, 0], frames[b, i, 1, 0], frames[b, i, 2, 0] = mx, my, mz
            frames[b, i, 0, 1], frames[b, i, 1, 1], frames[b, i, 2, 1] = ny * mz - nz * my, nz * mx - nx * mz, nx * my - ny * mx
            frames[b, i, 0, 2], frames[b, i, 1, 2], frames[b, i, 2, 2] = nx, ny, nz


@njit(cache=True, nogil=True, inline="always")
def _clamped_eigh(matrix: np.ndarray, a: np.ndarray, v: np.ndarray, values: np.ndarray,
                  vectors: np.ndarray) -> None:  # pragma: no cover - compiled
    """`_eigh_one`, with the eigenvalues clamped at 0 (covariances: negative only by rounding)."""
    _eigh_one(matrix, a, v, values, vectors)
    for c in range(3):
        values[c] = max(values[c], 0.0)


def local_geometry(points: torch.Tensor, index: torch.Tensor, k: int, frame_k: int
                   ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Curvature, local frame and radius of every point from its neighbour set, in one pass (what
    `cadpu.geometry.curvature_and_frames` computes; see it for the definitions).

    Args:
        points: (B, N, 3) CPU tensor (used in float64). index: (B, N, max(k, frame_k)) int64
            neighbour sets into N, in any order. k: neighbours of the curvature. frame_k: of the
            frame and radius.

    Returns:
        kappa (B, N), frames (B, N, 3, 3) (columns: major tangent towards +x, minor tangent,
        normal towards +z) and radius (B, N), float64; no gradients.
    """
    size = index.shape[-1]
    if not (1 <= k <= size and 1 <= frame_k <= size and max(k, frame_k) == size):
        raise ValueError(f"need neighbour sets of max(k, frame_k) = {max(k, frame_k)}, got {size}")
    array = points.detach().to(torch.float64).contiguous().numpy()
    lead = index.shape[:2]
    kappa, frames, radius = np.empty(lead), np.empty((*lead, 3, 3)), np.empty(lead)
    _local_geometry(array, _arrays(index), k, frame_k, kappa, frames, radius)
    return torch.from_numpy(kappa), torch.from_numpy(frames), torch.from_numpy(radius)


@njit(cache=True, nogil=True, inline="always")
def _covariance_of(points: np.ndarray, b: int, members: np.ndarray, count: int,
                   out: np.ndarray) -> None:  # pragma: no cover - compiled
    """Covariance (divided by count) of points[b, members[:count]] about their mean, into out (3, 3)."""
    mean = np.zeros(3)
    for s in range(count):
        for a in range(3):
            mean[a] += points[b, members[s], a]
    for a in range(3):
        mean[a] /= count
    for a in range(3):
        for c in range(3):
            out[a, c] = 0.0
    for s in range(count):
        j = members[s]
        for a in range(3):
            da = points[b, j, a] - mean[a]
            for c in range(a, 3):
                out[a, c] += da * (points[b, j, c] - mean[c])
    for a in range(3):
        for c in range(a, 3):
            out[a, c] /= count
            out[c, a] = out[a, c]


@njit(cache=True, nogil=True)
def _eigh_one(matrix: np.ndarray, a: np.ndarray, v: np.ndarray, values: np.ndarray,
              vectors: np.ndarray) -> None:  # pragma: no cover - compiled
    """Eigenvalues (ascending) into values (3,) and eigenvectors (columns) into vectors (3, 3) of
    one symmetric 3x3 `matrix`, by cyclic Jacobi rotations; a and v are (3, 3) scratch."""
    for i in range(3):
        for j in range(3):
            a[i, j] = matrix[i, j]
            v[i, j] = 1.0 if i == j else 0.0
    scale = a[0, 0] * a[0, 0] + a[1, 1] * a[1, 1] + a[2, 2] * a[2, 2]
    for _sweep in range(12):
        off = a[0, 1] * a[0, 1] + a[0, 2] * a[0, 2] + a[1, 2] * a[1, 2]
        if off <= 1e-30 * scale or off == 0.0:
            break
        for p, q in ((0, 1), (0, 2), (1, 2)):
            apq = a[p, q]
            if apq == 0.0:
                continue
            # The classical Jacobi rotation in the (p, q) plane that zeroes a[p, q].
            theta = (a[q, q] - a[p, p]) / (2.0 * apq)
            t = (1.0 if theta >= 0.0 else -1.0) / (abs(theta) + np.sqrt(theta * theta + 1.0))
            c = 1.0 / np.sqrt(t * t + 1.0)
            s = t * c
            for k in range(3):
                akp, akq = a[k, p], a[k, q]
                a[k, p] = c * akp - s * akq
                a[k, q] = s * akp + c * akq
            for k in range(3):
                apk, aqk = a[p, k], a[q, k]
                a[p, k] = c * apk - s * aqk
                a[q, k] = s * apk + c * aqk
            for k in range(3):
                vkp, vkq = v[k, p], v[k, q]
                v[k, p] = c * vkp - s * vkq
                v[k, q] = s * vkp + c * vkq
    # Ascending order (three values: compare directly), vectors as columns.
    i0, i1, i2 = 0, 1, 2
    if a[i0, i0] > a[i1, i1]:
        i0, i1 = i1, i0
    if a[i1, i1] > a[i2, i2]:
        i1, i2 = i2, i1
    if a[i0, i0] > a[i1, i1]:
        i0, i1 = i1, i0
    for column, i in enumerate((i0, i1, i2)):
        values[column] = a[i, i]
        for k in range(3):
            vectors[k, column] = v[k, i]


@njit(cache=True, nogil=True)
def _jacobi_eigh_3x3(matrices: np.ndarray, values: np.ndarray, vectors: np.ndarray) -> None:  # pragma: no cover
    a = np.empty((3, 3))
    v = np.empty((3, 3))
    for m in range(matrices.shape[0]):
        _eigh_one(matrices[m], a, v, values[m], vectors[m])


def symmetric_eigh_3x3(matrices: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Eigenvalues (ascending) and eigenvectors (columns) of symmetric 3x3 matrices.

    Same contract as `torch.linalg.eigh` (eigenvector signs are arbitrary); no gradients.

    Args:
        matrices: (..., 3, 3) float64 CPU tensor, symmetric.

    Returns:
        values (..., 3) and vectors (..., 3, 3), float64.
    """
    flat = matrices.detach().reshape(-1, 3, 3).to(torch.float64).contiguous().numpy()
    values = np.empty((len(flat), 3))
    vectors = np.empty((len(flat), 3, 3))
    _jacobi_eigh_3x3(flat, values, vectors)
    lead = matrices.shape[:-2]
    return torch.from_numpy(values).reshape(*lead, 3), torch.from_numpy(vectors).reshape(*lead, 3, 3)


def distances_3d(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """(B, N, M) float32 Euclidean distances between the points of (B, N, 3) `a` and (B, M, 3) `b`
    (CPU tensors; no gradient), each from its coordinate differences."""
    first = np.ascontiguousarray(a.detach().numpy(), dtype=np.float32)
    second = np.ascontiguousarray(b.detach().numpy().transpose(0, 2, 1), dtype=np.float32)
    out = np.empty((first.shape[0], first.shape[1], second.shape[2]), np.float32)
    return torch.from_numpy(_distances_3d(first, second, out))


@njit(cache=True, nogil=True)
def _distances_3d(a: np.ndarray, bt: np.ndarray, out: np.ndarray) -> np.ndarray:  # pragma: no cover
    for i in range(a.shape[0]):
        for p in range(a.shape[1]):
            x, y, z = a[i, p, 0], a[i, p, 1], a[i, p, 2]
            for q in range(bt.shape[2]):  # bt is (B, 3, M): this loop vectorises
                dx, dy, dz = x - bt[i, 0, q], y - bt[i, 1, q], z - bt[i, 2, q]
                out[i, p, q] = np.sqrt(dx * dx + dy * dy + dz * dz)
    return out


@njit(cache=True, nogil=True)
def _farthest_point_picks(points: np.ndarray, count: int, starts: np.ndarray,
                          out: np.ndarray) -> None:  # pragma: no cover - compiled
    batch, m = points.shape[0], points.shape[1]
    x, y, z = np.empty(m, np.float32), np.empty(m, np.float32), np.empty(m, np.float32)
    nearest = np.empty(m, np.float32)
    picked = np.empty(m, np.bool_)
    for b in range(batch):
        x[:], y[:], z[:] = points[b, :, 0], points[b, :, 1], points[b, :, 2]
        nearest[:] = np.inf
        picked[:] = False
        current = starts[b]
        for i in range(count):
            out[b, i] = current
            picked[current] = True
            cx, cy, cz = x[current], y[current], z[current]
            for j in range(m):  # branch-free, so that it vectorises
                dx, dy, dz = x[j] - cx, y[j] - cy, z[j] - cz
                nearest[j] = min(nearest[j], dx * dx + dy * dy + dz * dz)
            current = int(np.argmax(nearest))
            if nearest[current] == 0 and i + 1 < count:
                # only copies of picked points left: the next unpicked one, so that picks stay distinct
                current = int(np.argmin(picked))


def farthest_point_picks(points: np.ndarray, count: int, start: int | np.ndarray = 0) -> np.ndarray:
    """Greedy farthest point sampling of each set of a batch.

    Args:
        points: (B, M, 3) float32. count: picks per set, 1 <= count <= M.
        start: index into M of each set's first pick: one for all sets, or (B,) integers.

    Returns:
        (B, count) int64 distinct indices into M: the first `start`, each next the point farthest
        (by squared float32 distance; ties to the lowest index) from those picked before it; once
        only copies of picked points are left, the lowest unpicked index. The picks of
        `cadpu.geometry.farthest_point_sampling` from the same start (what runs on CUDA).
    """
    points = np.ascontiguousarray(points, dtype=np.float32)
    if points.ndim != 3 or points.shape[2] != 3 or not 1 <= count <= points.shape[1]:
        raise ValueError(f"farthest_point_picks: points must be (B, M, 3) with 1 <= count <= M, "
                         f"got {points.shape} and count {count}")
    starts = np.broadcast_to(np.asarray(start, dtype=np.int64), (points.shape[0],))
    if ((starts < 0) | (starts >= points.shape[1])).any():
        raise ValueError(f"farthest_point_picks: start must index the {points.shape[1]} points of a set, got {start}")
    out = np.empty((points.shape[0], count), np.int64)
    _farthest_point_picks(points, count, np.ascontiguousarray(starts), out)
    return out
