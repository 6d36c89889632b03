"""Completion metrics on top of the Rust nearest-neighbour core (PF-Net §4, Eq. 1).

``sample_metrics`` scores each (prediction, ground truth) pair; ``summarize`` turns per-sample
scores into the paper's per-category table: the mean over the samples of each category, and an
overall row that is the unweighted mean of the category means. The ``evaluate`` command and the
validation of ``pfnet train`` both use these two functions.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
from numpy.typing import ArrayLike

from pfnet.errors import ConfigError
from pfnet.geometry import nearest_neighbors

METRICS = ("pred_to_gt", "gt_to_pred", "cd_l2", "cd_l1", "f_score")
"""Per-sample metric names, in table order."""

SCALED = ("pred_to_gt", "gt_to_pred", "cd_l2")
"""Metrics reported ×1000 in the paper's tables (squared distances)."""


def _pairs(pred, gt) -> list[tuple[np.ndarray, np.ndarray]]:
    if isinstance(pred, np.ndarray) and isinstance(gt, np.ndarray):
        if pred.ndim != 3 or gt.ndim != 3:
            raise ValueError(
                f"pred and gt must be (B, P, 3) and (B, G, 3) arrays or lists of (P_i, 3) "
                f"arrays, got shapes {pred.shape} and {gt.shape}"
            )
    if len(pred) != len(gt):
        raise ValueError(f"pred and gt must hold as many clouds, got {len(pred)} and {len(gt)}")
    return list(zip(pred, gt))


def sample_metrics(
    pred, gt, f_threshold: float = 0.01, *, ignore_zeros: bool = False
) -> dict[str, np.ndarray]:
    """Per-sample completion metrics, in raw units (not ×1000).

    These are PoinTr's formulas (``extensions/chamfer_dist/__init__.py``,
    ``utils/metrics.py``): with ``d(p, Q)`` the Euclidean distance from ``p`` to its nearest
    point of ``Q``, ``CD-L2 = mean_P d(p, G)² + mean_G d(g, P)²``, ``CD-L1 = (mean_P d(p, G) +
    mean_G d(g, P)) / 2``, and ``F = 2·precision·recall / (precision + recall)`` (0 when both
    are 0) with precision the share of predicted points with ``d(p, G) < threshold`` and
    recall the share of ground-truth points with ``d(g, P) < threshold``.

    Args:
        pred: Predicted clouds, a ``(B, P, 3)`` array or a list of ``(P_i, 3)`` arrays.
        gt: Ground-truth clouds, ``(B, G, 3)`` or a list of ``(G_i, 3)`` arrays.
        f_threshold: Distance threshold of the F-score (in the clouds' units).
        ignore_zeros: Leave points whose coordinates sum to exactly 0 out of both clouds
            before the Chamfer terms, as PoinTr's ``ChamferDistanceL1/L2(ignore_zeros=True)``
            does at batch size 1 (its test loop); the F-score keeps every point. A cloud left
            empty by it raises ``ValueError``.

    Returns:
        float64 ``(B,)`` arrays: ``pred_to_gt`` and ``gt_to_pred`` (Eq. 1's two terms: mean
        squared nearest-neighbour distances), ``cd_l2`` (their sum), ``cd_l1`` (the mean of the
        two directions' mean unsquared distances) and ``f_score`` (harmonic mean of the fraction
        of predicted points within ``f_threshold`` of the ground truth and the reverse).
    """
    try:  # an int beyond float64 (10**400) would raise OverflowError
        threshold = float(f_threshold) if isinstance(f_threshold, (int, float)) else math.nan
    except OverflowError:
        threshold = math.inf
    if not (math.isfinite(threshold) and threshold > 0):
        # -1 gave every sample an F-score of 1, NaN of 0
        raise ConfigError(
            f"f_threshold must be a positive finite distance, got {f_threshold!r:.40}"
        )
    pairs = _pairs(pred, gt)
    out = {name: np.zeros(len(pairs)) for name in METRICS}
    if not pairs:
        return out
    if isinstance(pred, np.ndarray) and isinstance(gt, np.ndarray):
        # One batched call each way: the Rust core spreads the pairs over all cores.
        d_pg = nearest_neighbors(pred, gt)[0].astype(np.float64)
        d_gp = nearest_neighbors(gt, pred)[0].astype(np.float64)
        rows = list(zip(d_pg, d_gp))
    else:
        rows = [
            (
                nearest_neighbors(p, g)[0].astype(np.float64),
                nearest_neighbors(g, p)[0].astype(np.float64),
            )
            for p, g in pairs
        ]
    t2 = threshold**2
    for i, (pg, gp) in enumerate(rows):
        cd_pg, cd_gp = pg, gp
        if ignore_zeros:
            cd_pg, cd_gp = _without_zero_sum(pairs[i][0], pairs[i][1], pg, gp)
        out["pred_to_gt"][i] = cd_pg.mean()
        out["gt_to_pred"][i] = cd_gp.mean()
        out["cd_l1"][i] = 0.5 * (np.sqrt(cd_pg).mean() + np.sqrt(cd_gp).mean())
        precision = float((pg < t2).mean())
        recall = float((gp < t2).mean())
        total = precision + recall
        out["f_score"][i] = 2 * precision * recall / total if total > 0 else 0.0
    out["cd_l2"] = out["pred_to_gt"] + out["gt_to_pred"]
    return out


