"""Batches for training: which samples go together (:class:`EpochBatches`) and how they are
stacked, with the IFPS index sets the encoders and losses need (:class:`CompletionCollate`).

Both run where the data-loader puts them: the sampler in the training process, the collate
function in the workers, so the Rust sampling overlaps the training step.
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from typing import Any

import numpy as np
import torch
from torch.utils.data import BatchSampler, DistributedSampler, Sampler

from pfnet.geometry import farthest_point_sample
from pfnet.models.layers import multi_resolution_indices
from pfnet.models.pfnet import PRIMARY_POINTS, SECONDARY_POINTS


class CompletionCollate:
    """Stacks dataset items and adds the IFPS index sets the losses and encoders need.

    Runs in data-loader workers, so the Rust sampling overlaps the training step.

    Args:
        multi_resolution: Add ``scale_indices`` (``(B, n // 2)`` IFPS of the partial cloud).
        centre_targets: Add ``secondary_target`` (``(B, 128, 3)`` IFPS of the missing points)
            and ``primary_target`` (its first 64 points, which are the 64-point IFPS).
    """

    def __init__(self, multi_resolution: bool, centre_targets: bool) -> None:
        self.multi_resolution = multi_resolution
        self.centre_targets = centre_targets

    def __call__(self, items: list[dict[str, Any]]) -> dict[str, Any]:
        """Collate a list of ``CompletionDataset`` items into a batch dict."""
        batch: dict[str, Any] = {
            key: torch.stack([item[key] for item in items])
            for key in ("partial", "missing", "complete", "frame_radius")
        }
        batch["category"] = [item["category"] for item in items]
        batch["index"] = torch.tensor([int(item["index"]) for item in items])
        if self.multi_resolution:
            batch["scale_indices"] = torch.from_numpy(
                multi_resolution_indices(batch["partial"].numpy())
            )
        if self.centre_targets:
            missing = batch["missing"]
            index = torch.from_numpy(
                np.asarray(farthest_point_sample(missing.numpy(), SECONDARY_POINTS), np.int64)
            )
            secondary = torch.gather(missing, 1, index.unsqueeze(-1).expand(-1, -1, 3))
            batch["secondary_target"] = secondary
            batch["primary_target"] = secondary[:, :PRIMARY_POINTS].contiguous()
        return batch


class EpochBatches(Sampler[list[tuple[int, int]]]):
    """Batches of ``(epoch, index)`` keys of one epoch, optionally without its first batches.

    The epoch travels with every index because the data-loader workers live across epochs
    and keep the dataset object they started with; ``skip`` leaves out the batches already
    trained before a mid-epoch stop.

    Args:
        sampler: Shuffles (and, under DDP, shards) the indices; reseeded per epoch.
        batch_size: Clouds per batch (the last batch may be smaller).
    """

    def __init__(self, sampler: DistributedSampler, batch_size: int) -> None:
        self.sampler = sampler
        self.batch_size = batch_size
        self.epoch = 0
        self.skip = 0

    def set_epoch(self, epoch: int, skip: int = 0) -> None:
        """Serve ``epoch``, leaving out its first ``skip`` batches."""
        self.epoch = epoch
        self.skip = skip
        self.sampler.set_epoch(epoch)

    def __iter__(self) -> Iterator[list[tuple[int, int]]]:
        batches = BatchSampler(self.sampler, self.batch_size, drop_last=False)
        for i, batch in enumerate(batches):
            if i >= self.skip:
                yield [(self.epoch, index) for index in batch]

    @property
    def per_epoch(self) -> int:
        """Batches in a whole epoch."""
        return math.ceil(len(self.sampler) / self.batch_size)

    def __len__(self) -> int:
        return max(0, self.per_epoch - self.skip)
