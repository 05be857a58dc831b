"""Cutting a point set into 256-point patches and putting the upsampled patches back together.

Three coverings:
- `equal_clusters`: the paper's test protocol, disjoint spatial clusters of equal size
  (recursive median splits along the widest axis: 2048 points -> 8 x 256);
- `overlapping_patches`: any number of points, patches of K nearest neighbours around seeds
  spread by farthest point sampling, each point owned by the patch whose seed is nearest among
  those containing it; used for whole objects;
- `partitioned_patches`: any number of points, a balanced k-d partition into cells of at most
  K / overlap points, each cell's patch being the cell plus its nearest outside points as context;
  every point owned by its cell's patch. Used for LiDAR frames, whose density varies with range:
  it needs overlap * M / K patches where farthest-point seeding needs several rounds.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from numba import njit
from scipy.spatial import cKDTree


@dataclass(frozen=True)
class PatchCover:
    """Patches over M points.

    The patches may have been cut from the points with their axes scaled (`axis_scale`, e.g. z
    squashed on LiDAR scans, see `stages.tile`); `centroid`, `scale` and `normalized` are then in
    those scaled coordinates and `keep_owned` undoes the scaling.

    Attributes:
        point_index: (P, K) int64 indices of each patch's points.
        owner: (M,) int64 patch owning each point (the point is in that patch).
        centroid: (P, 3) float64 patch centres. scale: (P,) float64 patch radii.
        normalized: (P, K, 3) float32 patches in the unit sphere: (p * axis_scale - centroid) / scale.
        axis_scale: (3,) float64 factor each axis of the points was multiplied by before tiling.
    """

    point_index: np.ndarray
    owner: np.ndarray
    centroid: np.ndarray
    scale: np.ndarray
    normalized: np.ndarray
    axis_scale: np.ndarray = field(default_factory=lambda: np.ones(3))

    @property
    def num_patches(self) -> int:
        return int(self.point_index.shape[0])


def _normalize(points: np.ndarray, point_index: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    patches = points[point_index]
    centroid = patches.mean(axis=1)
    centred = patches - centroid[:, None]
    scale = np.maximum(np.linalg.norm(centred, axis=2).max(axis=1), 1e-9)
    return centroid, scale, (centred / scale[:, None, None]).astype(np.float32)


def equal_clusters(points: np.ndarray, parts: int) -> np.ndarray:
    """Split points into `parts` (a power of two) spatially compact clusters of equal size.

    Args:
        points: (M, 3) with M divisible by `parts`.

    Returns:
        (parts, M / parts) int64 point indices per cluster.
    """
    if parts & (parts - 1) or len(points) % parts:
        raise ValueError(f"need a power-of-two number of parts dividing {len(points)}, got {parts}")
    groups = [np.arange(len(points))]
    while len(groups) < parts:
        split = []
        for group in groups:
            subset = points[group]
            axis = int(np.argmax(subset.max(0) - subset.min(0)))
            order = group[np.argsort(subset[:, axis], kind="stable")]
            half = len(order) // 2
            split.extend([order[:half], order[half:]])
        groups = split
    return np.stack(groups)


#: A seed whose nearest neighbour lies farther than this share of its patch's radius is a stray (a
#: point far from every other): its patch spans the gap to the others, normalised so widely that
#: their copies come out far off, so it covers only its seed, and the others get patches of their
#: own in a later round (`overlapping_patches`).
STRAY_SEED_SHARE = 0.5


def overlapping_patches(points: np.ndarray, patch_size: int = 256, overlap: float = 1.0,
                        seed: int = 0, stray_seeds: bool = False) -> PatchCover:
    """Cover every point with patches of `patch_size` nearest neighbours.

    Seeds are placed in rounds: each round spreads ceil(overlap * U / patch_size) seeds by farthest
    point sampling over the U points no patch holds yet. One round suffices for evenly sampled
    surfaces; on LiDAR scans, whose density falls with range, later rounds put more seeds where the
    points are dense, so every point is covered without a patch per missed point.

    Args:
        points: (M, 3), M >= patch_size.
        overlap: seeds per round relative to the uncovered points' patch count (>= 1).
        seed: start of the farthest point sampling.
        stray_seeds: the patch of a stray seed (`STRAY_SEED_SHARE`) holds its neighbours but covers
            and owns only the seed (`cadpu.inference.Upsampler.upsample_object`). Off for the
            pipeline's `tile.method: fps`, whose output it would change (its rule was not
            measured on scans, where a far lone return is a stray).

    Returns:
        The `PatchCover`.
    """
    from .kernels import farthest_point_picks  # here: cadpu.kernels imports torch (seconds), which
    # the command line's verbs that upsample nothing (`kitti-pu info`, `config`) never need

    m = len(points)
    if m < patch_size:
        raise ValueError(f"need at least {patch_size} points, got {m}")
    tree = cKDTree(points)
    covered = np.zeros(m, dtype=bool)
    seeds, blocks, strays = [], [], []
    remaining = np.arange(m)
    round_number = 0
    while remaining.size:
        count = min(remaining.size, max(1, math.ceil(overlap * remaining.size / patch_size)))
        first = np.random.default_rng(seed + round_number).integers(remaining.size)
        picked = remaining[farthest_point_picks(points[remaining][None], count, first)[0]]
        distance, index = tree.query(points[picked], k=patch_size, workers=1)  # one core per pipeline worker
        index = np.asarray(index, dtype=np.int64).reshape(len(picked), patch_size)
        if covered[index].all():
            index = _patches_of_uncovered(points, picked, remaining, index)
        stray = np.zeros(len(picked), dtype=bool)
        if stray_seeds:  # from the seeds' own neighbours, whatever `_patches_of_uncovered` made
            distance = np.asarray(distance, dtype=np.float64).reshape(len(picked), patch_size)
            stray = distance[:, min(1, patch_size - 1)] > STRAY_SEED_SHARE * distance[:, -1]
        covered[index[~stray].ravel()] = True
        covered[picked[stray]] = True
        seeds.append(picked)
        blocks.append(index)
        strays.append(stray)
        remaining = np.flatnonzero(~covered)
        round_number += 1
    all_seeds = np.concatenate(seeds)
    point_index = np.concatenate(blocks)
    owner = _owners(points, all_seeds, point_index, np.concatenate(strays))
    centroid, scale, normalized = _normalize(points, point_index)
    return PatchCover(point_index, owner, centroid, scale, normalized)


def _patches_of_uncovered(points: np.ndarray, picked: np.ndarray, remaining: np.ndarray,
                          index: np.ndarray) -> np.ndarray:
    """Patches for a round whose nearest-neighbour patches covered no new point: more than a patch
    of points at one position (a cloud's repeated "no return" points), where the query's tie order
    returns the same covered copies every round. Each seed's patch takes its nearest uncovered
    points first (up to the patch size), then fills up from its own query, so every round covers
    new points and the cover ends.

    Args: points (M, 3); picked (S,) seeds; remaining (U,) the uncovered points; index (S, K) the
    seeds' nearest-neighbour patches. Returns (S, K) int64 patches."""
    patches = index.copy()
    size = index.shape[1]
    for row, seed in enumerate(picked):
        distance = ((points[remaining] - points[seed]) ** 2).sum(axis=1)
        nearest = remaining[np.argsort(distance, kind="stable")[:size]]
        rest = index[row][~np.isin(index[row], nearest)][:size - len(nearest)]
        patches[row] = np.concatenate([nearest, np.asarray(rest, dtype=np.int64)])
    return patches


def balanced_cells(points: np.ndarray, max_size: int) -> np.ndarray:
    """Split points into ceil(M / max_size) spatially compact cells of near-equal size.

    Recursive splits along each group's widest axis, at the count that gives both halves the
    same points per cell (so sizes differ by at most one point).

    Args:
        points: (M, 3). max_size: the largest cell, >= 1.

    Returns:
        (M,) int64 cell of each point, cells numbered 0 .. ceil(M / max_size) - 1, depth first
        with the lower half of each split first.
    """
    points = np.ascontiguousarray(points, dtype=np.float64)
    return _balanced_cells(points, max(1, math.ceil(len(points) / max_size)))


@njit(cache=True, nogil=True)
def _balanced_cells(points: np.ndarray, total_cells: int) -> np.ndarray:  # pragma: no cover - compiled
    m = len(points)
    order = np.arange(m)  # each group is a contiguous run of `order`
    cell = np.empty(m, np.int64)
    stack = np.empty((128, 3), np.int64)  # (start, stop, cells); depth ~ log2(cells), two per level
    stack[0, 0], stack[0, 1], stack[0, 2] = 0, m, total_cells
    top = 1
    next_cell = 0
    while top > 0:
        top -= 1
        start, stop, cells = stack[top, 0], stack[top, 1], stack[top, 2]
        if cells == 1:
            for s in range(start, stop):
                cell[order[s]] = next_cell
            next_cell += 1
            continue
        low = points[order[start]].copy()
        high = low.copy()
        for s in range(start + 1, stop):
            for a in range(3):
                value = points[order[s], a]
                low[a] = min(low[a], value)
                high[a] = max(high[a], value)
        axis = int(np.argmax(high - low))
        left_cells = cells // 2
        # round((stop - start) * left_cells / cells), halves to even as Python's round
        quotient, remainder = divmod((stop - start) * left_cells, cells)
        split = quotient + (1 if 2 * remainder > cells or (2 * remainder == cells and quotient % 2) else 0)
        _smallest_first(points, order, start, stop, start + split, axis)
        stack[top, 0], stack[top, 1], stack[top, 2] = start + split, stop, cells - left_cells
        stack[top + 1, 0], stack[top + 1, 1], stack[top + 1, 2] = start, start + split, left_cells
        top += 2
    return cell


@njit(cache=True, nogil=True)
def _smallest_first(points: np.ndarray, order: np.ndarray, start: int, stop: int, boundary: int,
                    axis: int) -> None:  # pragma: no cover - compiled
    """Reorder order[start:stop] so that no point before `boundary` lies above one after it along
    `axis` (a quickselect with three-way partitions, so runs of equal values cost nothing extra)."""
    low, high = start, stop
    while high - low > 1:
        a = points[order[low], axis]
        b = points[order[(low + high) // 2], axis]
        c = points[order[high - 1], axis]
        pivot = max(min(a, b), min(max(a, b), c))  # median of three
        less, i, greater = low, low, high
        while i < greater:
            value = points[order[i], axis]
            if value < pivot:
                order[less], order[i] = order[i], order[less]
                less += 1
                i += 1
            elif value > pivot:
                greater -= 1
                order[greater], order[i] = order[i], order[greater]
            else:
                i += 1
        if boundary < less:
            high = less
        elif boundary > greater:
            low = greater
        else:
            return


def partitioned_patches(points: np.ndarray, patch_size: int = 256, overlap: float = 4 / 3) -> PatchCover:
    """Cover every point with patches built on a balanced k-d partition.

    The points are split into cells of at most patch_size / overlap points (`balanced_cells`); a
    cell's patch is its own points followed by the outside points nearest to the cell's centroid,
    up to patch_size. The cell owns its points, so each point is upsampled in exactly one patch,
    with context on every side of the cell.

    Args:
        points: (M, 3), M >= patch_size.
        overlap: patch points per owned point, in [1, patch_size]; 1 gives disjoint patches.

    Returns:
        The `PatchCover` (owner = the point's cell; the owned points fill the first slots).
    """
    m = len(points)
    if m < patch_size:
        raise ValueError(f"need at least {patch_size} points, got {m}")
    if not 1.0 <= overlap <= patch_size:
        raise ValueError(f"overlap must be in [1, {patch_size}], got {overlap}")
    cell = balanced_cells(points, max(1, int(patch_size / overlap)))
    cells = int(cell.max()) + 1
    order = np.argsort(cell, kind="stable")
    size = np.bincount(cell, minlength=cells)
    start = np.concatenate([[0], np.cumsum(size)[:-1]])
    point_index = np.empty((cells, patch_size), dtype=np.int64)
    # Own points first: slot = rank of the point within its cell.
    point_index[cell[order], np.arange(m) - start[cell[order]]] = order
    # Context: the nearest outside points of the cell's centroid. Among its patch_size nearest
    # points at most size[c] are the cell's own, so there are always enough outside ones.
    centroid = np.stack([np.bincount(cell, points[:, i], cells) for i in range(3)], axis=1) / size[:, None]
    # The median-split (balanced) tree takes twice as long to build for the same exact answers;
    # one query thread, as each pipeline worker runs on one core.
    _, nearest = cKDTree(points, balanced_tree=False).query(centroid, k=patch_size, workers=1)
    nearest = np.asarray(nearest, dtype=np.int64).reshape(cells, patch_size)
    outside = cell[nearest] != np.arange(cells)[:, None]
    rank = np.cumsum(outside, axis=1) - 1
    take = outside & (rank < (patch_size - size)[:, None])
    rows = np.nonzero(take)[0]
    point_index[rows, size[rows] + rank[take]] = nearest[take]
    centroid, scale, normalized = _normalize(points, point_index)
    return PatchCover(point_index, cell, centroid, scale, normalized)


def _owners(points: np.ndarray, seeds: np.ndarray, point_index: np.ndarray,
            only_seed: np.ndarray | None = None) -> np.ndarray:
    """For each point, the patch containing it whose seed is nearest (-1 when in none); a patch
    marked in `only_seed` (P,) bool owns its seed alone (a stray's: its other members lie nearer
    to it than to any other seed, and so came out owned by it)."""
    patch_of = np.repeat(np.arange(len(seeds)), point_index.shape[1])
    members = point_index.ravel()
    distance = ((points[members] - points[seeds[patch_of]]) ** 2).sum(1)
    if only_seed is not None and only_seed.any():
        distance[only_seed[patch_of] & (members != seeds[patch_of])] = np.inf
    order = np.lexsort((distance, members))
    first = np.ones(len(order), dtype=bool)
    first[1:] = members[order][1:] != members[order][:-1]
    owner = np.full(len(points), -1, dtype=np.int64)
    owner[members[order][first]] = patch_of[order][first]
    return owner


def keep_owned(cover: PatchCover, upsampled: np.ndarray, parents: np.ndarray,
               patches: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Map upsampled patches back and keep, for every point, what its owning patch generated.

    Args:
        cover: the covering the patches came from.
        upsampled: (S, K*r, 3) generated points in the patches' unit spheres.
        parents: (S, K*r) int64 slot (0..K-1) of each generated point's parent in its patch.
        patches: (S,) int64 which of the cover's patches the rows are; None: all P, in order.

    Returns:
        points (Q, 3) float64 in the original frame (`axis_scale` undone), source (Q,) int64 index
        of the original point each came from. Linear in P*K*r.

    Raises:
        ValueError: `upsampled` and `parents` not of one shape (S, K*r) for the S patches named,
            `upsampled` not real numbers or not finite, `parents` or `patches` not whole numbers,
            a parent that is not a slot of its patch, or a patch that is not one of the cover's.
    """
    count = len(cover.point_index)
    patch = (np.arange(count) if patches is None else np.asarray(patches)).reshape(-1, 1)
    upsampled, parents = np.asarray(upsampled), np.asarray(parents)
    for name, values in (("parents", parents), ("patches", patch)):
        if values.size and values.dtype.kind not in "iu":  # float indices failed inside numpy's take
            raise ValueError(f"keep_owned: {name} must be whole numbers (an integer array), got {values.dtype}")
    if upsampled.dtype.kind != "f":
        raise ValueError(f"keep_owned: upsampled must be floating-point coordinates, got {upsampled.dtype}")
    if upsampled.dtype not in (np.float32, np.float64):  # float16, big-endian: the compiled step takes neither
        upsampled = upsampled.astype(np.float64)
    if patch.size and not (0 <= int(patch.min()) and int(patch.max()) < count):
        raise ValueError(f"keep_owned: patches must be indices 0 to {count - 1} of the cover's patches, got "
                         f"{int(patch.min())} to {int(patch.max())}")
    if upsampled.ndim != 3 or parents.shape != upsampled.shape[:2] or len(upsampled) != len(patch):
        which = "the patches given" if patches is not None else "all of the cover; pass patches= for a subset"
        raise ValueError(f"keep_owned: upsampled {upsampled.shape} and parents {parents.shape} must be (S, K*r, 3) "
                         f"and (S, K*r) for the S = {len(patch)} patches they are of ({which})")
    slots = cover.point_index.shape[1]
    if parents.size and not (0 <= int(parents.min()) and int(parents.max()) < slots):  # -1 wrapped to the last slot
        raise ValueError(f"keep_owned: parents must be slots 0 to {slots - 1} of their patches, got "
                         f"{int(parents.min())} to {int(parents.max())}")
    # a NaN or infinite coordinate was mapped back as it was
    if upsampled.size and not (np.isfinite(upsampled.min()) and np.isfinite(upsampled.max())):
        raise ValueError(f"keep_owned: upsampled holds {int((~np.isfinite(upsampled)).sum())} non-finite values")
    source = np.take_along_axis(cover.point_index[patch[:, 0]], parents, axis=1)  # (S, K*r)
    kept = np.flatnonzero(cover.owner[source] == patch)  # the kept points, in row-major order
    kept_patch = patch[kept // source.shape[1], 0]
    mapped = _map_back(np.ascontiguousarray(upsampled.reshape(-1, 3)), kept, kept_patch,
                       np.asarray(cover.scale, np.float64), np.asarray(cover.centroid, np.float64),
                       np.asarray(cover.axis_scale, np.float64))
    return mapped, source.reshape(-1)[kept]


@njit(cache=True, nogil=True)
def _map_back(points: np.ndarray, kept: np.ndarray, patch: np.ndarray, scale: np.ndarray, centroid: np.ndarray,
              axis_scale: np.ndarray) -> np.ndarray:  # pragma: no cover - compiled
    """(Q, 3) float64 (points[kept] * scale[patch] + centroid[patch]) / axis_scale, row by row:
    the numpy expression's arithmetic in one pass (points: (M, 3) normalised, kept/patch: (Q,))."""
    out = np.empty((len(kept), 3), np.float64)
    for q in range(len(kept)):
        row, p = kept[q], patch[q]
        for axis in range(3):
            out[q, axis] = (np.float64(points[row, axis]) * scale[p] + centroid[p, axis]) / axis_scale[axis]
    return out


def spare_points(cover: PatchCover, upsampled: np.ndarray, parents: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """What `keep_owned` leaves out: the points each patch generated from points another patch
    owns, mapped back the same way.

    Args:
        cover, upsampled, parents: as `keep_owned` takes them, for all of the cover's patches.

    Returns:
        points (S, 3) float64 in the original frame, source (S,) int64 index of the original point
        each came from.
    """
    patch = np.arange(len(cover.point_index)).reshape(-1, 1)
    source = np.take_along_axis(cover.point_index, np.asarray(parents), axis=1)
    spare = np.flatnonzero(cover.owner[source] != patch)
    mapped = _map_back(np.ascontiguousarray(np.asarray(upsampled).reshape(-1, 3)), spare,
                       patch[spare // source.shape[1], 0], np.asarray(cover.scale, np.float64),
                       np.asarray(cover.centroid, np.float64), np.asarray(cover.axis_scale, np.float64))
    return mapped, source.reshape(-1)[spare]


def to_count(points: np.ndarray, source: np.ndarray, count: int, spare: np.ndarray, spare_source: np.ndarray,
             origin: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """`points` made exactly `count` long, as evenly spread as one pass can: by dropping the most
    crowded (one of each close pair), or by adding the spare points that fill the widest gaps.

    A curvature-adaptive network draws each patch's copies by curvature, so the points its owned
    parents keep come to about, not exactly, ratio times the input; this evens a whole set's count
    out by its margin (about 1%), leaving the draws everywhere else as they were. A gap is a spare
    point's distance to the nearest point kept, over its source's distance to the nearest other
    original point: on the input's own scale, so that a lone point's wide surroundings do not draw
    every addition. Spare points farther from their source than 99% of the kept points are from
    theirs are never added (a patch stretched over a stray point makes copies far from every source).

    Args:
        points: (Q, 3) float64, source: (Q,) int64 their original points' indices into `origin`.
        count: how many to return. spare, spare_source: (S, 3) candidates to add, and their sources.
        origin: (M, 3) the original points, M >= 2.

    Returns:
        points (count, 3) and source (count,), the kept ones in their order, added ones after them.

    Raises:
        ValueError: more points needed than `points` and the spare points that qualify hold.
    """
    if len(points) == count:
        return points, source
    if len(points) > count:
        distance, nearest = cKDTree(points).query(points, k=2)
        order = np.argsort(distance[:, 1], kind="stable")
        dropped = np.zeros(len(points), dtype=bool)
        excess = len(points) - count
        for index in order:
            if not dropped[nearest[index, 1]]:  # of a close pair, one goes
                dropped[index] = True
                excess -= 1
                if not excess:
                    break
        if excess:  # more to drop than there are close pairs: the most crowded of the rest
            dropped[order[~dropped[order]][:excess]] = True
        return points[~dropped], source[~dropped]
    reach = np.linalg.norm(points - origin[source], axis=1)
    usable = np.flatnonzero(np.linalg.norm(spare - origin[spare_source], axis=1) <= np.quantile(reach, 0.99))
    need = count - len(points)
    if need > len(usable):
        raise ValueError(f"to_count: {count} points asked, {len(points)} kept and {len(usable)} spare near their "
                         "sources")
    spacing = cKDTree(origin).query(origin, k=2)[0][:, 1]
    gap = cKDTree(points).query(spare[usable])[0] / np.maximum(spacing[spare_source[usable]], np.finfo(float).tiny)
    added = usable[np.argsort(-gap, kind="stable")[:need]]
    return np.concatenate([points, spare[added]]), np.concatenate([source, spare_source[added]])