def zero_sum_mask(cloud: np.ndarray) -> np.ndarray:
    """Points PoinTr's ``ignore_zeros`` keeps: ``x + y + z != 0``, summed in float32."""
    return np.asarray(cloud, dtype=np.float32).sum(axis=1, dtype=np.float32) != 0


def _without_zero_sum(
    pred: np.ndarray, gt: np.ndarray, pg: np.ndarray, gp: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """The two directed squared-distance arrays over the clouds without zero-sum points."""
    keep_p, keep_g = zero_sum_mask(pred), zero_sum_mask(gt)
    if keep_p.all() and keep_g.all():
        return pg, gp
    if not keep_p.any() or not keep_g.any():
        raise ValueError("every point of a cloud has x + y + z = 0: no Chamfer distance")
    p = np.ascontiguousarray(pred[keep_p])
    g = np.ascontiguousarray(gt[keep_g])
    return (
        nearest_neighbors(p, g)[0].astype(np.float64),
        nearest_neighbors(g, p)[0].astype(np.float64),
    )


def summarize(
    per_sample: dict[str, ArrayLike],
    categories: Sequence[str],
    scale: float = 1000.0,
    scaled: Sequence[str] = SCALED,
) -> dict:
    """Per-category means and their unweighted mean, as in the paper's tables.

    Args:
        per_sample: Output of :func:`sample_metrics` (any subset of its keys).
        categories: The category of each sample, same length as the arrays.
        scale: Factor for the squared-distance metrics (the paper reports ×1000).
        scaled: The metrics multiplied by ``scale`` (PoinTr's protocols scale CD-L1 too).

    Returns:
        ``{"categories": {cat: {"n": int, metric: float, ...}}, "mean": {metric: float}}``,
        categories sorted by name; ``"mean"`` is the unweighted mean of the category means.
    """
    categories = np.asarray(categories, dtype=str)
    names = [m for m in METRICS if m in per_sample]
    values = {m: np.asarray(per_sample[m], dtype=np.float64) for m in names}
    for m, v in values.items():
        if v.shape != categories.shape:
            raise ValueError(
                f"per_sample[{m!r}] has shape {v.shape} but there are {categories.size} categories"
            )
    table: dict[str, dict] = {}
    for cat in sorted(set(categories.tolist())):
        sel = categories == cat
        row: dict = {"n": int(sel.sum())}
        for m in names:
            row[m] = float(values[m][sel].mean()) * (scale if m in scaled else 1.0)
        table[cat] = row
    mean = {
        m: float(np.mean([row[m] for row in table.values()])) if table else float("nan")
        for m in names
    }
    return {"categories": table, "mean": mean}


def fidelity(inputs, completions) -> np.ndarray:
    """KITTI's Fidelity of each completion: the mean squared distance from each input point to
    its nearest completion point (PoinTr ``KITTI_metric.py``: ``ChamferDistanceL2_split``'s
    first term, input → completion), raw units (papers report it ×1000).

    Args:
        inputs: The partial inputs, ``(B, N, 3)`` or a list of ``(N_i, 3)`` arrays.
        completions: The completions, ``(B, M, 3)`` or a list of ``(M_i, 3)`` arrays.

    Returns:
        float64 ``(B,)``.
    """
    return sample_metrics(completions, inputs)["gt_to_pred"]


def minimal_matching_distance(completions, references) -> tuple[np.ndarray, np.ndarray]:
    """KITTI's MMD terms: for each completion, the smallest CD-L2 (``mean_C d(c, R)² +
    mean_R d(r, C)²``, PoinTr's ``ChamferDistanceL2``) to any reference cloud (ShapeNet's
    cars), and which one. The MMD is the mean of the first array (×1000 in papers).

    Exact, as computing every pair (the same float64 value and the lowest index among equal
    distances), but a branch and bound in the Rust core (all cores): cheap lower bounds of
    each pair's distance (a distance grid of the completion, coarse samples of it) rule out
    most references without computing them; see ``rust/metrics.rs``.

    Args:
        completions: float32 ``(C, N, 3)``, or a list of ``(N_i, 3)`` arrays (sizes may
            differ; every reference's KD-tree is still built once).
        references: float32 ``(R, M, 3)``.

    Returns:
        float64 ``(C,)`` distances and int64 ``(C,)`` reference indices.
    """
    from pfnet._core import minimal_matching

    refs = np.ascontiguousarray(references, dtype=np.float32)
    if refs.ndim != 3 or refs.shape[2] != 3:
        raise ValueError(f"references must be a (B, N, 3) array, got shape {refs.shape}")
    if isinstance(completions, np.ndarray):
        comps = np.ascontiguousarray(completions, dtype=np.float32)
        if comps.ndim != 3 or comps.shape[2] != 3:
            raise ValueError(f"completions must be a (B, N, 3) array, got shape {comps.shape}")
        counts = [comps.shape[1]] * comps.shape[0]
        points = comps.reshape(-1, 3)
    else:
        clouds = [np.asarray(c, dtype=np.float32) for c in completions]
        for k, cloud in enumerate(clouds):
            if cloud.ndim != 2 or cloud.shape[1] != 3:
                raise ValueError(f"completions[{k}] must be an (N, 3) array, got {cloud.shape}")
        counts = [len(c) for c in clouds]
        points = np.ascontiguousarray(
            np.concatenate(clouds) if clouds else np.zeros((0, 3)), dtype=np.float32
        )
    return minimal_matching(points, counts, refs)
