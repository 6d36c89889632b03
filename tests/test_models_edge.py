"""PF-Net + mirror + edge (pfnet.models.edge): the edge score against a naive reference and on
hand-made rims, the seventh channel, growing from a trained PF-Net + mirror (its ONNX export:
test_models_mirror.py)."""

from __future__ import annotations

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from pfnet.models import ModelConfig, build_model  # noqa: E402
from pfnet.models.edge import IN_CHANNELS, NEIGHBOURS, PFNetEdge, edge_scores  # noqa: E402
from pfnet.models.mirror import PFNetMirror  # noqa: E402
from pfnet.models.pfnet import PFNetVanilla  # noqa: E402


def _naive_edge_scores(cloud: np.ndarray, k: int) -> np.ndarray:
    """Point by point: the k nearest others (brute force), |mean - p| / mean distance."""
    out = np.zeros(len(cloud))
    for i, p in enumerate(cloud):
        distance = np.linalg.norm(cloud - p, axis=1)
        distance[i] = np.inf
        near = np.argsort(distance, kind="stable")[:k]
        out[i] = np.linalg.norm(cloud[near].mean(axis=0) - p) / distance[near].mean()
    return out


def test_edge_scores_match_a_naive_reference():
    rng = np.random.default_rng(3)
    clouds = rng.normal(size=(2, 200, 3)).astype(np.float32)
    fast = edge_scores(torch.from_numpy(clouds), neighbours=12).numpy()
    for cloud, scores in zip(clouds, fast, strict=True):
        np.testing.assert_allclose(scores, _naive_edge_scores(cloud, 12), atol=1e-4)


def test_the_rim_of_a_cut_scores_high_and_the_inside_low():
    # a flat 21 x 21 grid, the plane y = 0: its border is the rim of a cut
    u, v = np.meshgrid(np.linspace(-1, 1, 21), np.linspace(-1, 1, 21))
    grid = np.stack([u.ravel(), np.zeros(u.size), v.ravel()], axis=1).astype(np.float32)
    scores = edge_scores(torch.from_numpy(grid)[None], neighbours=8)[0].numpy()
    border = (np.abs(grid[:, 0]) == 1) | (np.abs(grid[:, 2]) == 1)
    inside = (np.abs(grid[:, 0]) < 0.75) & (np.abs(grid[:, 2]) < 0.75)
    assert scores[border].min() > 0.25
    assert scores[inside].max() < 1e-5  # eight neighbours in a symmetric ring: centroid is p
    assert np.all((scores >= 0) & (scores <= 1))


def test_few_points_and_repeated_points():
    two = torch.tensor([[[0.0, 0.0, 0.0], [1.0, 0.0, 0.0]]])
    # one neighbour each: the centroid is that neighbour, a whole distance away
    assert torch.allclose(edge_scores(two), torch.ones(1, 2))
    assert torch.equal(edge_scores(two[:, :1]), torch.zeros(1, 1))
    same = torch.zeros(1, 40, 3)  # every neighbour at distance 0: no rim, no NaN
    assert torch.equal(edge_scores(same), torch.zeros(1, 40))


def test_the_seventh_channel_carries_the_edge_scores_and_zeros_on_the_mirror_images():
    torch.manual_seed(0)
    model = PFNetEdge(n_points=256, n_missing=128, width=0.125).eval()
    partial = torch.rand(1, 128, 3) * 2 - 1
    seen = []
    for cmlp in model.encoder.cmlps:
        cmlp.register_forward_pre_hook(lambda module, args: seen.append(args[0]))
    model(partial)
    full = edge_scores(partial, NEIGHBOURS)
    for features, m in zip(seen, (128, 64, 32), strict=True):
        assert features.shape == (1, m + m // 2, IN_CHANNELS)
        assert not features[0, m:, 6].any()  # the mirror images
    assert torch.allclose(seen[0][0, :128, 6], full[0])
    # a coarser scale's points keep their own score from the whole partial
    nearest = torch.cdist(seen[1][0, :64, :3], partial[0]).argmin(dim=1)
    assert torch.allclose(seen[1][0, :64, 6], full[0, nearest])


@pytest.mark.parametrize("source", [PFNetMirror, PFNetVanilla])
def test_grown_from_a_trained_network_it_computes_the_same_completion(source):
    torch.manual_seed(1)
    trained = source(n_points=256, n_missing=128, width=0.125)
    for module in trained.modules():  # BatchNorm statistics away from their defaults
        if isinstance(module, torch.nn.BatchNorm1d):
            module.running_mean.uniform_(-0.1, 0.1)
    grown = PFNetEdge(n_points=256, n_missing=128, width=0.125)
    grown.grow_from(trained)
    partial = torch.rand(2, 128, 3) * 2 - 1
    if source is PFNetMirror:  # the same function until the new channel's weights move
        expected, got = trained.eval()(partial), grown.eval()(partial)
        assert torch.allclose(got.detail, expected.detail, atol=1e-6)
    first = grown.encoder.cmlps[0].mlp.layers[0][0].weight
    assert first.shape[1] == IN_CHANNELS and not first[:, 6].any()


def test_a_training_step_moves_the_edge_weights():
    model = build_model(
        ModelConfig(model="pfnet-edge", n_points=256, missing_ratio=0.5, width=0.125)
    )
    completion = model(torch.rand(2, 128, 3) * 2 - 1)
    completion.detail.sum().backward()
    first = model.encoder.cmlps[0].mlp.layers[0][0].weight
    assert first.grad is not None and first.grad[:, 6].abs().sum() > 0
