"""The CAD-PU generator and the PointNet discriminator (paper, section 4.1 and Appendix A).

Generator = feature extractor (24-d lift, 4 dense EdgeConv blocks with skip connections)
-> curvature-adaptive feature expansion (uniform + equation (3) sampling, 2D grid codes, MLP 2x128)
-> regression MLP 128 -> 64 -> 3.

Widths the paper leaves to MPU/PU-GAN follow PU-GAN: growth rate 24, 48-channel bottleneck
before every block after the first, K = 16 neighbours found in feature space.

One deliberate parameterisation choice: the regression head predicts each output point as an
offset from its parent input point (the expansion knows the parent of every output), rather than
absolute coordinates. The function class is the same (the parent coordinate is a fixed input);
it makes the untrained network start from "copy the input" and trains far faster on a CPU.
"""

from __future__ import annotations

import math

import torch
from torch import nn

from .geometry import CURVATURE_K, tracing_graph, curvature_and_frames, gather, knn, sampling_weights
from .kernels import edge_terms, expansion_hidden, placed_points

#: Epsilon of equation (3).
SAMPLING_EPS = 0.01
#: Spacing of the 2D grid codes given to duplicate features.
GRID_SPACING = 0.2
#: Initial tangent-plane offset per unit of grid code, in neighbourhood radii (0.2 * 2 = 0.4:
#: the first ring of copies starts 0.4 neighbourhood radii from its parent).
CODE_SPREAD = 2.0
#: Axes of the learned offsets: the parent's local PCA frame, or the patch's own x, y, z (where a
#: direction means the same in every patch, as "up" does in LiDAR patches, whose z is vertical).
OFFSET_FRAMES = ("local", "global")


def grid_codes(count: int) -> torch.Tensor:
    """The first `count` corners of the integer grid, spreading out from the origin.

    Ring by ring (Chebyshev radius 1, 2, ...) and, within a ring, counter-clockwise from the
    positive x axis: [1,0], [1,1], [0,1], [-1,1], [-1,0], ... as in the paper; scaled by
    GRID_SPACING.

    Returns:
        (count, 2) float32.
    """
    corners: list[tuple[int, int]] = []
    radius = 1
    while len(corners) < count:
        ring = [(x, y) for x in range(-radius, radius + 1) for y in range(-radius, radius + 1)
                if max(abs(x), abs(y)) == radius]
        ring.sort(key=lambda c: math.atan2(c[1], c[0]) % (2 * math.pi))
        corners.extend(ring)
        radius += 1
    return torch.tensor(corners[:count], dtype=torch.float32) * GRID_SPACING


def _mlp(*widths: int, last_act: bool = True) -> nn.Sequential:
    """Shared per-point MLP over the last axis (a 1x1 convolution in channels-last layout)."""
    layers: list[nn.Module] = []
    for i, (cin, cout) in enumerate(zip(widths[:-1], widths[1:])):
        layers.append(nn.Linear(cin, cout))
        if last_act or i < len(widths) - 2:
            layers.append(nn.ReLU(inplace=True))
    return nn.Sequential(*layers)


def compiled_inference(activations: torch.Tensor) -> bool:
    """Whether the network's compiled inference kernels (`cadpu.kernels`) replace torch's calls on
    these activations: float32 on a CPU, gradients off (`torch.no_grad` or `torch.inference_mode`,
    as inference runs; the kernels are invisible to autograd, so with gradients on, the weights
    would get none) and no graph being traced. Training, exports, `torch.compile` and other data
    types take the torch path."""
    return (activations.device.type == "cpu" and activations.dtype == torch.float32
            and not torch.is_grad_enabled() and not tracing_graph())


