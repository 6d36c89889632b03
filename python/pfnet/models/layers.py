"""Building blocks shared by PF-Net, its discriminator and the baselines."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor, nn

from pfnet.geometry import farthest_point_sample


def scaled(channels: int, width: float, minimum: int = 4) -> int:
    """The number of channels of a layer in a network ``width`` times as wide as the paper's."""
    return max(minimum, round(channels * width))


def check_partial(partial: Tensor, min_points: int = 1) -> None:
    """Raise ``ValueError`` unless ``partial`` is a float ``(B, n, 3)`` tensor, n >= min_points."""
    if partial.ndim != 3 or partial.shape[2] != 3:
        raise ValueError(f"partial must have shape (B, n, 3); got {tuple(partial.shape)}")
    if not partial.is_floating_point():
        raise ValueError(f"partial must be a float tensor; got {partial.dtype}")
    if partial.shape[0] < 1 or partial.shape[1] < min_points:
        raise ValueError(
            f"partial must hold at least one cloud of at least {min_points} points; "
            f"got shape {tuple(partial.shape)}"
        )


class BatchNormFC(nn.BatchNorm1d):
    """``BatchNorm1d`` for fully connected features ``(B, C)`` that accepts a batch of one.

    In training mode a batch of one has no variance across the batch, and ``nn.BatchNorm1d``
    raises (the authors' training crashes on such a last batch). Here a batch of one is
    normalised with the running statistics instead, and does not update them.
    """

    def forward(self, x: Tensor) -> Tensor:
        if self.training and x.shape[0] == 1:
            return F.batch_norm(
                x, self.running_mean, self.running_var, self.weight, self.bias, False, 0.0, self.eps
            )
        return super().forward(x)


class PointMLP(nn.Module):
    """A shared per-point MLP: Conv1d (kernel 1) + BatchNorm + ReLU per layer.

    Args:
        channels: Output channels of each layer, e.g. ``(64, 64, 128, 256, 512, 1024)``.
        in_channels: Channels of each input point (3 for xyz).
    """

    def __init__(self, channels: Sequence[int], in_channels: int = 3) -> None:
        super().__init__()
        layers = []
        for out in channels:
            layers.append(
                nn.Sequential(nn.Conv1d(in_channels, out, 1), nn.BatchNorm1d(out), nn.ReLU())
            )
            in_channels = out
        self.layers = nn.ModuleList(layers)

    def forward(self, points: Tensor) -> list[Tensor]:
        """Features of every layer.

        Args:
            points: ``(B, n, 3)`` points.

        Returns:
            One ``(B, C_l, n)`` tensor per layer.
        """
        x = points.transpose(1, 2)
        outputs = []
        for layer in self.layers:
            x = layer(x)
            outputs.append(x)
        return outputs


def fc_block(in_features: int, out_features: int) -> nn.Sequential:
    """Linear + BatchNorm (batch-of-one safe) + ReLU."""
    return nn.Sequential(nn.Linear(in_features, out_features), BatchNormFC(out_features), nn.ReLU())


def multi_resolution_indices(partial: np.ndarray | Tensor, n_scales: int = 3) -> np.ndarray:
    """Indices of the IFPS subsets that form the coarser scales of the multi-resolution input.

    Scale ``s`` (``s = 1 .. n_scales - 1``) of a cloud of n points is its first
    ``n // 2**s`` farthest points (k = 2 in the paper). IFPS from a fixed start is greedy, so
    the first ``n // 4`` of an ``n // 2`` sample *are* the ``n // 4`` sample: one call to the
    Rust sampler serves every scale, and the caller slices prefixes.

    Args:
        partial: ``(B, n, 3)`` partial clouds (numpy or a CPU/GPU tensor; copied to the CPU).
        n_scales: Number of scales including the full-resolution one.

    Returns:
        int64 ``(B, n // 2)`` indices into the n points (``(B, 0)`` when ``n_scales == 1``).
    """
    if isinstance(partial, Tensor):
        partial = partial.detach().to("cpu", torch.float32).numpy()
    batch, n = partial.shape[:2]
    if n_scales <= 1:
        return np.zeros((batch, 0), dtype=np.int64)
    if n // 2 ** (n_scales - 1) < 1:
        raise ValueError(
            f"partial clouds of {n} points are too small for {n_scales} resolutions "
            f"(need at least {2 ** (n_scales - 1)} points)"
        )
    return np.asarray(farthest_point_sample(partial, n // 2), dtype=np.int64)


def gather_points(points: Tensor, index: Tensor) -> Tensor:
    """``points[b, index[b, j]]``: ``(B, n, 3)`` and ``(B, k)`` -> ``(B, k, 3)``."""
    return torch.gather(points, 1, index.unsqueeze(-1).expand(-1, -1, points.shape[-1]))
