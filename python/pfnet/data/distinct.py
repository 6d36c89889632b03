"""Distinct shapes: identical geometry stored once, near-copies kept in one split.

Real model collections repeat themselves: FlightGear ships a livery as a copy of its mesh
with another texture name (``Cessna172_blue.ac``, ``Cessna172_red.ac``...), and an airliner
family's meshes differ by a few faces. A data set that put one copy in ``train`` and another in
``test`` would score memory, not completion. :func:`prepare_dataset` with ``distinct`` does:

1. **Identical geometry once.** Each mesh's digest (:func:`geometry_digest`: a hash of its
   used vertices, rounded and sorted, so the order of the file and its textures do not
   matter) is computed in the worker; of the shapes sharing a digest the one with the
   smallest key is kept, the others are counted as merged, by category.
2. **Near-copies in one split.** Two shapes (of any categories) are near-copies when the Chamfer
   distance between their clouds is within :data:`NEAR_COPY_RATIO` times what two independent
   samples of one surface are from each other (:func:`near_copy_groups`; both measured on
   :data:`NEAR_POINTS` points of the normalised shapes). Near-copies form groups (connected
   components); a group's shapes are all kept and all go to the split drawn for the group.

The Chamfer distance here is the symmetric one, ``pred→gt + gt→pred`` of
:func:`pfnet.geometry.chamfer` (means of squared distances, unit-ball units).
"""

from __future__ import annotations

import hashlib

import numpy as np

__all__ = [
    "NEAR_COPY_RATIO",
    "NEAR_POINTS",
    "geometry_digest",
    "near_copy_groups",
    "self_distance",
    "symmetric_chamfer",
]

NEAR_POINTS = 2048
"""Points per shape on which near-copies are compared (the first of each cloud; a uniform
sample, since the cloud is one)."""

NEAR_COPY_RATIO = 1.5
"""Two shapes are near-copies when their Chamfer distance is at most this many times the mean
of their self-distances (two independent samples of one surface). Measured on the open-shapes
corpus (``benchmarks/open_shapes_check.py``): for pairs of identical meshes sampled
independently, the ratio has median 1.0 and its 99.9th percentile below 1.5."""

# extents (sorted box sides of the normalised cloud) further apart than this never hold a
# near-copy: comparing them would only cost time (the check in benchmarks/ compares all)
_EXTENT_GAP = 0.1


def geometry_digest(vertices: np.ndarray, faces: np.ndarray | None) -> str:
    """A hash of a shape's geometry: its used vertices, rounded to 1e-5 of its size, sorted.

    Liveries and re-textured copies of one mesh have the same digest; the order of the
    vertices in the file does not change it.
    """
    used = vertices if faces is None or len(faces) == 0 else vertices[np.unique(faces)]
    used = np.asarray(used, dtype=np.float64)
    size = float(np.ptp(used, axis=0).max()) if len(used) else 0.0
    quantum = size * 1e-5 if size > 0 else 1.0
    grid = np.round((used - used.min(axis=0)) / quantum).astype(np.int64)
    grid = np.unique(grid, axis=0)  # sorted rows, duplicates gone
    return hashlib.blake2b(grid.tobytes(), digest_size=16).hexdigest()


def symmetric_chamfer(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``pred→gt + gt→pred`` Chamfer distances of batched clouds ``(B, N, 3)``."""
    from pfnet.geometry import chamfer

    forward, backward = chamfer(
        np.ascontiguousarray(a, dtype=np.float32), np.ascontiguousarray(b, dtype=np.float32)
    )
    return np.asarray(forward) + np.asarray(backward)


def self_distance(first: np.ndarray, second: np.ndarray) -> float:
    """The symmetric Chamfer distance between two independent samples of one surface."""
    return float(symmetric_chamfer(first[None], second[None])[0])


def _extents(clouds: np.ndarray) -> np.ndarray:
    return np.sort(clouds.max(axis=1) - clouds.min(axis=1), axis=1)


def near_copy_groups(
    clouds: np.ndarray,
    self_distances: np.ndarray,
    ratio: float = NEAR_COPY_RATIO,
    batch: int = 4096,
) -> tuple[np.ndarray, list[tuple[int, int, float]]]:
    """Group near-copies, whatever their categories (a storage tank filed under ``building``
    in one folder and ``other`` in another is still one shape).

    Args:
        clouds: ``(S, N, 3)`` normalised clouds (``N`` at least :data:`NEAR_POINTS`; the first
            :data:`NEAR_POINTS` are used).
        self_distances: ``(S,)`` each shape's self-distance on :data:`NEAR_POINTS` points.
        ratio: The near-copy threshold, in self-distances.
        batch: Pairs compared at once.

    Returns:
        ``(group, pairs)``: the group of each shape (the smallest index in its group) and the
        near-copy pairs found ``(i, j, distance / mean self-distance)``.
    """
    n = len(clouds)
    parent = np.arange(n)

    def find(i: int) -> int:
        while parent[i] != i:
            parent[i] = parent[parent[i]]
            i = parent[i]
        return i

    small = np.ascontiguousarray(clouds[:, :NEAR_POINTS], dtype=np.float32)
    extents = _extents(small)
    pairs: list[tuple[int, int, float]] = []
    for first in range(0, n, 512):  # rows of the pair matrix, a block at a time
        i, j = _pair_block(n, first, 512)
        close = np.abs(extents[i] - extents[j]).max(axis=1) <= _EXTENT_GAP
        i, j = i[close], j[close]
        for start in range(0, len(i), batch):
            a, b = i[start : start + batch], j[start : start + batch]
            distance = symmetric_chamfer(small[a], small[b])
            scale = 0.5 * (self_distances[a] + self_distances[b])
            found = distance <= ratio * scale
            for x, y, r in zip(a[found], b[found], (distance / scale)[found], strict=True):
                pairs.append((int(x), int(y), float(r)))
                rx, ry = find(int(x)), find(int(y))
                if rx != ry:
                    parent[max(rx, ry)] = min(rx, ry)
    return np.array([find(k) for k in range(n)]), pairs


def _pair_block(n: int, first: int, rows: int) -> tuple[np.ndarray, np.ndarray]:
    """The pairs ``(i, j)``, ``i < j``, of rows ``first .. first + rows``."""
    i = np.arange(first, min(first + rows, n))
    ii, jj = np.meshgrid(i, np.arange(n), indexing="ij")
    keep = jj > ii
    return ii[keep], jj[keep]