class DenseEdgeConv(nn.Module):
    """EdgeConv with 3 densely connected 1x1 layers over K feature-space neighbours, max-pooled.

    Edge feature of (i, j): [f_i, f_j - f_i]. Its first layer is linear in f_i and f_j, so it is
    evaluated per point and gathered per edge (W [f_i, f_j - f_i] = (W_a - W_b) f_i + W_b f_j),
    which is exact and K times cheaper; the same holds for the edge-feature part of the dense
    inputs of layers 2 and 3.

    Input (B, N, C) features; output (B, N, 3 * growth).

    `layout` orders the per-edge tensors: "neighbour-major" (K, B*N, g), whose max-pool is an
    elementwise max over K contiguous slabs, or "point-major" (B*N, K, g), each point's K edges
    adjacent (bench/inference.py compares them).
    """

    LAYOUTS = ("neighbour-major", "point-major")

    def __init__(self, channels: int, growth: int = 24, k: int = 16) -> None:
        super().__init__()
        self.k = k
        self.layout = self.LAYOUTS[0]
        self.growth = growth
        # Per-point linear maps of the edge feature into each of the three layers.
        self.centre = nn.Linear(channels, 3 * growth)
        self.neighbour = nn.Linear(channels, 3 * growth, bias=False)
        self.layer2 = nn.Linear(growth, growth, bias=False)
        self.layer3 = nn.Linear(2 * growth, growth, bias=False)

    def forward(self, features: torch.Tensor) -> torch.Tensor:
        batch, n, _ = features.shape
        g, k = self.growth, self.k
        index = knn(features, features, k, nearest_first=False)  # (B, N, K); the max-pool ignores order
        # Edges laid out neighbour-major (K, B*N, g): the max-pool is then an elementwise max
        # over K contiguous slabs, much faster on a CPU than a strided reduction.
        point_major = self.layout == "point-major"
        tracked = torch.is_grad_enabled()  # in-place products without gradients, out of place with them
        offsets = (torch.arange(batch, device=index.device) * n).view(-1, 1, 1)
        flat_index = (index + offsets if point_major else (index + offsets).permute(2, 0, 1)).reshape(-1)
        neighbour = self.neighbour(features)
        own = self.centre(features) - neighbour
        if self._compiled_edges(features):
            # Gathers and adds of all three layers in one compiled pass; the same values.
            edges = edge_terms(neighbour.reshape(batch * n, 3 * g), own.reshape(batch * n, 3 * g), flat_index, 3)
            edge = [edges[i] for i in range(3)]
        else:
            # One contiguous (B*N, g) slab per layer, so every per-edge tensor below is contiguous.
            neighbour = neighbour.reshape(batch * n, 3, g).transpose(0, 1).contiguous()
            own = own.reshape(batch * n, 3, g)
            shape, own_shape = ((batch * n, k, g), (batch * n, 1, g)) if point_major else ((k, batch * n, g), (batch * n, g))
            edge = [neighbour[i].index_select(0, flat_index).view(shape) for i in range(3)]
            edge = [(edge[i] + own[:, i].view(own_shape) if tracked else edge[i].add_(own[:, i].view(own_shape)))
                    .view(-1, g) for i in range(3)]
        # Dense connections as fused in-place matrix products instead of concatenations: the
        # block is memory-bound on a CPU. relu commutes with the max-pool, so h3 is pooled first.
        # With gradients the same products run out of place: autograd's backward of an in-place
        # change of a view copies the whole gradient of its base (CopySlices), once per change.
        w3 = self.layer3.weight.t()
        if tracked:
            h1 = torch.relu(edge[0])
            h2 = torch.relu(torch.addmm(edge[1], h1, self.layer2.weight.t()))
            pre3 = torch.addmm(torch.addmm(edge[2], h1, w3[:g]), h2, w3[g:])
        else:
            h1 = edge[0].relu_()
            h2 = edge[1].addmm_(h1, self.layer2.weight.t()).relu_()
            pre3 = edge[2].addmm_(h1, w3[:g]).addmm_(h2, w3[g:])
        pooled = [h.view(batch, n, k, g).amax(dim=2) if point_major else h.view(k, batch, n, g).amax(dim=0)
                  for h in (h1, h2, pre3)]
        pooled[2] = torch.relu(pooled[2])
        return torch.cat(pooled, dim=-1)

    def _compiled_edges(self, features: torch.Tensor) -> bool:
        """Whether `forward` builds the edges with `cadpu.kernels.edge_terms`:
        `compiled_inference` and the neighbour-major layout."""
        return self.layout == self.LAYOUTS[0] and compiled_inference(features)


