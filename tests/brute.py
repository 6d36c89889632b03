"""Shared by the benchmark-protocol tests: an independent nearest-neighbour computation, and
the marker for tests that run a model."""

from __future__ import annotations

import importlib.util

import numpy as np
import pytest

# predict runs the shipped model on PyTorch or, in the light install, ONNX Runtime.
needs_runtime = pytest.mark.skipif(
    not any(importlib.util.find_spec(m) for m in ("torch", "onnxruntime")),
    reason="predict needs PyTorch or ONNX Runtime",
)


def nearest_distances(queries: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Euclidean distance from each query to its nearest point, by brute force in float64."""
    q, p = np.asarray(queries, np.float64), np.asarray(points, np.float64)
    out = np.empty(len(q))
    for start in range(0, len(q), 512):  # at most 512 × len(p) distances at a time
        block = q[start : start + 512]
        out[start : start + 512] = np.sqrt(((block[:, None] - p[None]) ** 2).sum(-1).min(1))
    return out
