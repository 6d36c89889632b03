"""Shared by the tests: independent nearest-neighbour computations (the core's rule by brute
force, and Euclidean distances), clouds far from a tilted plane or line, the marker for tests
that run a model, and binary PCD files as the benchmarks' releases hold them."""

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


def nearest_naive(query: np.ndarray, reference: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The core's nearest neighbours by brute force: for each query the reference point with the
    smallest float64 squared distance ``dx*dx + dy*dy + dz*dz`` from the float32 coordinates, the
    lowest index among equal ones; ``(that distance rounded to float32, int64 index)``."""
    q = np.asarray(query, np.float32).astype(np.float64)
    r = np.asarray(reference, np.float32).astype(np.float64)
    sq_dist, index = np.empty(len(q), np.float32), np.empty(len(q), np.int64)
    for start in range(0, len(q), 64):  # at most 64 × len(r) distances at a time
        diff = q[start : start + 64, None, :] - r[None, :, :]
        d = diff[..., 0] * diff[..., 0] + diff[..., 1] * diff[..., 1] + diff[..., 2] * diff[..., 2]
        best = d.argmin(axis=1)  # the first of equal minima
        index[start : start + 64] = best
        sq_dist[start : start + 64] = d[np.arange(len(d)), best]
    return sq_dist, index


def far_from_tilted(
    shape: str, n: int, heights: list[float], seed: int = 0
) -> tuple[np.ndarray, np.ndarray]:
    """``(query, reference)``: ``n`` points on a tilted unit patch of a plane (``shape`` =
    "plane") or on a tilted unit segment ("line"), and ``n`` queries at the given heights
    (cycled; negative below) above points of it. Every point near a far query's foot ties with
    the nearest in float32 (audit K1)."""
    rng = np.random.default_rng(seed)
    if shape == "plane":
        a, b = rng.random(n), rng.random(n)
        reference = np.c_[a, b, 0.3 * a + 0.7 * b]
        fa, fb = rng.random(n), rng.random(n)
        feet = np.c_[fa, fb, 0.3 * fa + 0.7 * fb]
        away = np.broadcast_to(np.array([0.3, 0.7, -1.0]) / np.sqrt(1.58), (n, 3))
    else:
        direction = np.array([1.0, 0.6, 0.3]) / np.sqrt(1.45)
        reference = rng.random((n, 1)) * direction
        feet = rng.random((n, 1)) * direction
        away = rng.normal(size=(n, 3))
        away -= (away @ direction)[:, None] * direction
        away /= np.linalg.norm(away, axis=1, keepdims=True)
    h = np.resize(np.asarray(heights, np.float64), n)[:, None]
    return (feet + h * away).astype(np.float32), reference.astype(np.float32)


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
    import pfnet.viz.rendering

    drawn: list = []
    original = pfnet.viz.rendering.render_panels

    def recording(out, rows, **kwargs):
        drawn.append(rows)
        return original(out, rows, **kwargs)

    monkeypatch.setattr(pfnet.viz.rendering, "render_panels", recording)
    return drawn