class FeatureExtractor(nn.Module):
    """24-d lift, then 4 dense EdgeConv blocks; each block's output is concatenated with its
    input (skip connection), blocks after the first see a 48-channel bottleneck.

    Input (B, N, 3) points; output (B, N, out_channels).
    """

    def __init__(self, lift: int = 24, growth: int = 24, bottleneck: int = 48, k: int = 16,
                 blocks: int = 4) -> None:
        super().__init__()
        self.lift = _mlp(3, lift)
        self.bottlenecks = nn.ModuleList()
        self.blocks = nn.ModuleList()
        channels = lift
        for b in range(blocks):
            cin = channels if b == 0 else bottleneck
            self.bottlenecks.append(nn.Identity() if b == 0 else _mlp(channels, bottleneck))
            self.blocks.append(DenseEdgeConv(cin, growth, k))
            channels = channels + 3 * growth
        self.out_channels = channels

    def forward(self, points: torch.Tensor) -> torch.Tensor:
        features = self.lift(points)
        for squeeze, block in zip(self.bottlenecks, self.blocks):
            features = torch.cat([features, block(squeeze(features))], dim=-1)
        return features


def expansion_indices(kappa: torch.Tensor, ratio: int, alpha: float,
                      generator: torch.Generator | None = None) -> torch.Tensor:
    """Which input point each of the r*N expanded features is copied from.

    alpha*r*N indices are uniform: every point round(alpha*r) times when alpha*r is an integer,
    otherwise floor(alpha*r) times plus a uniform draw without replacement for the remainder.
    The other (1-alpha)*r*N are drawn with replacement with the probabilities of equation (3).

    Args:
        kappa: (B, N) curvature of the input points. ratio: r >= 1. alpha: in [0, 1].
        generator: random source of the draws (None: torch's global one).

    Returns:
        (B, r*N) int64 parent indices, sorted so that copies of one parent are adjacent.
    """
    batch, n = kappa.shape
    total = ratio * n
    uniform_count = int(round(alpha * total))
    per_point, remainder = divmod(uniform_count, n)
    parts = [torch.arange(n, device=kappa.device).repeat(per_point).expand(batch, -1)]
    if remainder:
        scores = torch.rand(batch, n, generator=generator, device=kappa.device)
        parts.append(scores.topk(remainder, dim=1).indices)
    adaptive = total - uniform_count
    if adaptive:
        weights = sampling_weights(kappa, SAMPLING_EPS)
        parts.append(torch.multinomial(weights, adaptive, replacement=True, generator=generator))
    parents = torch.cat(parts, dim=1)
    return parents.sort(dim=1, stable=True).values


def copy_rank(parents: torch.Tensor) -> torch.Tensor:
    """For sorted parent indices (B, M), the rank of each copy within its parent's group (0, 1, ...)."""
    batch, m = parents.shape
    position = torch.arange(m, device=parents.device).expand(batch, -1)
    starts = torch.ones_like(parents, dtype=torch.bool)
    starts[:, 1:] = parents[:, 1:] != parents[:, :-1]
    group_start = torch.where(starts, position, torch.zeros_like(position)).cummax(dim=1).values
    return position - group_start


