"""Training losses of CAD-PU (paper, section 4.2): EMD, the curvature regularizer, LSGAN terms.

The generator's objective per training pair (equations (2) and (8)): J = L + BETA * R +
GAMMA / 2 * (D(G(P)) - 1)^2, where L, equation (4), SUMS the matched distances over the r * N
points while R, equation (7), AVERAGES over them (`generator_objective`).
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor

import numpy as np
import torch
from scipy.optimize import linear_sum_assignment

from .assignment import auction_assignment
from .geometry import CURVATURE_K, gather, pairwise_sq_dist
from .kernels import distances_3d, smallest_k_indices

BETA = 0.15
GAMMA = 0.005

_POOL = ThreadPoolExecutor(max_workers=2)


def optimal_assignment(pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """Exact minimum-cost bijection between two equal-size point sets (Euclidean cost).

    Solved with the Jonker-Volgenant algorithm (scipy's linear_sum_assignment) on the detached
    distances, one problem per batch item in a thread pool. Exact, so the EMD below has no
    approximation error; at 1024 points it costs milliseconds once predictions are near the
    target (a random start costs ~0.1 s per item).

    Args:
        pred: (B, M, 3). target: (B, M, 3).

    Returns:
        (B, M) int64: target index matched to every pred point.
    """
    if pred.shape != target.shape:
        raise ValueError(f"EMD needs equal-size sets, got {tuple(pred.shape)} and {tuple(target.shape)}")
    cost = _detached_distances(pred, target).cpu().numpy().astype(np.float64)

    def solve(matrix: np.ndarray) -> np.ndarray:
        return linear_sum_assignment(matrix)[1]

    matches = list(_POOL.map(solve, cost))
    return torch.from_numpy(np.stack(matches)).to(pred.device)


def assignment(pred: torch.Tensor, target: torch.Tensor, epsilon: float = 0.0,
               distances: torch.Tensor | None = None) -> torch.Tensor:
    """The bijection of the EMD: exact (`optimal_assignment`) when epsilon is 0, otherwise the
    auction of `cadpu.assignment`, whose mean matched distance is at most epsilon above the exact one.

    Args:
        pred: (B, M, 3). target: (B, M, 3). epsilon: >= 0, in the points' units.
        distances: `pred_target_distances(pred, target)` if the caller has them, else None.

    Returns:
        (B, M) int64: target index matched to every pred point.
    """
    if epsilon <= 0:
        return optimal_assignment(pred, target)
    if pred.shape != target.shape:
        raise ValueError(f"EMD needs equal-size sets, got {tuple(pred.shape)} and {tuple(target.shape)}")
    if distances is None:
        distances = _detached_distances(pred, target)
    cost = distances.detach().cpu().numpy()
    columns = auction_assignment(cost, epsilon, threads=torch.get_num_threads())
    return torch.from_numpy(columns).to(pred.device)


def pred_target_distances(pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """Detached (B, M, M*) distances from every predicted to every target point, computed once per
    step and shared by `emd` (its cost) and `curvature_regularizer` (its neighbours)."""
    return _detached_distances(pred, target)


def _detached_distances(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Detached (B, N, M) Euclidean distances between two batched point sets, compiled for float32
    3-D points on a CPU (`cadpu.kernels.distances_3d`)."""
    a, b = a.detach(), b.detach()
    if a.device.type == "cpu" and a.dtype == b.dtype == torch.float32 and a.shape[-1] == b.shape[-1] == 3:
        return distances_3d(a, b)
    return pairwise_sq_dist(a, b).sqrt_()


def emd(pred: torch.Tensor, target: torch.Tensor, epsilon: float = 0.0,
        distances: torch.Tensor | None = None) -> torch.Tensor:
    """Earth mover's distance, equation (4): mean over points of ||q - psi(q)|| under the optimal
    bijection psi, averaged over the batch.

    Args:
        pred: (B, M, 3) generated points. target: (B, M, 3) ground truth.
        epsilon: 0 for the exact bijection; > 0 for the auction's, which puts the value at most
            epsilon above the exact one (see `assignment`).
        distances: `pred_target_distances(pred, target)` if the caller has them.

    Returns:
        Scalar tensor, differentiable with respect to `pred`.
    """
    matched = gather(target, assignment(pred, target, epsilon, distances))
    return (pred - matched).norm(dim=-1).mean()


def generator_objective(emd_mean: torch.Tensor, regularizer: torch.Tensor, adversarial: torch.Tensor,
                        points: int, beta: float = BETA, gamma: float = GAMMA) -> torch.Tensor:
    """The generator's training objective per pair, as the paper weighs its terms.

    Equation (4) sums the matched distances over the prediction's points and equation (7) averages
    the curvatures, so against beta = 0.15 the EMD term is `points` times larger than `emd`'s
    mean: with the mean, the regularizer would weigh ~1,000 times more than in the paper.

    Args:
        emd_mean: `emd` (mean matched distance per point, batch mean). regularizer:
            `curvature_regularizer`. adversarial: `generator_adversarial` (0 before the
            discriminator starts). points: r * N, the points of each prediction.
        beta, gamma: the paper's weights.

    Returns:
        Scalar: points * emd_mean + beta * regularizer + gamma / 2 * adversarial, batch mean.
    """
    return points * emd_mean + beta * regularizer + 0.5 * gamma * adversarial


def _mean_abs_cosine(offsets: torch.Tensor, normals: torch.Tensor) -> torch.Tensor:
    """mean_k |<offset_k / ||offset_k||, n_k>| for (B, M, k, 3) offsets and normals -> (B, M)."""
    unit = offsets / offsets.norm(dim=-1, keepdim=True).clamp_min(1e-9)
    return (unit * normals).sum(-1).abs().mean(-1)


def curvature_regularizer(pred: torch.Tensor, target: torch.Tensor, target_normals: torch.Tensor,
                          k: int = CURVATURE_K, distances: torch.Tensor | None = None) -> torch.Tensor:
    """The regularizer R of equation (7): mean over predicted points of kappa (eq. 5) + kappa~ (eq. 6).

    kappa(q; Q): neighbours of q among the predictions, with the normal of q taken from the ground
    truth point closest to q. kappa~(q; Q*): neighbours of q among the ground truth, each with its
    own ground-truth normal. Both are 0 when the points lie on a plane.

    Args:
        pred: (B, M, 3). target: (B, M*, 3) ground truth. target_normals: (B, M*, 3) unit normals.
        k: neighbourhood size (12 in the paper).
        distances: `pred_target_distances(pred, target)` if the caller has them (the EMD's).

    Returns:
        Scalar tensor.
    """
    own = _detached_distances(pred, pred)
    own.diagonal(dim1=-2, dim2=-1).fill_(float("inf"))  # q is not its own neighbour
    # Neighbour sets in any order: both curvatures average over the k neighbours.
    own_index = _smallest_k(own, k)
    own_offsets = gather(pred, own_index) - pred.unsqueeze(2)
    to_target = _detached_distances(pred, target) if distances is None else distances.detach()
    gt_index = _smallest_k(to_target, k)
    closest = gt_index[..., 0]  # nearest first, ties to the lower index: to_target.argmin(-1)
    own_normals = gather(target_normals, closest).unsqueeze(2)
    kappa = _mean_abs_cosine(own_offsets, own_normals)

    gt_offsets = gather(target, gt_index) - pred.unsqueeze(2)
    kappa_gt = _mean_abs_cosine(gt_offsets, gather(target_normals, gt_index))
    return (kappa + kappa_gt).mean()


def _smallest_k(scores: torch.Tensor, k: int) -> torch.Tensor:
    """(B, N, k) indices of each row's k smallest scores, smallest first (Numba on a CPU)."""
    if scores.device.type == "cpu":
        return smallest_k_indices(scores, k)
    return scores.topk(k, dim=-1, largest=False, sorted=True).indices


def generator_adversarial(fake_scores: torch.Tensor) -> torch.Tensor:
    """Least-squares GAN generator term, equation (8): mean (D(G(P)) - 1)^2."""
    return ((fake_scores - 1.0) ** 2).mean()


def discriminator_loss(real_scores: torch.Tensor, fake_scores: torch.Tensor) -> torch.Tensor:
    """Least-squares GAN discriminator loss: mean (D(Q*) - 1)^2 + mean D(G(P))^2, halved."""
    return 0.5 * (((real_scores - 1.0) ** 2).mean() + (fake_scores ** 2).mean())


def chamfer(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Symmetric Chamfer distance: mean of the two directed mean nearest-neighbour distances.

    Args:
        a: (B, N, 3). b: (B, M, 3).

    Returns:
        (B,) distances in the input units.
    """
    d = pairwise_sq_dist(a, b)
    return 0.5 * (d.amin(-1).sqrt().mean(-1) + d.amin(-2).sqrt().mean(-1))


def to_sensor_frame(points: torch.Tensor, rotations: torch.Tensor, augment_scale: torch.Tensor,
                    centroid: torch.Tensor, scale: torch.Tensor, vertical_scale: torch.Tensor) -> torch.Tensor:
    """Points of augmented, normalised patches back in their scans' sensor frame.

    Args:
        points: (B, M, 3) as the network sees them: s * R q for a patch point q in its unit sphere
            (`cadpu.data.augment_with_transform`'s rotations R (B, 3, 3) and scales s (B,)).
        centroid (B, 3), scale (B,), vertical_scale (B,): the patches' `cadpu.scan_data.PatchFrames`.

    Returns:
        (B, M, 3) sensor frame, metres; differentiable with respect to `points`.
    """
    unit_sphere = torch.einsum("bji,bnj->bni", rotations, points) / augment_scale[:, None, None]
    tiled = unit_sphere * scale[:, None, None] + centroid[:, None, :]
    axis = torch.stack([torch.ones_like(vertical_scale), torch.ones_like(vertical_scale), vertical_scale], dim=1)
    return tiled / axis[:, None, :]


def snap_to_elevations(xyz: torch.Tensor, elevations: torch.Tensor, ring: torch.Tensor | None = None) -> torch.Tensor:
    """Move every point to one of its patch's ring elevations, keeping its azimuth and range (the
    pipeline's ring snapping, `stages.ring_snap`, with one elevation per ring and patch).

    Args:
        xyz: (B, M, 3) sensor frame, metres. elevations: (B, K) radians, NaN for none.
        ring: (B, M) int, each point's place in `elevations`; None takes the nearest in elevation
            (a patch with no elevations then gets NaN points). A negative place leaves NaN.

    Returns:
        (B, M, 3) snapped points; differentiable through range and azimuth (the ring chosen is not).
    """
    distance = xyz.norm(dim=-1).clamp_min(1e-6)
    azimuth = torch.atan2(xyz[..., 1], xyz[..., 0])
    if ring is None:
        elevation = torch.asin((xyz[..., 2] / distance).clamp(-1.0, 1.0)).detach()
        ring = (elevation[..., None] - elevations[:, None, :]).abs().nan_to_num(nan=float("inf")).argmin(-1)
    chosen = torch.gather(elevations, 1, ring.long().clamp_min(0)).masked_fill(ring < 0, float("nan"))
    flat = distance * torch.cos(chosen)
    return torch.stack([flat * torch.cos(azimuth), flat * torch.sin(azimuth), distance * torch.sin(chosen)], dim=-1)


def snapped_chamfer(pred: torch.Tensor, truth: torch.Tensor, rotations: torch.Tensor, augment_scale: torch.Tensor,
                    centroid: torch.Tensor, scale: torch.Tensor, vertical_scale: torch.Tensor,
                    truth_ring: torch.Tensor, ring_elevations: torch.Tensor) -> torch.Tensor:
    """The mean of `snapped_chamfers_per_patch` (0 when no patch has rings between the input's):
    a scalar, differentiable with respect to `pred`."""
    values = snapped_chamfers_per_patch(pred, truth, rotations, augment_scale, centroid, scale, vertical_scale,
                                        truth_ring, ring_elevations)
    return values.mean() if len(values) else pred.new_zeros(())


def snapped_chamfers_per_patch(pred: torch.Tensor, truth: torch.Tensor, rotations: torch.Tensor,
                               augment_scale: torch.Tensor, centroid: torch.Tensor, scale: torch.Tensor,
                               vertical_scale: torch.Tensor, truth_ring: torch.Tensor,
                               ring_elevations: torch.Tensor) -> torch.Tensor:
    """The Chamfer distance the pipeline's output is scored by, on training patches: predictions
    snapped onto the rings between the input's, against the truth points of those rings, in metres
    over the patch radius (so near and far patches weigh alike).

    Both sides are snapped (`snap_to_elevations`): a prediction to the ring nearest in elevation,
    a truth point to its own ring, each ring at one elevation per patch. So a prediction is scored
    by where it puts a point along a ring (azimuth, range) and by the ring it falls on, not by its
    height within the ring's band, which the pipeline's snapping overwrites; and the truth scores
    itself 0 though a ring's elevation, seen from the origin, drifts within a patch (the lasers sit
    off the sensor axis).

    The sum of the two directed mean nearest-neighbour distances per patch (predictions to truth:
    are the points where a denser scan has them; truth to predictions: is every such point
    covered), for the patches that have such rings.

    Args:
        pred: (B, M, 3), truth: (B, M*, 3), both as the network sees them (augmented, normalised).
        rotations, augment_scale: the batch's augmentation (`to_sensor_frame`).
        centroid, scale, vertical_scale, truth_ring (B, M*) int, ring_elevations (B, K): the
            patches' `cadpu.scan_data.PatchFrames`.

    Returns:
        (U,) one value per patch with truth points between the input's rings, in batch order;
        differentiable with respect to `pred`.
    """
    between = truth_ring >= 0
    usable = between.any(-1)
    pred, truth, rotations, augment_scale, centroid, scale, vertical_scale, truth_ring, ring_elevations, between = (
        t[usable] for t in (pred, truth, rotations, augment_scale, centroid, scale, vertical_scale, truth_ring,
                            ring_elevations, between))
    if not len(pred):
        return pred.new_zeros((0,))
    snapped = snap_to_elevations(to_sensor_frame(pred, rotations, augment_scale, centroid, scale, vertical_scale),
                                 ring_elevations)
    target = snap_to_elevations(to_sensor_frame(truth, rotations, augment_scale, centroid, scale, vertical_scale),
                                ring_elevations, truth_ring).detach().nan_to_num(nan=0.0)
    # exact differences: the matrix-product form loses millimetres to cancellation at 10-80 m
    distances = torch.cdist(snapped, target, compute_mode="donot_use_mm_for_euclid_dist")
    distances = distances.masked_fill(~between[:, None, :], float("inf"))
    forward = distances.amin(-1).mean(-1)
    nearest = distances.amin(-2)
    backward = torch.where(between, nearest, torch.zeros_like(nearest)).sum(-1) / between.sum(-1)
    return (forward + backward) / scale
