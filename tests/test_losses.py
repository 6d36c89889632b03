"""The differentiable Chamfer loss against the Rust metric, and the training losses."""

from __future__ import annotations

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from pfnet import geometry  # noqa: E402
from pfnet.models import Completion  # noqa: E402
from pfnet.training.losses import (  # noqa: E402
    alpha_for_epoch,
    chamfer_distance,
    chamfer_loss,
    completion_loss,
    discriminator_loss,
    generator_adversarial_loss,
    joint_loss,
    nearest_neighbor_indices,
)


def _naive_chamfer(pred: np.ndarray, gt: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    d = ((pred[:, :, None, :].astype(np.float64) - gt[:, None, :, :]) ** 2).sum(-1)
    return d.min(2).mean(1), d.min(1).mean(1)


@pytest.mark.parametrize("n_pred, n_gt", [(512, 512), (64, 700), (333, 17), (1, 5)])
def test_chamfer_equals_the_rust_metric(n_pred: int, n_gt: int) -> None:
    rng = np.random.default_rng(n_pred)
    pred = (rng.random((3, n_pred, 3), dtype=np.float32) * 2 - 1).astype(np.float32)
    gt = (rng.random((3, n_gt, 3), dtype=np.float32) * 2 - 1).astype(np.float32)
    p2g, g2p = chamfer_distance(torch.from_numpy(pred), torch.from_numpy(gt))
    rust_p2g, rust_g2p = geometry.chamfer(pred, gt)
    np.testing.assert_allclose(p2g.numpy(), rust_p2g, rtol=1e-5)
    np.testing.assert_allclose(g2p.numpy(), rust_g2p, rtol=1e-5)


def test_chunked_chamfer_equals_unchunked_and_naive() -> None:
    rng = np.random.default_rng(1)
    pred = torch.from_numpy(rng.normal(size=(2, 257, 3)).astype(np.float32))
    gt = torch.from_numpy(rng.normal(size=(2, 300, 3)).astype(np.float32))
    whole = chamfer_distance(pred, gt)
    # A budget of 7 rows per block: 37 blocks, the last one partial.
    chunked = chamfer_distance(pred, gt, max_chunk_bytes=7 * 2 * 300 * 4)
    naive = _naive_chamfer(pred.numpy(), gt.numpy())
    for a, b, c in zip(whole, chunked, naive, strict=True):
        torch.testing.assert_close(a, b, rtol=0, atol=0)
        np.testing.assert_allclose(a.numpy(), c, rtol=1e-5)


def test_nearest_neighbor_indices_match_the_rust_search() -> None:
    rng = np.random.default_rng(2)
    pred = rng.random((2, 100, 3), dtype=np.float32)
    gt = rng.random((2, 80, 3), dtype=np.float32)
    p_idx, g_idx = nearest_neighbor_indices(
        torch.from_numpy(pred), torch.from_numpy(gt), max_chunk_bytes=1
    )
    np.testing.assert_array_equal(p_idx.numpy(), geometry.nearest_neighbors(pred, gt)[1])
    np.testing.assert_array_equal(g_idx.numpy(), geometry.nearest_neighbors(gt, pred)[1])


def test_chamfer_gradient_matches_finite_differences() -> None:
    rng = np.random.default_rng(3)
    pred = torch.from_numpy(rng.random((2, 9, 3))).requires_grad_()
    gt = torch.from_numpy(rng.random((2, 11, 3)))
    assert torch.autograd.gradcheck(lambda p: sum(chamfer_distance(p, gt)), (pred,))


def test_chamfer_gradient_flows_to_the_prediction_only() -> None:
    pred = torch.tensor([[[0.0, 0.0, 0.0], [-1.0, 0.0, 0.0]]], requires_grad=True)
    gt = torch.tensor([[[1.0, 0.0, 0.0]]])
    p2g, g2p = chamfer_distance(pred, gt)
    assert p2g.item() == pytest.approx((1.0 + 4.0) / 2) and g2p.item() == pytest.approx(1.0)
    (p2g + g2p).sum().backward()
    # d/dp_i of mean_i |p_i - g|^2 is (p_i - g); gt's nearest pred (point 0) adds 2 (p_0 - g).
    expected = torch.tensor([[[-3.0, 0.0, 0.0], [-2.0, 0.0, 0.0]]])
    torch.testing.assert_close(pred.grad, expected)
    assert gt.grad is None


@pytest.mark.parametrize(
    "pred_shape, gt_shape, match",
    [
        ((2, 5, 3), (3, 5, 3), "same batch size"),
        ((2, 5), (2, 5, 3), r"pred must have shape \(B, N, 3\)"),
        ((2, 5, 3), (2, 0, 3), r"gt must have shape \(B, N, 3\) with N >= 1"),
    ],
)
def test_chamfer_rejects_bad_shapes(pred_shape, gt_shape, match) -> None:
    with pytest.raises(ValueError, match=match):
        chamfer_distance(torch.zeros(pred_shape), torch.zeros(gt_shape))


def test_alpha_schedule_of_the_authors() -> None:
    schedule = ((0, 0.01), (30, 0.05), (80, 0.1))
    assert [alpha_for_epoch(e, schedule) for e in (0, 29, 30, 79, 80, 500)] == [
        0.01,
        0.01,
        0.05,
        0.05,
        0.1,
        0.1,
    ]


def test_completion_loss_weights_the_centre_terms_by_alpha_and_two_alpha() -> None:
    gt = torch.zeros(1, 4, 3)
    detail = torch.ones(1, 4, 3)  # squared distance 3 both ways: CD = 6
    primary = torch.full((1, 2, 3), 2.0)  # 12 both ways: CD = 24
    secondary = torch.full((1, 3, 3), 3.0)  # 27 both ways: CD = 54
    completion = Completion(primary, secondary, detail)
    total, parts = completion_loss(completion, gt, gt[:, :3], gt[:, :2], alpha=0.1, scale=10.0)
    assert parts["cd_detail"].item() == pytest.approx(60.0)
    assert parts["cd_primary"].item() == pytest.approx(240.0)
    assert parts["cd_secondary"].item() == pytest.approx(540.0)
    assert total.item() == pytest.approx(60.0 + 0.1 * 240.0 + 0.2 * 540.0)
    baseline_total, baseline_parts = completion_loss(
        Completion(None, None, detail), gt, None, None, alpha=0.1, scale=10.0
    )
    assert baseline_total.item() == pytest.approx(60.0)
    assert set(baseline_parts) == {"cd_detail"}


def test_l1_chamfer_loss_is_the_mean_distance_of_a_float64_reference() -> None:
    rng = np.random.default_rng(4)
    pred = rng.random((3, 70, 3), dtype=np.float32)
    gt = rng.random((3, 90, 3), dtype=np.float32)
    d = np.sqrt(((pred[:, :, None, :].astype(np.float64) - gt[:, None, :, :]) ** 2).sum(-1))
    expected = 7.0 * (d.min(2).mean(1) + d.min(1).mean(1)).mean()
    loss = chamfer_loss(torch.from_numpy(pred), torch.from_numpy(gt), 7.0, chamfer="l1")
    assert loss.item() == pytest.approx(expected, rel=1e-5)
    squared = chamfer_loss(torch.from_numpy(pred), torch.from_numpy(gt), 7.0)
    naive = _naive_chamfer(pred, gt)
    assert squared.item() == pytest.approx(7.0 * (naive[0] + naive[1]).mean(), rel=1e-5)


def test_l1_chamfer_gradient_is_a_unit_pull_and_zero_on_the_surface() -> None:
    # Point 0 lies 2 from the gt point along x, point 1 on it: |p - g| has gradient
    # (p - g) / |p - g| away from 0 and none at 0 (no NaN from 0 / 0).
    pred = torch.tensor([[[2.0, 0.0, 0.0], [0.0, 0.0, 0.0]]], requires_grad=True)
    gt = torch.tensor([[[0.0, 0.0, 0.0]]])
    loss = chamfer_loss(pred, gt, 1.0, chamfer="l1")
    assert loss.item() == pytest.approx((2.0 + 0.0) / 2 + 0.0)
    loss.backward()
    torch.testing.assert_close(pred.grad, torch.tensor([[[0.5, 0.0, 0.0], [0.0, 0.0, 0.0]]]))
    rng = np.random.default_rng(5)
    p64 = torch.from_numpy(rng.random((2, 9, 3))).requires_grad_()
    g64 = torch.from_numpy(rng.random((2, 11, 3)))
    assert torch.autograd.gradcheck(lambda p: chamfer_loss(p, g64, 3.0, chamfer="l1"), (p64,))


def test_completion_loss_on_l1_logs_the_squared_chamfer_of_each_stage() -> None:
    gt = torch.zeros(1, 4, 3)
    detail = torch.ones(1, 4, 3)  # distance √3 both ways: L1 sum 2√3, L2 sum 6
    primary = torch.full((1, 2, 3), 2.0)  # 2√3 and 12
    completion = Completion(primary, None, detail)
    total, parts = completion_loss(
        completion, gt, None, gt[:, :2], alpha=0.1, scale=10.0, chamfer="l1"
    )
    root3 = 3.0**0.5
    assert total.item() == pytest.approx(10.0 * 2 * root3 + 0.1 * 10.0 * 4 * root3)
    assert parts["cd_detail"].item() == pytest.approx(60.0)
    assert parts["cd_primary"].item() == pytest.approx(240.0)
    with pytest.raises(ValueError, match="chamfer must be one of l2, l1; got 'l3'"):
        completion_loss(completion, gt, None, gt[:, :2], alpha=0.1, scale=1.0, chamfer="l3")


def test_adversarial_losses_are_bce_with_logits() -> None:
    logits = torch.tensor([0.0, 2.0, -1.0])
    real = discriminator_loss(logits, real=True)
    fake = discriminator_loss(logits, real=False)
    expected_real = torch.nn.functional.softplus(-logits).mean()
    expected_fake = torch.nn.functional.softplus(logits).mean()
    torch.testing.assert_close(real, expected_real)
    torch.testing.assert_close(fake, expected_fake)
    torch.testing.assert_close(generator_adversarial_loss(logits), expected_real)
    total = joint_loss(torch.tensor(2.0), torch.tensor(10.0), 0.05)
    assert total.item() == pytest.approx(0.95 * 2.0 + 0.05 * 10.0)
