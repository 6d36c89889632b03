"""Shared by the benchmark-protocol tests: an independent nearest-neighbour computation, the
marker for tests that run a model, and binary PCD files as the benchmarks' releases hold them."""

from __future__ import annotations

import importlib.util
from pathlib import Path

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


def write_pcd(path: Path, points: np.ndarray) -> None:
    """A binary PCD as Open3D writes PCN's and KITTI's files."""
    points = np.asarray(points, np.float32)
    header = (
        "# .PCD v0.7 - Point Cloud Data file format\nVERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\n"
        f"TYPE F F F\nCOUNT 1 1 1\nWIDTH {len(points)}\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\n"
        f"POINTS {len(points)}\nDATA binary\n"
    )
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(header.encode() + points.tobytes())


def naive_fps(points: np.ndarray, n: int) -> np.ndarray:
    """Farthest point sampling from point 0, one numpy pass a sample (lowest index on ties)."""
    chosen = [0]
    dist = ((points - points[0]) ** 2).sum(axis=1)
    for _ in range(n - 1):
        nxt = int(np.argmax(dist))
        chosen.append(nxt)
        dist = np.minimum(dist, ((points - points[nxt]) ** 2).sum(axis=1))
    return points[chosen]


def capture_panels(monkeypatch) -> list:
    """Record the rows every gallery draws (then draw them as usual)."""
    import pfnet.rendering

    drawn: list = []
    original = pfnet.rendering.render_panels

    def recording(out, rows, **kwargs):
        drawn.append(rows)
        return original(out, rows, **kwargs)

    monkeypatch.setattr(pfnet.rendering, "render_panels", recording)
    return drawn
