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
from pfnet.training.config import CHAMFER_KINDS

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


def nearest_squared_distances(
    pred: Tensor, gt: Tensor, *, max_chunk_bytes: int = DEFAULT_CHUNK_BYTES
) -> tuple[Tensor, Tensor]:
    """Each point's squared distance to its nearest neighbour in the other cloud, differentiable.

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
        ``(B, P)`` squared distances of pred points to gt and ``(B, G)`` of gt points to pred.

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
        return (pred - nearest_gt).square().sum(-1), (gt - nearest_pred).square().sum(-1)


def chamfer_distance(
    pred: Tensor, gt: Tensor, *, max_chunk_bytes: int = DEFAULT_CHUNK_BYTES
) -> tuple[Tensor, Tensor]:
    """The two directed Chamfer terms of paper Eq. (1), differentiable, per cloud.

    Args:
        pred: ``(B, P, 3)`` float predicted clouds.
        gt: ``(B, G, 3)`` float reference clouds (P and G may differ).
        max_chunk_bytes: Memory budget of one block of the distance matrix.

    Returns:
        ``(pred_to_gt (B,), gt_to_pred (B,))``: mean squared distance of each pred point to
        its nearest gt point, and the reverse (see :func:`nearest_squared_distances`).

    Raises:
        ValueError: Shapes that are not ``(B, *, 3)`` with equal B and at least one point.
    """
    to_gt, to_pred = nearest_squared_distances(pred, gt, max_chunk_bytes=max_chunk_bytes)
    return to_gt.mean(1), to_pred.mean(1)


def _distance(squared: Tensor) -> Tensor:
    """``√squared``, with value and gradient 0 where ``squared`` is 0 (not 0 / 0 = NaN)."""
    on_surface = squared == 0
    return torch.where(on_surface, 0.0, torch.where(on_surface, 1.0, squared).sqrt())


def _chamfer_terms(pred: Tensor, gt: Tensor, scale: float, chamfer: str) -> tuple[Tensor, Tensor]:
    """``(loss, scale · CD-L2)`` of a batch from one neighbour search (see :func:`chamfer_loss`).

    The second value is the paper's Chamfer whatever the loss, so that logs of runs trained
    on either loss compare.
    """
    if chamfer not in CHAMFER_KINDS:
        raise ValueError(f"chamfer must be one of {', '.join(CHAMFER_KINDS)}; got {chamfer!r}")
    to_gt, to_pred = nearest_squared_distances(pred, gt)
    squared = scale * (to_gt.mean(1) + to_pred.mean(1)).mean()
    if chamfer == "l2":
        return squared, squared
    to_gt, to_pred = _distance(to_gt), _distance(to_pred)
    return scale * (to_gt.mean(1) + to_pred.mean(1)).mean(), squared


def chamfer_loss(pred: Tensor, gt: Tensor, scale: float, chamfer: str = "l2") -> Tensor:
    """Batch mean of ``scale`` times the two directed Chamfer terms, a scalar.

    Args:
        pred: ``(B, P, 3)`` predicted clouds.
        gt: ``(B, G, 3)`` reference clouds.
        scale: Factor on the sum of both terms.
        chamfer: ``"l2"`` (paper Eq. 1): the mean squared distances; ``"l1"``: the mean
            distances (PoinTr's CD-L1 without its halving), which charge far points less and
            points near the surface more than the squares do.

    Raises:
        ValueError: An unknown ``chamfer``, or clouds :func:`nearest_squared_distances`
            refuses.
    """
    return _chamfer_terms(pred, gt, scale, chamfer)[0]


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
    chamfer: str = "l2",
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
        chamfer: ``"l2"`` (the paper's) or ``"l1"``: the kind of every Chamfer term of the
            loss (:func:`chamfer_loss`).

    Returns:
        The scalar loss and its parts ``{"cd_detail", "cd_primary", "cd_secondary"}``
        (detached, only the stages present), each ``scale`` times the stage's CD-L2 whatever
        ``chamfer`` is, so that runs on either loss log the same measure.
    """
    total, cd_detail = _chamfer_terms(completion.detail, missing, scale, chamfer)
    parts = {"cd_detail": cd_detail.detach()}
    if completion.primary is not None and primary_target is not None:
        loss, cd_primary = _chamfer_terms(completion.primary, primary_target, scale, chamfer)
        total = total + alpha * loss
        parts["cd_primary"] = cd_primary.detach()
    if completion.secondary is not None and secondary_target is not None:
        loss, cd_secondary = _chamfer_terms(completion.secondary, secondary_target, scale, chamfer)
        total = total + 2.0 * alpha * loss
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
