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
from collections import Counter

import numpy as np

from pfnet.data.format import SPLITS
from pfnet.data.sampling import normalize, resample_points, sample_surface, shape_rng
from pfnet.data.sources import ShapeItem
from pfnet.data.splits import assign_splits

__all__ = [
    "NEAR_COPY_RATIO",
    "NEAR_POINTS",
    "distinct_sample",
    "distinct_summary",
    "geometry_digest",
    "near_copy_groups",
    "self_distance",
    "split_distinct",
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


def distinct_sample(geometry, item: ShapeItem, points: np.ndarray, n_points: int, seed: int):
    """The normalised points, "", the geometry's digest and its self-distance: the Chamfer
    distance between the cloud's first NEAR_POINTS points and as many more drawn from an
    independent stream, normalised alike."""
    second_rng = shape_rng(seed, f"{item.key}#second-sample")
    n_near = min(NEAR_POINTS, n_points)
    if geometry.faces is None:
        second = resample_points(geometry.vertices, n_near, second_rng, 0)
    else:
        second = sample_surface(geometry.vertices, geometry.faces, n_near, second_rng)
    both = normalize(np.concatenate([points, second]), n_points)
    cloud, second = both[: len(points)], both[len(points) :]
    digest = geometry_digest(geometry.vertices, geometry.faces)
    return cloud, "", digest, self_distance(cloud[:n_near], second)


def split_distinct(
    loaded: list[tuple[ShapeItem, np.ndarray, str, float]],
    kept: dict[str, list[tuple[ShapeItem, np.ndarray]]],
    has_splits: bool,
    seed: int,
    test_fraction: float,
    val_fraction: float,
    origins: dict[str, dict],
) -> tuple[dict[str, list[tuple[ShapeItem, np.ndarray]]], dict]:
    """Identical geometry once, near-copies in one split (:mod:`pfnet.data.distinct`).

    Returns:
        The kept shapes by split, and the record of what was merged and grouped.
    """
    if not loaded:  # not asked for (or nothing read): the shapes as they were split
        return kept, {}
    loaded = sorted(loaded, key=lambda entry: entry[0].key)
    first_of: dict[str, ShapeItem] = {}
    unique: list[tuple[ShapeItem, np.ndarray, float]] = []
    identical: dict[str, int] = {}
    merged_into: dict[str, list[str]] = {}
    for item, cloud, digest, self_dist in loaded:
        if digest in first_of:
            identical[item.category] = identical.get(item.category, 0) + 1
            merged_into.setdefault(first_of[digest].name, []).append(item.path)
            continue
        first_of[digest] = item
        unique.append((item, cloud, self_dist))
    clouds = np.stack([cloud[:NEAR_POINTS] for _, cloud, _ in unique])
    groups, pairs = near_copy_groups(
        clouds,
        np.array([d for *_, d in unique], dtype=np.float64),
    )
    roots = sorted(set(groups.tolist()))
    root_items = [unique[r][0] for r in roots]
    if has_splits:
        root_split = {r: unique[r][0].split or "train" for r in roots}
    else:
        drawn = assign_splits(root_items, seed, test_fraction, val_fraction)
        root_split = dict(zip(roots, drawn, strict=True))
    kept: dict[str, list[tuple[ShapeItem, np.ndarray]]] = {split: [] for split in SPLITS}
    for index, (item, cloud, _) in enumerate(unique):
        kept[root_split[int(groups[index])]].append((item, cloud))
    sizes = Counter(groups.tolist())
    grouped: dict[str, int] = {}
    grouped_shapes: dict[str, int] = {}
    for root, size in sizes.items():
        if size > 1:
            category = unique[root][0].category
            grouped[category] = grouped.get(category, 0) + 1
            grouped_shapes[category] = grouped_shapes.get(category, 0) + size
    by_source: dict[str, dict[str, int]] = {}
    for item, *_ in unique:
        source = origins.get(item.key, {}).get("source", "")
        counts = by_source.setdefault(source, {})
        counts[item.category] = counts.get(item.category, 0) + 1
    info = {
        "loaded": len(loaded),
        "distinct_meshes": len(unique),
        "identical_merged": dict(sorted(identical.items())),
        "near_copy_ratio": NEAR_COPY_RATIO,
        "near_copy_points": NEAR_POINTS,
        "near_copy_groups": dict(sorted(grouped.items())),
        "near_copy_shapes": dict(sorted(grouped_shapes.items())),
        "distinct_groups": dict(sorted(Counter(i.category for i in root_items).items())),
        "kept_by_source": {s: dict(sorted(c.items())) for s, c in sorted(by_source.items())},
        "merged_into": dict(sorted(merged_into.items())),
        "near_copies": [
            [unique[i][0].name, unique[j][0].name, round(r, 3)] for i, j, r in sorted(pairs)
        ],
    }
    return kept, info


def distinct_summary(info: dict) -> list[str]:
    """The summary lines of the distinct step."""
    if not info:
        return []
    lines = [
        f"distinct: {info['distinct_meshes']} meshes of {info['loaded']} read; identical "
        f"geometry merged: {sum(info['identical_merged'].values())}"
    ]
    if info["identical_merged"]:
        lines.append(
            "  merged by category: "
            + ", ".join(f"{c} {n}" for c, n in info["identical_merged"].items())
        )
    if info["near_copy_groups"]:
        lines.append(
            f"  near-copies (Chamfer within {info['near_copy_ratio']}x two samples of one "
            "surface), kept in one split: "
            + ", ".join(
                f"{c} {info['near_copy_shapes'][c]} in {n} groups"
                for c, n in info["near_copy_groups"].items()
            )
        )
    for source, counts in info["kept_by_source"].items():
        total = sum(counts.values())
        lines.append(
            f"  from {source or 'the source'}: {total} ("
            + ", ".join(f"{c} {n}" for c, n in counts.items())
            + ")"
        )
    return lines
