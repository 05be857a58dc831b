"""Point-set geometry used by the model, its training data and the stages.

Every function is batched over leading dimensions and accepts torch tensors; the numpy
entry points (`*_np`) wrap them for callers that hold arrays. Points are (..., N, 3) in
whatever frame the caller uses; distances are in that frame's units.
"""

from __future__ import annotations

import threading

import numpy as np
import torch
from scipy.spatial import cKDTree

from .kernels import local_geometry, smallest_k_indices, symmetric_eigh_3x3

#: Neighbourhood size of the surface-variation curvature (paper, section 4.1.2).
CURVATURE_K = 12
#: Most 3x3 matrices per `torch.linalg.eigh` call on the torch path. cuSOLVER's batched
#: eigensolver fails above about 32k matrices a call (CUSOLVER_STATUS_INTERNAL_ERROR at 65,536 on
#: an H100, a batch of 256 patches; mujocolab/mjlab#732 reports the same limit), so larger batches
#: go in calls of this many.
EIGH_CHUNK = 16_384

#: Device types whose linear-algebra library a `torch.linalg.eigh` call has loaded in this process.
_linalg_loaded: set[str] = set()
_linalg_lock = threading.Lock()


def pairwise_sq_dist(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Squared Euclidean distances between two batched point sets.

    Args:
        a: (B, N, C) points. b: (B, M, C) points.

    Returns:
        (B, N, M) squared distances, clamped at 0.
    """
    a2 = (a * a).sum(-1, keepdim=True)
    b2 = (b * b).sum(-1).unsqueeze(-2)
    return (a2 + b2 - 2.0 * a @ b.transpose(-1, -2)).clamp_min_(0.0)


def knn(query: torch.Tensor, points: torch.Tensor, k: int, nearest_first: bool = True) -> torch.Tensor:
    """Indices of the k nearest `points` of every `query` point (the point itself included
    when it belongs to `points`).

    Points are ranked by |p|^2 - 2 q.p, which orders them as |q - p|^2 does (the |q|^2 term is
    the same along a row): one fused matrix product and no full distance matrix.

    Args:
        query: (B, N, C). points: (B, M, C). k: neighbours, k <= M.
        nearest_first: sort each row nearest first; False returns the same set in any order (faster).

    Returns:
        (B, N, k) int64 indices into `points`.
    """
    squared_norms = (points * points).sum(-1).unsqueeze(-2)  # (B, 1, M)
    scores = torch.baddbmm(squared_norms, query, points.transpose(-1, -2), alpha=-2.0)
    if scores.device.type == "cpu" and not tracing_graph():
        return smallest_k_indices(scores, k)  # nearest first, whether asked or not
    return scores.topk(k, dim=-1, largest=False, sorted=nearest_first).indices


def tracing_graph() -> bool:
    """Whether torch is tracing this call into a graph (ONNX export, torch.compile), which the
    compiled kernels of `cadpu.kernels` cannot enter: the graph then holds torch's own operations
    (torch.topk for the kNN: the same neighbour set)."""
    return torch.jit.is_tracing() or torch.compiler.is_compiling() or torch.onnx.is_in_onnx_export()


def gather(points: torch.Tensor, index: torch.Tensor) -> torch.Tensor:
    """Batched gather: out[b, ...] = points[b, index[b, ...]].

    Args:
        points: (B, M, C). index: (B, ...) int64 into M.

    Returns:
        (B, ..., C).
    """
    batch, m, channels = points.shape
    offsets = (torch.arange(batch, device=points.device) * m).reshape(batch, *([1] * (index.dim() - 1)))
    # index_select on the flattened batch is several times faster than torch.gather on CPU.
    picked = points.reshape(batch * m, channels).index_select(0, (index + offsets).reshape(-1))
    return picked.reshape(*index.shape, channels)


def farthest_point_sampling(points: torch.Tensor, count: int, start: int | None = 0,
                            generator: torch.Generator | None = None) -> torch.Tensor:
    """Greedy farthest point sampling.

    Args:
        points: (B, N, 3). count: points to pick, <= N.
        start: index of the first pick; None draws it at random from `generator`.

    Returns:
        (B, count) int64 distinct indices into N: each next pick the point farthest from those
        before it (ties to the lowest index); once only copies of picked points are left, the
        lowest unpicked index.
    """
    batch, n, _ = points.shape
    chosen = torch.empty(batch, count, dtype=torch.long, device=points.device)
    if start is None:
        current = torch.randint(n, (batch,), generator=generator, device=points.device)
    else:
        current = torch.full((batch,), start, dtype=torch.long, device=points.device)
    nearest = torch.full((batch, n), float("inf"), device=points.device, dtype=points.dtype)
    rows = torch.arange(batch, device=points.device)
    for i in range(count):
        chosen[:, i] = current
        d = ((points - points[rows, current].unsqueeze(1)) ** 2).sum(-1)
        nearest = torch.minimum(nearest, d)
        nearest[rows, current] = -1.0  # never picked again: copies of it, at 0, come first
        current = nearest.argmax(-1)
    return chosen


def local_covariance(points: torch.Tensor, k: int = CURVATURE_K) -> torch.Tensor:
    """Covariance of every point's k-nearest neighbourhood (the point included).

    Args:
        points: (B, N, 3).

    Returns:
        (B, N, 3, 3) covariance matrices.
    """
    return _covariance(points, knn(points, points, k, nearest_first=False))


def _covariance(points: torch.Tensor, index: torch.Tensor) -> torch.Tensor:
    """(B, N, 3, 3) covariances of the neighbourhoods `index` (B, N, k) of (B, N, 3) points."""
    neighbours = gather(points, index)  # (B, N, k, 3)
    centred = neighbours - neighbours.mean(dim=2, keepdim=True)
    return centred.transpose(-1, -2) @ centred / index.shape[-1]


def curvature_and_normals(points: torch.Tensor, k: int = CURVATURE_K) -> tuple[torch.Tensor, torch.Tensor]:
    """Surface-variation curvature and unoriented normals (paper, section 4.1.2).

    kappa = l1 / (l1 + l2 + l3) with l1 <= l2 <= l3 the eigenvalues of the covariance of the
    k nearest neighbours: 0 on a plane, up to 1/3 for an isotropic neighbourhood. The normal is the
    eigenvector of l1.

    Args:
        points: (B, N, 3). k: neighbourhood size (12 in the paper).

    Returns:
        kappa (B, N) in [0, 1/3]; normals (B, N, 3) unit vectors, oriented towards +z.
    """
    kappa, frames, _ = curvature_and_frames(points, k)
    return kappa, frames[..., :, 2]


def curvature_and_frames(points: torch.Tensor, k: int = CURVATURE_K, frame_k: int | None = None,
                         curvature: bool = True) -> tuple[torch.Tensor | None, torch.Tensor, torch.Tensor]:
    """Surface-variation curvature, local PCA frame and neighbourhood radius of every point.

    Args:
        points: (B, N, 3).
        k: neighbourhood of the curvature (12 in the paper).
        frame_k: neighbourhood of the frame and radius; `k` when None. A wider one (24) keeps the
            frame of a point on a LiDAR scan line from degenerating: its 12 nearest neighbours
            often lie on its own line, which leaves the minor tangent and the normal undefined.
        curvature: False when only the frames and radii are needed: kappa is then None, and
            where frame_k exceeds k the curvature's own decomposition is skipped (the frames and
            radii are the same either way).

    Returns:
        kappa (B, N), or None (see `curvature`); frames (B, N, 3, 3), right-handed, whose columns
        are the major tangent (towards +x), the minor tangent and the normal (towards +z) of the
        neighbourhood; radius (B, N) = sqrt(l1 + l2 + l3), the RMS distance of the neighbours
        from their mean.
    """
    frame_k = frame_k or k
    if points.device.type == "cpu" and not points.requires_grad and not tracing_graph():
        # One neighbour search for both sizes (in float64 where the torch path searches in it);
        # the compiled kernel does the rest point by point.
        searched = points.double() if frame_k == k else points
        sets = knn(searched, searched, max(k, frame_k), nearest_first=False)
        if not curvature and frame_k > k:  # the same sets, ranked the same: the same frames
            _, frames, radius = local_geometry(points, sets, frame_k, frame_k)
            return None, frames.to(points.dtype), radius.to(points.dtype)
        kappa, frames, radius = local_geometry(points, sets, k, frame_k)
        return kappa.to(points.dtype) if curvature else None, frames.to(points.dtype), radius.to(points.dtype)
    double = points.double()
    if frame_k == k:
        kappa, vectors, values = _pca(local_covariance(double, k))
    else:
        neighbours = knn(points, points, max(k, frame_k), nearest_first=True)
        kappa = _pca(_covariance(double, neighbours[..., :k]))[0] if curvature else None
        _, vectors, values = _pca(_covariance(double, neighbours[..., :frame_k]))
    major, normal = vectors[..., :, 2], vectors[..., :, 0]
    # Eigenvector signs are arbitrary; fix them by a global rule (major tangent towards +x,
    # normal towards +z, minor = normal x major), so equal geometry always gets the same frame.
    major = major * torch.where(major[..., :1] < 0, -1.0, 1.0)
    normal = normal * torch.where(normal[..., 2:] < 0, -1.0, 1.0)
    minor = torch.linalg.cross(normal, major)
    frames = torch.stack([major, minor, normal], dim=-1)
    return kappa.to(points.dtype) if curvature else None, frames.to(points.dtype), values.sum(-1).sqrt().to(points.dtype)


def _pca(cov: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Surface variation (..., ), eigenvectors (..., 3, 3) as columns and eigenvalues (..., 3),
    ascending and clamped at 0, of (..., 3, 3) covariances."""
    if cov.requires_grad:
        values, vectors = _chunked_eigh(cov)
    elif cov.device.type == "cpu":
        values, vectors = symmetric_eigh_3x3(cov)
    else:
        values, vectors = jacobi_eigh_3x3(cov)
    values = values.clamp_min(0.0)
    return values[..., 0] / values.sum(-1).clamp_min(1e-30), vectors, values


