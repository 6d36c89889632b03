"""Training losses: differentiable Chamfer distance, multi-stage completion loss, GAN losses.

The Chamfer terms equal :func:`pfnet.geometry.chamfer` (paper Eq. 1, raw units) on the same
clouds; they are what the network is trained on, while evaluation uses the exact Rust metric.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
import torch.nn.functional as F
from torch import Tensor

from pfnet.models.completion import Completion

DEFAULT_CHUNK_BYTES = 64 * 2**20


@torch.no_grad()
def nearest_neighbor_indices(
    pred: Tensor, gt: Tensor, *, max_chunk_bytes: int = DEFAULT_CHUNK_BYTES
) -> tuple[Tensor, Tensor]:
    """Index of each point's nearest neighbour in the other cloud, in bounded memory.

    The squared distances come from ``|p|² + |g|² - 2 p·g`` one block of pred rows at a
    time, so at most ``max_chunk_bytes`` of the ``(B, P, G)`` distance matrix exist at once
    (36 × 2048 × 2048 float32 would be 604 MB). Ties go to the lowest index.

    Args:
        pred: ``(B, P, 3)`` predicted clouds.
        gt: ``(B, G, 3)`` reference clouds.
        max_chunk_bytes: Memory budget of one distance block.

    Returns:
        int64 ``(B, P)`` indices into gt and ``(B, G)`` indices into pred.
    """
    batch, n_pred, _ = pred.shape
    n_gt = gt.shape[1]
    pred = pred.detach()
    gt = gt.detach()
    rows = max(1, max_chunk_bytes // max(1, batch * n_gt * pred.element_size()))
    gt_sq = (gt * gt).sum(-1).unsqueeze(1)  # (B, 1, G)
    pred_to_gt = torch.empty(batch, n_pred, dtype=torch.long, device=pred.device)
    best_gt = torch.full((batch, n_gt), float("inf"), dtype=pred.dtype, device=pred.device)
    gt_to_pred = torch.zeros(batch, n_gt, dtype=torch.long, device=pred.device)
    for start in range(0, n_pred, rows):
        block = pred[:, start : start + rows]
        dist = torch.baddbmm(
            (block * block).sum(-1).unsqueeze(2) + gt_sq, block, gt.transpose(1, 2), alpha=-2.0
        )
        pred_to_gt[:, start : start + rows] = dist.argmin(dim=2)
        value, index = dist.min(dim=1)
        better = value < best_gt  # strict: an earlier block keeps ties (lowest index)
        best_gt = torch.where(better, value, best_gt)
        gt_to_pred = torch.where(better, index + start, gt_to_pred)
    return pred_to_gt, gt_to_pred


def chamfer_distance(
    pred: Tensor, gt: Tensor, *, max_chunk_bytes: int = DEFAULT_CHUNK_BYTES
) -> tuple[Tensor, Tensor]:
    """The two directed Chamfer terms of paper Eq. (1), differentiable, per cloud.

    Nearest neighbours are found without gradient (:func:`nearest_neighbor_indices`); the
    squared distances to them are then recomputed exactly as ``|p - g|²``, so the values
    match the Rust metric and gradients flow to ``pred`` (and to ``gt`` if it requires them).
    Always computed in at least float32, with autocast off: a bfloat16 distance matrix would
    pick wrong neighbours (8 bits of mantissa) and sum the terms coarsely.

    Args:
        pred: ``(B, P, 3)`` float predicted clouds.
        gt: ``(B, G, 3)`` float reference clouds (P and G may differ).
        max_chunk_bytes: Memory budget of one block of the distance matrix.

    Returns:
        ``(pred_to_gt (B,), gt_to_pred (B,))``: mean squared distance of each pred point to
        its nearest gt point, and the reverse.

    Raises:
        ValueError: Shapes that are not ``(B, *, 3)`` with equal B and at least one point.
    """
    for name, cloud in (("pred", pred), ("gt", gt)):
        if cloud.ndim != 3 or cloud.shape[2] != 3 or cloud.shape[1] == 0:
            raise ValueError(
                f"{name} must have shape (B, N, 3) with N >= 1; got {tuple(cloud.shape)}"
            )
    if pred.shape[0] != gt.shape[0]:
        raise ValueError(
            "pred and gt must have the same batch size; "
            f"got {tuple(pred.shape)} and {tuple(gt.shape)}"
        )
    dtype = torch.promote_types(torch.promote_types(pred.dtype, gt.dtype), torch.float32)
    with torch.autocast(pred.device.type, enabled=False):
        pred, gt = pred.to(dtype), gt.to(dtype)
        pred_index, gt_index = nearest_neighbor_indices(pred, gt, max_chunk_bytes=max_chunk_bytes)
        nearest_gt = torch.gather(gt, 1, pred_index.unsqueeze(-1).expand(-1, -1, 3))
        nearest_pred = torch.gather(pred, 1, gt_index.unsqueeze(-1).expand(-1, -1, 3))
        pred_to_gt = (pred - nearest_gt).square().sum(-1).mean(1)
        gt_to_pred = (gt - nearest_pred).square().sum(-1).mean(1)
    return pred_to_gt, gt_to_pred


def chamfer_loss(pred: Tensor, gt: Tensor, scale: float) -> Tensor:
    """Batch mean of ``scale · (pred_to_gt + gt_to_pred)``, a scalar."""
    pred_to_gt, gt_to_pred = chamfer_distance(pred, gt)
    return scale * (pred_to_gt + gt_to_pred).mean()


def alpha_for_epoch(epoch: int, schedule: Sequence[Sequence[float]]) -> float:
    """The weight α of the centre terms at 0-based ``epoch``.

    Args:
        epoch: 0-based epoch.
        schedule: ``[(first_epoch, alpha), ...]`` sorted by first_epoch, starting at 0. The
            authors' schedule is ``[(0, 0.01), (30, 0.05), (80, 0.1)]``.
    """
    alpha = float(schedule[0][1])
    for first_epoch, value in schedule:
        if epoch >= first_epoch:
            alpha = float(value)
    return alpha


def completion_loss(
    completion: Completion,
    missing: Tensor,
    secondary_target: Tensor | None,
    primary_target: Tensor | None,
    *,
    alpha: float,
    scale: float,
) -> tuple[Tensor, dict[str, Tensor]]:
    """Multi-stage completion loss, paper Eq. (2).

    ``L_com = CD(detail, gt) + α·CD(primary, IFPS64(gt)) + 2α·CD(secondary, IFPS128(gt))``,
    each CD the sum of both directed terms, averaged over the batch and multiplied by
    ``scale`` (the authors' ``PointLoss`` is ``100 · (d1 + d2) / 2``, i.e. scale 50). Stages
    the model does not produce (``None``) are left out.

    Args:
        completion: The generator's output.
        missing: ``(B, M, 3)`` ground truth of the missing region.
        secondary_target: ``(B, 128, 3)`` IFPS sample of ``missing``, or ``None``.
        primary_target: ``(B, 64, 3)`` IFPS sample of ``missing``, or ``None``.
        alpha: The α of the schedule (:func:`alpha_for_epoch`).
        scale: Factor applied to every Chamfer term.

    Returns:
        The scalar loss and its parts ``{"cd_detail", "cd_primary", "cd_secondary"}``
        (detached, only the stages present).
    """
    cd_detail = chamfer_loss(completion.detail, missing, scale)
    total = cd_detail
    parts = {"cd_detail": cd_detail.detach()}
    if completion.primary is not None and primary_target is not None:
        cd_primary = chamfer_loss(completion.primary, primary_target, scale)
        total = total + alpha * cd_primary
        parts["cd_primary"] = cd_primary.detach()
    if completion.secondary is not None and secondary_target is not None:
        cd_secondary = chamfer_loss(completion.secondary, secondary_target, scale)
        total = total + 2.0 * alpha * cd_secondary
        parts["cd_secondary"] = cd_secondary.detach()
    return total, parts


def discriminator_loss(logits: Tensor, *, real: bool) -> Tensor:
    """BCE-with-logits of the discriminator (Eq. 3): real clouds labelled 1, predictions 0."""
    target = torch.ones_like(logits) if real else torch.zeros_like(logits)
    return F.binary_cross_entropy_with_logits(logits, target)


def generator_adversarial_loss(fake_logits: Tensor) -> Tensor:
    """The generator's adversarial term: BCE-with-logits of its predictions labelled real."""
    return discriminator_loss(fake_logits, real=True)


def joint_loss(completion: Tensor, adversarial: Tensor, adversarial_weight: float) -> Tensor:
    """``λ_com · L_com + λ_adv · L_adv`` with ``λ_com = 1 - λ_adv`` (paper Eq. 4; 0.95/0.05)."""
    return (1.0 - adversarial_weight) * completion + adversarial_weight * adversarial
