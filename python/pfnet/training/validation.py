"""Validation during training: the val split cropped with the deterministic test protocol,
scored by the metric functions ``pfnet evaluate`` uses (:mod:`pfnet.evaluation.metrics`),
each rank's share gathered under DDP so that every rank gets the same figures."""

from __future__ import annotations

from collections.abc import Callable
from contextlib import AbstractContextManager
from typing import Any

import numpy as np
import torch
from torch.utils.data import DataLoader, Dataset, Subset

from pfnet.training import distributed
from pfnet.training.batches import CompletionCollate
from pfnet.training.distributed import DistContext


def validation_batches(
    val_set: Dataset, context: DistContext, batch_size: int, multi_resolution: bool
) -> list[dict[str, Any]]:
    """This rank's share of ``val_set`` in batches (every ``world_size``-th sample), built
    once by the caller: the test protocol's crops do not change between epochs."""
    shard = Subset(val_set, range(context.rank, len(val_set), context.world_size))
    loader = DataLoader(
        shard,
        batch_size=batch_size,
        num_workers=0,
        collate_fn=CompletionCollate(multi_resolution, centre_targets=False),
    )
    return list(loader)


@torch.no_grad()
def score_generator(
    network: torch.nn.Module,
    batches: list[dict[str, Any]],
    device: torch.device | str,
    autocast: Callable[[], AbstractContextManager],
    context: DistContext,
    prefix: str,
) -> dict[str, float]:
    """The mean over categories of each metric of ``network``'s completions of ``batches``,
    over every rank's batches, keyed ``<prefix><metric>`` (the squared-distance terms ×1000,
    as :func:`pfnet.evaluation.metrics.summarize` gives them); empty when no rank has a sample. The
    network is put in eval mode for the pass and restored after."""
    from pfnet.evaluation.metrics import sample_metrics, summarize

    was_training = network.training
    network.eval()
    rows: list[tuple[int, str, dict[str, float]]] = []
    for batch in batches:
        partial = batch["partial"].to(device)
        with autocast():
            detail = network(partial, batch.get("scale_indices")).detail
        # scored in the data set's units: a scan-frame sample was divided by its own radius
        radius = batch["frame_radius"].numpy().astype(np.float64)[:, None, None]
        metrics = sample_metrics(
            detail.float().cpu().numpy() * radius, batch["missing"].numpy() * radius
        )
        for j, index in enumerate(batch["index"].tolist()):
            values = {k: float(v[j]) for k, v in metrics.items()}
            rows.append((index, batch["category"][j], values))
    network.train(was_training)
    gathered = distributed.all_gather_objects(rows, context)
    rows = sorted((r for part in gathered for r in part), key=lambda r: r[0])
    if not rows:
        return {}
    per_sample = {k: np.array([r[2][k] for r in rows]) for k in rows[0][2]}
    summary = summarize(per_sample, [r[1] for r in rows])["mean"]
    return {f"{prefix}{k}": float(v) for k, v in summary.items() if k != "n"}