#: Sweeps after which `jacobi_eigh_3x3` stops whether or not every matrix has converged (as the
#: compiled kernel `cadpu.kernels.symmetric_eigh_3x3` does; 3x3 matrices converge in about 5).
JACOBI_SWEEPS = 12
#: The planes of a sweep's rotations (p, q) and the third axis r, in the compiled kernel's order.
_JACOBI_PLANES = ((0, 1, 2), (0, 2, 1), (1, 2, 0))


def jacobi_eigh_3x3(matrices: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Eigenvalues (ascending) and eigenvectors (columns) of symmetric 3x3 matrices on any device.

    Cyclic Jacobi rotations, as `cadpu.kernels.symmetric_eigh_3x3` computes them on a CPU, in
    batched torch operations: the torch path's eigen-decomposition on a GPU. There, cuSOLVER's
    batched solver (`torch.linalg.eigh`) reserves gigabytes of workspace for the matrices of a
    batch of patches, so that four pipeline workers on one GPU ran out of memory, and it fails
    outright above about 32k matrices (docs/inference.md, "On a GPU"). No gradients.

    Args:
        matrices: (..., 3, 3) symmetric, float64 for the precision of the CPU path.

    Returns:
        values (..., 3) and vectors (..., 3, 3) in the dtype and on the device of `matrices`.
    """
    flat = matrices.detach().reshape(-1, 3, 3)
    a = {(i, j): flat[:, i, j].clone() for i in range(3) for j in range(i, 3)}
    v = torch.eye(3, dtype=flat.dtype, device=flat.device).expand(len(flat), 3, 3).clone()
    scale = a[0, 0] ** 2 + a[1, 1] ** 2 + a[2, 2] ** 2
    for _sweep in range(JACOBI_SWEEPS):
        off = a[0, 1] ** 2 + a[0, 2] ** 2 + a[1, 2] ** 2
        unconverged = (off > 1e-30 * scale) & (off != 0.0)
        if not bool(unconverged.any()):
            break
        for p, q, r in _JACOBI_PLANES:
            apq = a[p, q]
            rotate = unconverged & (apq != 0.0)
            # The classical rotation in the (p, q) plane that zeroes a[p, q]; t = 0 leaves a
            # matrix exactly as it is (c = 1, s = 0).
            theta = (a[q, q] - a[p, p]) / (2.0 * torch.where(rotate, apq, 1.0))
            t = torch.where(theta >= 0.0, 1.0, -1.0) / (theta.abs() + torch.sqrt(theta * theta + 1.0))
            t = torch.where(rotate, t, 0.0)
            c = 1.0 / torch.sqrt(t * t + 1.0)
            s = t * c
            a[p, p], a[q, q] = a[p, p] - t * apq, a[q, q] + t * apq
            a[p, q] = torch.where(rotate, 0.0, apq)
            arp, arq = a[min(r, p), max(r, p)], a[min(r, q), max(r, q)]
            a[min(r, p), max(r, p)], a[min(r, q), max(r, q)] = c * arp - s * arq, s * arp + c * arq
            vp, vq = v[:, :, p].clone(), v[:, :, q]
            v[:, :, p] = c[:, None] * vp - s[:, None] * vq
            v[:, :, q] = s[:, None] * vp + c[:, None] * vq
    values, order = torch.stack([a[0, 0], a[1, 1], a[2, 2]], dim=-1).sort(dim=-1, stable=True)
    vectors = v.gather(2, order[:, None, :].expand(-1, 3, -1))
    lead = matrices.shape[:-2]
    return values.reshape(*lead, 3), vectors.reshape(*lead, 3, 3)


def _chunked_eigh(cov: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """`torch.linalg.eigh` of (..., 3, 3) symmetric matrices, at most EIGH_CHUNK per call.

    Before the first call on a device type in this process, one identity matrix is decomposed under
    a lock: torch loads its CUDA linear-algebra library on first use, and concurrent first uses
    from several threads fail with "lazy wrapper should be called at most once"
    (pytorch/pytorch#90613), as a Dask worker running two frames at once on a GPU did.
    """
    if cov.device.type not in _linalg_loaded:
        with _linalg_lock:
            if cov.device.type not in _linalg_loaded:
                torch.linalg.eigh(torch.eye(3, dtype=cov.dtype, device=cov.device))
                _linalg_loaded.add(cov.device.type)
    flat = cov.reshape(-1, 3, 3)
    if len(flat) <= EIGH_CHUNK:
        return torch.linalg.eigh(cov)
    parts = [torch.linalg.eigh(chunk) for chunk in flat.split(EIGH_CHUNK)]
    values = torch.cat([values for values, _ in parts]).reshape(cov.shape[:-1])
    vectors = torch.cat([vectors for _, vectors in parts]).reshape(cov.shape)
    return values, vectors


def curvature(points: torch.Tensor, k: int = CURVATURE_K) -> torch.Tensor:
    """Surface-variation curvature kappa (B, N) of (B, N, 3) points; see `curvature_and_normals`."""
    return curvature_and_normals(points, k)[0]


def sampling_weights(kappa: torch.Tensor, eps: float = 0.01) -> torch.Tensor:
    """Curvature-adaptive sampling probabilities, equation (3) of the paper.

    w_i = log(kappa_i + 1 + eps) / sum_j log(kappa_j + 1 + eps).

    Args:
        kappa: (..., N) curvatures. eps: keeps flat points (kappa = 0) samplable.

    Returns:
        (..., N) probabilities summing to 1 over the last axis.
    """
    logits = torch.log(kappa + 1.0 + eps)
    return logits / logits.sum(-1, keepdim=True)


def normalize_to_unit_sphere(points: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Centre each point set on its centroid and scale it into the unit sphere.

    Args:
        points: (B, N, 3).

    Returns:
        normalized (B, N, 3), centroid (B, 1, 3), scale (B, 1, 1) with
        points == normalized * scale + centroid.
    """
    centroid = points.mean(dim=1, keepdim=True)
    centred = points - centroid
    scale = centred.norm(dim=-1).amax(dim=1).clamp_min(1e-12).reshape(-1, 1, 1)
    return centred / scale, centroid, scale


def denormalize(normalized: torch.Tensor, centroid: torch.Tensor, scale: torch.Tensor) -> torch.Tensor:
    """Inverse of `normalize_to_unit_sphere`: normalized * scale + centroid."""
    return normalized * scale + centroid


def curvature_np(points: np.ndarray, k: int = CURVATURE_K) -> np.ndarray:
    """numpy form of `curvature`: (N, 3) points -> (N,) float64."""
    return curvature_and_normals_np(points, k)[0]


def curvature_and_normals_np(points: np.ndarray, k: int = CURVATURE_K) -> tuple[np.ndarray, np.ndarray]:
    """numpy form of `curvature_and_normals` for one (N, 3) point set of any size.

    Neighbours come from a k-d tree, so memory stays O(N k) (the torch form builds N x N
    distances and suits patches).

    Returns:
        kappa (N,) float64 in [0, 1/3]; normals (N, 3) float64 unit vectors, sign arbitrary.
    """
    array = np.asarray(points, dtype=np.float64)
    _, index = cKDTree(array).query(array, k=k)
    neighbours = array[index]  # (N, k, 3)
    centred = neighbours - neighbours.mean(axis=1, keepdims=True)
    cov = np.einsum("nki,nkj->nij", centred, centred) / k
    values, vectors = np.linalg.eigh(cov)
    values = np.clip(values, 0.0, None)
    kappa = values[:, 0] / np.maximum(values.sum(-1), 1e-30)
    return kappa, vectors[:, :, 0]
