"""PF-Net + mirror + edge: :mod:`pfnet.models.mirror`'s network whose encoder also reads, for
each point of the partial, how much it lies on the edge of the cut (issue 34). Not the paper's
network.

On the scan protocol the test error is a few scans whose completion goes to the wrong end of
the partial (docs/scan-protocol.md): nothing in a frame fixed by the partial's own points says
which side the hole is on, and PF-Net's encoder (a shared per-point MLP, max-pooled) cannot
see a point's neighbourhood. But a cut leaves a rim: where the viewpoint's ball took the
surface away, the points that remain have their neighbours on one side only. On the 270
five-view test cuts of SweetHome3D the tenth of the points with the highest edge score lie
among the tenth nearest the hole 2.8 times as often as chance, and their centroid lies on
the hole's side of the partial's in 87 % of the cuts (the frame's sign rules manage 62–69 %).

**The edge score** of a point (:func:`edge_scores`): the distance from it to the centroid of
its :data:`NEIGHBOURS` nearest points, over their mean distance from it. It is dimensionless,
in [0, 1]: near 0 inside a surface sampled evenly, about 0.5 on the rim of a half-disc. It is
computed once per forward pass, without gradients, on the whole partial (the encoder's
``_context`` hook of :class:`pfnet.models.mirror.MirrorEncoder`), so every path that runs a
generator gets it; each scale's points take their own scores.

**Input.** :class:`pfnet.models.mirror.MirrorEncoder`'s six channels and a seventh: the
point's edge score, 0 on the mirror images. :meth:`PFNetEdge.grow_from` starts it from a
trained PF-Net + mirror (or PF-Net) generator with zero weights on the new channel, so that
it begins as the network it grows from.
"""

from __future__ import annotations

from typing import ClassVar

import torch
from torch import Tensor

from pfnet.models.layers import gather_points
from pfnet.models.mirror import IN_CHANNELS as MIRROR_CHANNELS
from pfnet.models.mirror import MirrorEncoder, PFNetMirror

NEIGHBOURS = 32  # of each point, for its edge score
IN_CHANNELS = MIRROR_CHANNELS + 1  # the mirror model's six and the edge score


def edge_scores(points: Tensor, neighbours: int = NEIGHBOURS) -> Tensor:
    """The edge score of every point of ``(B, n, 3)`` clouds -> ``(B, n)`` in [0, 1].

    ``|mean(q) - p| / mean(|q - p|)`` over the ``neighbours`` nearest points ``q`` of ``p``
    (itself left out; the nearest of fewer when the cloud has fewer points).
    """
    k = min(neighbours, points.shape[1] - 1)
    if k < 1:
        return points[..., 0] * 0
    squared = (points * points).sum(dim=-1)
    distance2 = squared.unsqueeze(2) + squared.unsqueeze(1) - 2.0 * points @ points.transpose(1, 2)
    nearest2, index = torch.topk(distance2, k + 1, dim=2, largest=False)
    # the first is the point itself (or a duplicate of it: distance 0 either way)
    index = index[:, :, 1 : k + 1]
    distance = nearest2[:, :, 1 : k + 1].clamp(min=0.0).sqrt()
    found = gather_points(points, index.reshape(points.shape[0], -1))
    found = found.reshape(points.shape[0], points.shape[1], k, 3)
    offset = (found.mean(dim=2) - points).norm(dim=-1)
    return (offset / distance.mean(dim=-1).clamp(min=1e-12)).clamp(max=1.0)


class EdgeEncoder(MirrorEncoder):
    """:class:`pfnet.models.mirror.MirrorEncoder` whose points also carry their edge score.

    Args:
        width: Multiplier of every layer's channels.
    """

    def __init__(self, width: float = 1.0) -> None:
        super().__init__(width, IN_CHANNELS)

    def _context(self, partial: Tensor) -> Tensor:
        return edge_scores(partial)

    def _extended(self, features: Tensor, context: Tensor | None, index: Tensor | None) -> Tensor:
        """The edge score of each point as a seventh channel, 0 on the mirror images that
        follow the points."""
        if context is None:
            return features
        edge = context if index is None else torch.gather(context, 1, index)
        # the slice's end written out: an open end is an int64 2**63 - 1 the ONNX check refuses
        images = features[:, edge.shape[1] : features.shape[1], 0] * 0
        column = torch.cat([edge, images], dim=1).unsqueeze(-1)
        return torch.cat([features, column], dim=2)


class PFNetEdge(PFNetMirror):
    """PF-Net + mirror whose encoder also reads each point's edge score (:class:`EdgeEncoder`);
    the decoder and the loss are PF-Net's.

    Args:
        n_points: Size N of the complete clouds the model is trained for.
        n_missing: M, the number of points it predicts (a multiple of 128).
        width: Multiplier of every hidden layer.
    """

    grows_from: ClassVar[tuple[str, ...]] = ("pfnet", "pfnet-vanilla", "pfnet-mirror")

    @staticmethod
    def _encoder(width: float) -> MirrorEncoder:
        return EdgeEncoder(width)
