import pytest
import torch

from cadpu.geometry import sampling_weights
from cadpu.network import Discriminator, Generator, copy_rank, expansion_indices, grid_codes


def _patch(batch: int = 2, n: int = 256, seed: int = 0) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    p = torch.randn(batch, n, 3, generator=g)
    return p / p.norm(dim=-1, keepdim=True).amax(dim=1, keepdim=True)


@pytest.mark.parametrize("ratio", [2, 4, 5])
@pytest.mark.parametrize("alpha", [0.0, 0.5, 1.0])
def test_output_size_and_parents(ratio: int, alpha: float) -> None:
    net = Generator(ratio=ratio, alpha=alpha).eval()
    points, parents = net(_patch())
    assert points.shape == (2, 256 * ratio, 3)
    assert parents.shape == (2, 256 * ratio)
    assert parents.min() >= 0 and parents.max() < 256


def test_uniform_expansion_copies_every_point_r_times() -> None:
    kappa = torch.rand(3, 100)
    parents = expansion_indices(kappa, 4, 1.0)
    counts = torch.stack([torch.bincount(p, minlength=100) for p in parents])
    assert (counts == 4).all()


def test_adaptive_draws_follow_equation_3() -> None:
    kappa = torch.zeros(1, 4)
    kappa[0, 3] = 0.3  # one high-curvature point
    draws = expansion_indices(kappa.expand(400, -1).contiguous(), 1000, 0.0,
                              torch.Generator().manual_seed(0))
    frequency = torch.bincount(draws.reshape(-1), minlength=4).double()
    frequency /= frequency.sum()
    expected = sampling_weights(kappa[0].double(), 0.01)
    assert torch.allclose(frequency, expected, atol=0.003)
    assert frequency[3] > 10 * frequency[0]


def test_hybrid_expansion_keeps_alpha_share_uniform() -> None:
    kappa = torch.rand(1, 256)
    parents = expansion_indices(kappa, 4, 0.5, torch.Generator().manual_seed(0))
    counts = torch.bincount(parents[0], minlength=256)
    assert parents.shape == (1, 1024)
    assert (counts >= 2).all()  # every point has its two uniform copies


def test_copy_rank_numbers_duplicates() -> None:
    parents = torch.tensor([[0, 0, 0, 2, 5, 5]])
    assert copy_rank(parents).tolist() == [[0, 1, 2, 0, 0, 1]]


def test_grid_codes_spread_from_the_origin_in_the_papers_order() -> None:
    codes = grid_codes(9) / 0.2
    assert codes[:5].round().tolist() == [[1, 0], [1, 1], [0, 1], [-1, 1], [-1, 0]]
    norms = codes.norm(dim=1)
    assert norms[8] > norms[:8].max() - 1e-6


def test_fixed_seed_gives_identical_outputs() -> None:
    net = Generator().eval()
    patch = _patch()
    a, pa = net(patch, generator=torch.Generator().manual_seed(3))
    b, pb = net(patch, generator=torch.Generator().manual_seed(3))
    assert torch.equal(a, b) and torch.equal(pa, pb)


def test_edgeconv_decomposition_matches_the_direct_edge_mlp() -> None:
    net = Generator().eval()
    block = net.extractor.blocks[0]
    features = torch.randn(1, 64, block.centre.in_features)
    from cadpu.geometry import gather, knn

    index = knn(features, features, block.k)
    centre = features.unsqueeze(2).expand(-1, -1, block.k, -1)
    edge = torch.cat([centre, gather(features, index) - centre], dim=-1)
    c = features.shape[-1]
    # [f_i, f_j - f_i] -> W_a f_i + W_b (f_j - f_i) with W_a = centre, W_b = neighbour
    first = edge[..., :c] @ block.centre.weight.T + edge[..., c:] @ block.neighbour.weight.T + block.centre.bias
    g = block.growth
    h1 = torch.relu(first[..., :g])
    h2 = torch.relu(first[..., g:2 * g] + h1 @ block.layer2.weight.T)
    h3 = torch.relu(first[..., 2 * g:] + torch.cat([h1, h2], -1) @ block.layer3.weight.T)
    direct = torch.cat([h1, h2, h3], -1).amax(dim=2)
    assert torch.allclose(block(features), direct, atol=1e-5)


def test_edgeconv_training_gradients_match_the_direct_edge_mlp() -> None:
    """With gradients on, the block's decomposed, out-of-place products give the gradients of the
    plain edge MLP, for its input and for every weight."""
    torch.manual_seed(1)
    block = Generator().extractor.blocks[1]
    features = torch.randn(2, 64, block.centre.in_features)
    from cadpu.geometry import gather, knn

    def direct(f: torch.Tensor) -> torch.Tensor:
        index = knn(f.detach(), f.detach(), block.k)
        centre = f.unsqueeze(2).expand(-1, -1, block.k, -1)
        neighbour = gather(f, index) - centre
        first = centre @ block.centre.weight.T + neighbour @ block.neighbour.weight.T + block.centre.bias
        g = block.growth
        h1 = torch.relu(first[..., :g])
        h2 = torch.relu(first[..., g:2 * g] + h1 @ block.layer2.weight.T)
        h3 = torch.relu(first[..., 2 * g:] + torch.cat([h1, h2], -1) @ block.layer3.weight.T)
        return torch.cat([h1, h2, h3], -1).amax(dim=2)

    weights = [block.centre.weight, block.centre.bias, block.neighbour.weight, block.layer2.weight, block.layer3.weight]
    grads = []
    for forward in (block, direct):
        tracked = features.clone().requires_grad_(True)
        (forward(tracked) * torch.linspace(-1, 1, 3 * block.growth)).sum().backward()
        grads.append([tracked.grad.clone()] + [w.grad.clone() for w in weights])
        block.zero_grad()
    for ours, reference in zip(*grads):
        assert torch.allclose(ours, reference, atol=1e-4, rtol=1e-4)


