"""The heading reader's network, for training: a PointNet over a partial cloud's points that
scores the bins of its turn about the up axis (:mod:`pfnet.data.heading` runs it in NumPy).

Not part of PF-Net: a separate step in front of a network trained with the heading known
(the ``heading`` frame, docs/scan-protocol.md).
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import torch
from torch import Tensor, nn

from pfnet.data.heading import FORMAT, VERSION

POINT_WIDTHS = (64, 128, 256, 512)
HEAD_WIDTHS = (256,)
BINS = 36
POINTS = 512


class HeadingNet(nn.Module):
    """Shared per-point layers (1×1 convolutions, batch norm, ReLU), a max pool, then a
    small MLP to ``bins`` scores.

    Args:
        bins: Bins over the full turn (36: 10° each).
        point_widths: Widths of the per-point layers.
        head_widths: Widths of the hidden layers after the pool.
    """

    def __init__(
        self,
        bins: int = BINS,
        point_widths: tuple[int, ...] = POINT_WIDTHS,
        head_widths: tuple[int, ...] = HEAD_WIDTHS,
    ) -> None:
        super().__init__()
        self.bins = bins
        layers: list[nn.Module] = []
        width = 3
        for out in point_widths:
            layers += [nn.Conv1d(width, out, 1), nn.BatchNorm1d(out), nn.ReLU()]
            width = out
        self.points = nn.Sequential(*layers)
        head: list[nn.Module] = []
        for out in head_widths:
            head += [nn.Linear(width, out), nn.BatchNorm1d(out), nn.ReLU()]
            width = out
        head.append(nn.Linear(width, bins))
        self.head = nn.Sequential(*head)

    def forward(self, samples: Tensor) -> Tensor:
        """``(B, P, 3)`` points -> ``(B, bins)`` scores."""
        return self.head(self.points(samples.transpose(1, 2)).max(dim=2).values)


def soft_targets(angles: np.ndarray, bins: int = BINS) -> np.ndarray:
    """``(B, bins)`` training targets: a wrapped Gaussian of one bin's width about each angle
    (a near miss costs less than a far one)."""
    centres = (np.arange(bins) + 0.5) * (2 * math.pi / bins)
    gap = np.angle(np.exp(1j * (centres[None, :] - np.asarray(angles)[:, None])))
    weights = np.exp(-0.5 * (gap / (2 * math.pi / bins)) ** 2)
    return (weights / weights.sum(axis=1, keepdims=True)).astype(np.float32)


def _folded(layer: nn.Module, norm: nn.BatchNorm1d) -> tuple[np.ndarray, np.ndarray]:
    """A linear layer (or 1×1 convolution) followed by batch norm in eval mode, as one."""
    weight = layer.weight.detach().double().reshape(layer.weight.shape[0], -1)
    bias = layer.bias.detach().double()
    scale = norm.weight.detach().double() / torch.sqrt(norm.running_var.double() + norm.eps)
    folded_bias = (bias - norm.running_mean.double()) * scale + norm.bias.detach().double()
    return (
        (weight * scale[:, None]).float().numpy(),
        folded_bias.float().numpy(),
    )


def reader_tensors(net: HeadingNet) -> dict[str, np.ndarray]:
    """The tensors of a heading reader file: every layer with its batch norm folded in."""
    tensors = {}
    convs = [m for m in net.points if isinstance(m, nn.Conv1d)]
    norms = [m for m in net.points if isinstance(m, nn.BatchNorm1d)]
    for k, (conv, norm) in enumerate(zip(convs, norms, strict=True)):
        tensors[f"point.{k}.weight"], tensors[f"point.{k}.bias"] = _folded(conv, norm)
    linears = [m for m in net.head if isinstance(m, nn.Linear)]
    head_norms = [m for m in net.head if isinstance(m, nn.BatchNorm1d)]
    for k, (linear, norm) in enumerate(zip(linears[:-1], head_norms, strict=True)):
        tensors[f"head.{k}.weight"], tensors[f"head.{k}.bias"] = _folded(linear, norm)
    last = linears[-1]
    k = len(linears) - 1
    tensors[f"head.{k}.weight"] = last.weight.detach().float().numpy().copy()
    tensors[f"head.{k}.bias"] = last.bias.detach().float().numpy().copy()
    return tensors


def save_reader(net: HeadingNet, path: str | Path, *, points: int = POINTS, card: dict) -> Path:
    """Write ``net`` as a heading reader file (atomically), its ``card`` in the header."""
    from safetensors.numpy import save_file

    from pfnet.io.files import atomic_path

    tensors = reader_tensors(net)
    metadata = {
        "format": FORMAT,
        "version": VERSION,
        "bins": str(net.bins),
        "points": str(points),
        "point_layers": str(sum(1 for k in tensors if k.startswith("point.")) // 2),
        "head_layers": str(sum(1 for k in tensors if k.startswith("head.")) // 2),
        "card": json.dumps(card),
    }
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(path) as partial:
        save_file(tensors, str(partial), metadata=metadata)
    return path