class Generator(nn.Module):
    """CAD-PU generator: (B, N, 3) normalised points -> (B, r*N, 3) points and parent indices.

    Args:
        ratio: upsampling ratio r >= 2 the network produces per forward pass.
        alpha: share of uniformly expanded features (1.0 = PU-GAN-style uniform expansion).
        frame_k: neighbours of the local frame and radius the offsets are expressed in.
        offset_frame: axes of the learned offsets, one of OFFSET_FRAMES ("local": the parent's
            frame; "global": the patch's x, y, z). The grid-code spread is always in the local frame.
        code_spread: initial tangent-plane offset per unit of grid code, in neighbourhood radii.
    """

    def __init__(self, ratio: int = 4, alpha: float = 0.5, lift: int = 24, growth: int = 24,
                 bottleneck: int = 48, k: int = 16, expansion_width: int = 128,
                 frame_k: int = CURVATURE_K, offset_frame: str = "local",
                 code_spread: float = CODE_SPREAD) -> None:
        super().__init__()
        if ratio < 2:
            raise ValueError(f"ratio must be >= 2, got {ratio}")
        if not 0.0 <= alpha <= 1.0:
            raise ValueError(f"alpha must be in [0, 1], got {alpha}")
        if offset_frame not in OFFSET_FRAMES:
            raise ValueError(f"offset_frame must be one of {OFFSET_FRAMES}, got {offset_frame!r}")
        self.ratio = ratio
        self.alpha = alpha
        self.config = dict(ratio=ratio, alpha=alpha, lift=lift, growth=growth, bottleneck=bottleneck,
                           k=k, expansion_width=expansion_width, frame_k=frame_k,
                           offset_frame=offset_frame, code_spread=code_spread)
        self.extractor = FeatureExtractor(lift, growth, bottleneck, k)
        channels = self.extractor.out_channels
        # First expansion layer on [f_parent; code], split into its feature part (evaluated once
        # per input point, then copied) and its code part: exact, and r times cheaper.
        self.expand_feature = nn.Linear(channels, expansion_width)
        self.expand_code = nn.Linear(2, expansion_width, bias=False)
        self.expand = _mlp(expansion_width, expansion_width)
        self.regress = _mlp(expansion_width, 64, 3, last_act=False)
        nn.init.zeros_(self.regress[-1].weight)
        nn.init.zeros_(self.regress[-1].bias)
        self.code_skip = nn.Linear(2, 3, bias=False)
        with torch.no_grad():  # grid code (u, v) -> (u, v, 0) * code_spread in the local frame
            self.code_skip.weight.copy_(torch.tensor([[1.0, 0.0], [0.0, 1.0], [0.0, 0.0]]) * code_spread)
        self.register_buffer("codes", grid_codes(64), persistent=False)

    @property
    def frame_k(self) -> int:
        """Neighbours of the local frame (from `config`, which the weight file stores)."""
        return self.config["frame_k"]

    @property
    def min_points(self) -> int:
        """The fewest points a patch may have: every point needs its EdgeConv neighbours, its
        curvature's and its local frame's among the patch (each neighbourhood counts the point)."""
        return max(self.config["k"], CURVATURE_K, self.frame_k)

    @property
    def offset_frame(self) -> str:
        """Axes of the learned offsets, one of OFFSET_FRAMES (from `config`)."""
        return self.config["offset_frame"]

    def forward(self, points: torch.Tensor, generator: torch.Generator | None = None,
                ratio: int | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """Upsample a batch of patches.

        Args:
            points: (B, N, 3) patches normalised to the unit sphere.
            generator: random source of the curvature-adaptive draws (fixed for reproducibility).
            ratio: override of self.ratio for this call (see `cadpu.inference` for ratios the
                weights were not trained at).

        Returns:
            (B, r*N, 3) generated points and (B, r*N) int64 index of each one's parent input point.
        """
        r = ratio or self.ratio
        parents, rank, frames, radius = self.expansion(points, r, generator)
        return self.decode(points, parents, rank, frames, radius), parents

    def expansion(self, points: torch.Tensor, ratio: int, generator: torch.Generator | None = None
                  ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        """The non-learned part of a forward pass: curvature, local frames and the expansion draw.

        Args:
            points: (B, N, 3) normalised patches. ratio: r. generator: random source of the draws.

        Returns:
            parents (B, r*N) int64 (sorted), rank (B, r*N) int64 (each copy's rank within its
            parent's group, capped at the last grid code), frames (B, N, 3, 3) and radius (B, N),
            in the dtype of `points`.
        """
        adaptive = self.alpha < 1.0  # only the curvature-adaptive draws of equation (3) read the curvature
        with torch.no_grad():
            kappa, frames, radius = curvature_and_frames(points.detach(), CURVATURE_K, self.frame_k, curvature=adaptive)
        if kappa is None:  # uniform expansion draws nothing by curvature: `expansion_indices` reads only the shape
            kappa = radius.new_zeros(radius.shape)
        # drawn where `generator` lives: a CPU generator gives the same draws for any batching and
        # device (a CUDA one's stream advances per kernel launch, so its draws follow the batching)
        draws = kappa if generator is None else kappa.to(generator.device)
        parents = expansion_indices(draws, ratio, self.alpha, generator).to(kappa.device)
        rank = copy_rank(parents).clamp_max(self.codes.shape[0] - 1)
        return parents, rank, frames, radius

    def decode(self, points: torch.Tensor, parents: torch.Tensor, rank: torch.Tensor, frames: torch.Tensor,
               radius: torch.Tensor) -> torch.Tensor:
        """The learned part of a forward pass, deterministic given `expansion`'s outputs (what
        `cadpu.engines` export): features, expansion MLP and regression.

        Args:
            points (B, N, 3); parents, rank (B, M) int64; frames (B, N, 3, 3); radius (B, N).

        Returns:
            (B, M, 3) generated points in the frame of `points`.
        """
        features = self.extractor(points)  # (B, N, C)
        if compiled_inference(features):
            return self._decode_compiled(points, features, parents, rank, frames, radius)
        # index_select, not advanced indexing: several times faster on a CPU.
        flat_rank = rank.reshape(-1)
        code = self.codes.index_select(0, flat_rank).view(*rank.shape, 2)
        # expand_code of the few distinct codes, then looked up: a 2-wide matrix product per
        # output point is slow on a CPU.
        code_term = self.expand_code(self.codes).index_select(0, flat_rank).view(*rank.shape, -1)
        hidden = gather(self.expand_feature(features), parents) + code_term
        hidden = self.expand(torch.relu_(hidden))
        # Offset from the parent in units of its neighbourhood radius. The code skip starts copies
        # spread over the parent's tangent plane (local frame: major tangent, minor tangent, normal);
        # the learned part is in the same local frame, or in the patch's own axes ("global").
        frame = gather(frames.reshape(*frames.shape[:2], 9), parents).reshape(*parents.shape, 3, 3)
        scale = gather(radius.unsqueeze(-1), parents)
        learned = self.regress(hidden)
        if self.offset_frame == "local":
            offset = frame @ (learned + self.code_skip(code)).unsqueeze(-1)
        else:
            offset = frame @ self.code_skip(code).unsqueeze(-1) + learned.unsqueeze(-1)
        return gather(points, parents) + offset.squeeze(-1) * scale

    def _decode_compiled(self, points: torch.Tensor, features: torch.Tensor, parents: torch.Tensor,
                         rank: torch.Tensor, frames: torch.Tensor, radius: torch.Tensor) -> torch.Tensor:
        """`decode` after the feature extractor, with the per-output gathers done inside two
        compiled passes (`cadpu.kernels.expansion_hidden`, `placed_points`); the same values."""
        hidden = expansion_hidden(self.expand_feature(features), self.expand_code(self.codes), parents, rank)
        learned = self.regress(self.expand(hidden))
        return placed_points(points, frames, radius, parents, rank, learned, self.code_skip(self.codes),
                             self.offset_frame == "local")


class Discriminator(nn.Module):
    """PointNet discriminator: (B, M, 3) point sets -> (B,) realness scores (least-squares GAN)."""

    def __init__(self, width: int = 128) -> None:
        super().__init__()
        self.points = _mlp(3, 64, width, 2 * width)
        self.head = _mlp(2 * width, width, 1, last_act=False)

    def forward(self, points: torch.Tensor) -> torch.Tensor:
        features = self.points[:-2](points)  # (B, M, width): the layers before the widest one and its ReLU
        return self.head(self._pooled_widest(features)).squeeze(-1)

    def _pooled_widest(self, features: torch.Tensor) -> torch.Tensor:
        """relu(widest layer) max-pooled over the points, (B, M, width) -> (B, 2 * width).

        The same values as `relu(layer(features)).max(dim=1)` (relu is monotone, the bias is the
        same for every point), but autograd keeps only each channel's winning point: the full
        (B, M, 2 * width) product runs without gradients to find it, and only the B x 2 * width
        winning dot products are recomputed with them. Its backward then touches B * 2 * width rows
        instead of the whole product, its ReLU and the max-pool's scatter (cadpu/MODEL_CARD.md,
        "Training throughput", has the time saved)."""
        layer = self.points[-2]  # `points` ends with the widest layer and its ReLU
        with torch.no_grad():
            winner = torch.matmul(features, layer.weight.t()).argmax(dim=1)  # (B, 2 * width)
        picked = features.gather(1, winner.unsqueeze(-1).expand(-1, -1, features.shape[-1]))
        return torch.relu((picked * layer.weight).sum(-1) + layer.bias)