def test_edgeconv_compiled_inference_path_equals_the_torch_path() -> None:
    """Without gradients a block gathers its edges in one compiled pass; with them (training) it
    runs in torch. Both give the same values, in every block and batch size."""
    torch.manual_seed(0)
    net = Generator().eval()
    for block in net.extractor.blocks:
        for batch in (1, 3):
            features = torch.randn(batch, 96, block.centre.in_features)
            with torch.no_grad():
                assert block._compiled_edges(features)
                compiled = block(features)
            tracked = features.clone().requires_grad_(True)
            assert not block._compiled_edges(tracked)
            reference = block(tracked)
            assert torch.allclose(compiled, reference.detach(), atol=1e-6, rtol=0)
            reference.sum().backward()
            assert tracked.grad is not None and tracked.grad.abs().sum() > 0


def test_edgeconv_weights_get_gradients_from_inputs_without_them() -> None:
    """With gradients on, a block's own weights are trained even when its input needs none: the
    compiled kernels, invisible to autograd, must not run then."""
    block = Generator().extractor.blocks[0]
    out = block(torch.randn(2, 64, block.centre.in_features))
    assert out.requires_grad
    out.sum().backward()
    assert block.neighbour.weight.grad is not None and block.neighbour.weight.grad.abs().sum() > 0


@pytest.mark.parametrize("offset_frame", ["local", "global"])
def test_decode_compiled_inference_path_equals_the_torch_path(offset_frame: str) -> None:
    torch.manual_seed(1)
    net = Generator(offset_frame=offset_frame).eval()
    with torch.no_grad():
        for parameter in net.parameters():  # the regression head starts at zero: make it count
            parameter.add_(torch.randn_like(parameter) * 0.05)
    points = torch.randn(2, 256, 3)
    with torch.no_grad():
        parents, rank, frames, radius = net.expansion(points, 4, torch.Generator().manual_seed(0))
        compiled = net.decode(points, parents, rank, frames, radius)
    reference = net.decode(points, parents, rank, frames, radius)  # gradients on: the torch path
    assert reference.requires_grad
    assert torch.allclose(compiled, reference.detach(), atol=1e-6, rtol=0)


def test_discriminator_scores_each_set() -> None:
    scores = Discriminator()(torch.randn(5, 1024, 3))
    assert scores.shape == (5,)


def test_rejects_bad_ratio_and_alpha() -> None:
    with pytest.raises(ValueError, match="ratio"):
        Generator(ratio=1)
    with pytest.raises(ValueError, match="alpha"):
        Generator(alpha=1.5)


@pytest.mark.parametrize("offset_frame", ["local", "global"])
def test_learned_offsets_are_in_the_chosen_axes(offset_frame: str) -> None:
    """A constant learned offset (0, 0, 1) radius: along z in patch axes ("global"), along each
    parent's own normal ("local"), where a sphere's normals are anything but z."""
    net = Generator(ratio=4, alpha=1.0, offset_frame=offset_frame, code_spread=0.0).eval()
    with torch.no_grad():
        net.regress[-1].bias.copy_(torch.tensor([0.0, 0.0, 1.0]))
    points = _patch(batch=1)
    out, parents = net(points)
    offset = out - points[0, parents[0]]
    direction = offset / offset.norm(dim=-1, keepdim=True)
    along_z = direction[..., 2].abs()
    if offset_frame == "global":
        assert torch.allclose(along_z, torch.ones_like(along_z), atol=1e-5)
    else:
        assert along_z.mean() < 0.9


def test_rejects_an_unknown_offset_frame() -> None:
    with pytest.raises(ValueError, match="offset_frame"):
        Generator(offset_frame="sensor")


def test_discriminator_pools_as_the_plain_max_does_values_and_gradients() -> None:
    """The discriminator's pooled widest layer keeps only each channel's winning point under
    autograd; scores and every gradient must be those of relu(layer(features)).max over the points."""
    torch.manual_seed(0)
    discriminator = Discriminator()
    points = torch.randn(3, 512, 3)

    def scores_and_gradients(forward) -> list[torch.Tensor]:
        discriminator.zero_grad()
        given = points.clone().requires_grad_(True)
        scores = forward(given)
        (scores * torch.arange(1.0, 4.0)).sum().backward()
        return [scores.detach(), given.grad, *(p.grad for p in discriminator.parameters())]

    def plain(given: torch.Tensor) -> torch.Tensor:
        return discriminator.head(discriminator.points(given).max(dim=1).values).squeeze(-1)

    for ours, theirs in zip(scores_and_gradients(discriminator), scores_and_gradients(plain), strict=True):
        assert ours.shape == theirs.shape
        assert torch.allclose(ours, theirs, rtol=1e-5, atol=1e-6 * float(theirs.abs().max()))
