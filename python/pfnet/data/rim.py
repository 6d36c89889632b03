"""The cut's rim, found in numpy: where a partial cloud's points have their neighbours on one
side only (issue 34; no torch, so that the light install's ``pfnet complete`` can use it).

A viewpoint crop removes a ball of the surface; the points that remain around its edge have
their nearest neighbours on the far side only. The **edge score** of a point (the same as
:func:`pfnet.models.edge.edge_scores`, which the ``pfnet-edge`` network computes in torch): the
distance from it to the centroid of its :data:`NEIGHBOURS` nearest points over their mean
distance from it, in [0, 1] (0 inside an evenly sampled surface, about 0.5 on the rim of a
half-disc). **The rim** is the :data:`RIM_SHARE` of the points with the highest scores; on
SweetHome3D's five-view test cuts their centroid lies on the hole's side of the partial's in
87 % of the cuts (``benchmarks/edge_probe.py``). The ``aligned-rim`` and ``rim`` frames
(:func:`pfnet.data.scan_frame.frame_of`) turn the rim's side to +x.
"""

from __future__ import annotations

import numpy as np

__all__ = ["NEIGHBOURS", "RIM_POINTS", "RIM_SHARE", "edge_scores", "rim_centroid"]

NEIGHBOURS = 32
"""The nearest points of each point its edge score compares it with (``pfnet-edge``'s)."""

RIM_SHARE = 0.1
"""The share of a partial's points, highest edge scores first, that make its rim."""

RIM_POINTS = 2048
"""A larger cloud's rim is found on this many of its points (farthest point sampling): the
scores cost ``n²`` distances, and a scan of 10⁵ points has the same rim at a coarser step."""

_ROWS = 1024  # distance rows computed at a time (a 1024 x 2048 float64 block is 16 MB)


def edge_scores(points: np.ndarray, neighbours: int = NEIGHBOURS) -> np.ndarray:
    """The edge score of every point of an ``(n, 3)`` cloud -> float64 ``(n,)`` in [0, 1].

    ``|mean(q) - p| / mean(|q - p|)`` over the ``neighbours`` nearest points ``q`` of ``p``
    (itself left out; the nearest of fewer when the cloud has fewer points; 0 for a cloud of
    one point).
    """
    p = np.asarray(points, np.float64)
    n = len(p)
    k = min(neighbours, n - 1)
    if k < 1:
        return np.zeros(n)
    squared = (p * p).sum(axis=1)
    scores = np.empty(n)
    for start in range(0, n, _ROWS):
        rows = p[start : start + _ROWS]
        d2 = squared[start : start + _ROWS, None] + squared[None, :] - 2.0 * rows @ p.T
        index = np.argpartition(d2, k, axis=1)[:, : k + 1]
        near2 = np.take_along_axis(d2, index, axis=1)
        order = np.argsort(near2, axis=1, kind="stable")
        # the nearest is the point itself (or a duplicate of it: distance 0 either way)
        index = np.take_along_axis(index, order, axis=1)[:, 1:]
        distance = np.sqrt(np.clip(np.take_along_axis(near2, order, axis=1)[:, 1:], 0.0, None))
        offset = np.linalg.norm(p[index].mean(axis=1) - rows, axis=1)
        scores[start : start + _ROWS] = offset / np.maximum(distance.mean(axis=1), 1e-12)
    return np.minimum(scores, 1.0)


def rim_centroid(points: np.ndarray) -> np.ndarray:
    """The centroid ``(3,)`` (float64) of the :data:`RIM_SHARE` of ``points`` with the highest
    edge scores (of a :data:`RIM_POINTS`-point farthest point sample of a larger cloud); the
    cloud's centroid when it has fewer than two points."""
    p = np.asarray(points, np.float64)
    if len(p) < 2:
        return p.mean(axis=0) if len(p) else np.zeros(3)
    if len(p) > RIM_POINTS:
        from pfnet.geometry import farthest_point_sample

        p = p[farthest_point_sample(p.astype(np.float32), RIM_POINTS)]
    scores = edge_scores(p)
    count = max(1, int(round(RIM_SHARE * len(p))))
    top = np.argsort(-scores, kind="stable")[:count]
    return p[top].mean(axis=0)
