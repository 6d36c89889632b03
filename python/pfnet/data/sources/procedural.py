"""Procedural furniture: seeded chairs, tables, lamps, sofas and cabinets from primitives.

Dependency-free fixtures for tests and quick runs. Each shape is a union of boxes,
cylinders and cone frustums with proportions drawn from the shape's own generator (so the
same seed gives the same shapes). Shapes are y-up, like the SweetHome3D models.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from pfnet.data.sampling import shape_rng
from pfnet.data.sources import Geometry, Scan, ShapeItem

__all__ = ["CATEGORIES", "build_shape", "scan"]

_Part = tuple[np.ndarray, np.ndarray]

_BOX_FACES = np.array(
    [
        [0, 2, 1], [0, 3, 2], [4, 5, 6], [4, 6, 7], [0, 1, 5], [0, 5, 4],
        [1, 2, 6], [1, 6, 5], [2, 3, 7], [2, 7, 6], [3, 0, 4], [3, 4, 7],
    ]
)  # fmt: skip


def _box(center: tuple[float, float, float], size: tuple[float, float, float]) -> _Part:
    """An axis-aligned box, 8 vertices and 12 triangles."""
    half = np.asarray(size, dtype=np.float64) / 2.0
    corners = np.array(
        [[-1, -1, -1], [1, -1, -1], [1, -1, 1], [-1, -1, 1],
         [-1, 1, -1], [1, 1, -1], [1, 1, 1], [-1, 1, 1]],
        dtype=np.float64,
    )  # fmt: skip
    return np.asarray(center, dtype=np.float64) + corners * half, _BOX_FACES.copy()


def _frustum(
    center: tuple[float, float, float],
    radius_bottom: float,
    radius_top: float,
    height: float,
    sections: int = 24,
) -> _Part:
    """A closed cone frustum along y centred at ``center`` (a cylinder for equal radii)."""
    angle = np.linspace(0.0, 2.0 * np.pi, sections, endpoint=False)
    ring = np.stack([np.cos(angle), np.zeros(sections), np.sin(angle)], axis=1)
    bottom = ring * radius_bottom + [0.0, -height / 2.0, 0.0]
    top = ring * radius_top + [0.0, height / 2.0, 0.0]
    hubs = np.array([[0.0, -height / 2.0, 0.0], [0.0, height / 2.0, 0.0]])
    vertices = np.concatenate([bottom, top, hubs]) + np.asarray(center, dtype=np.float64)
    i = np.arange(sections)
    j = (i + 1) % sections
    side = np.concatenate(
        [np.stack([i, j, sections + j], 1), np.stack([i, sections + j, sections + i], 1)]
    )
    caps = np.concatenate(
        [np.stack([np.full(sections, 2 * sections), j, i], 1),
         np.stack([np.full(sections, 2 * sections + 1), sections + i, sections + j], 1)]
    )  # fmt: skip
    return vertices, np.concatenate([side, caps])


def _merge(parts: list[_Part]) -> Geometry:
    vertices, faces, offset = [], [], 0
    for v, f in parts:
        vertices.append(v)
        faces.append(f + offset)
        offset += len(v)
    return Geometry(np.concatenate(vertices), np.concatenate(faces).astype(np.int64))


def _legs(
    rng: np.random.Generator, width: float, depth: float, height: float, thick: float
) -> list[_Part]:
    """Four legs under a ``width`` × ``depth`` top, square or round."""
    inset = rng.uniform(0.0, 0.1) * min(width, depth)
    x, z = width / 2 - inset - thick / 2, depth / 2 - inset - thick / 2
    round_legs = rng.random() < 0.5
    parts = []
    for sx in (-1, 1):
        for sz in (-1, 1):
            center = (sx * x, height / 2, sz * z)
            if round_legs:
                parts.append(_frustum(center, thick / 2, thick / 2, height, sections=12))
            else:
                parts.append(_box(center, (thick, height, thick)))
    return parts


def _chair(rng: np.random.Generator) -> list[_Part]:
    width, depth = rng.uniform(0.4, 0.6), rng.uniform(0.4, 0.6)
    seat_h, seat_t = rng.uniform(0.38, 0.5), rng.uniform(0.03, 0.08)
    leg = rng.uniform(0.03, 0.06)
    back_h, back_t = rng.uniform(0.3, 0.6), rng.uniform(0.02, 0.06)
    parts = _legs(rng, width, depth, seat_h, leg)
    parts.append(_box((0, seat_h + seat_t / 2, 0), (width, seat_t, depth)))
    parts.append(
        _box((0, seat_h + seat_t + back_h / 2, -depth / 2 + back_t / 2), (width, back_h, back_t))
    )
    if rng.random() < 0.4:  # armrests
        arm_h = rng.uniform(0.15, 0.25)
        for side in (-1, 1):
            parts.append(
                _box((side * (width / 2 - 0.02), seat_h + seat_t + arm_h, 0), (0.04, 0.04, depth))
            )
            parts.append(
                _box((side * (width / 2 - 0.02), seat_h + seat_t + arm_h / 2, depth / 2 - 0.03),
                     (0.03, arm_h, 0.03))
            )  # fmt: skip
    return parts


def _table(rng: np.random.Generator) -> list[_Part]:
    height, top_t = rng.uniform(0.45, 0.8), rng.uniform(0.02, 0.06)
    if rng.random() < 0.3:  # round pedestal table
        radius = rng.uniform(0.3, 0.6)
        return [
            _frustum((0, height - top_t / 2, 0), radius, radius, top_t, sections=32),
            _frustum((0, (height - top_t) / 2, 0), 0.04, 0.04, height - top_t, sections=12),
            _frustum((0, 0.015, 0), radius * 0.5, radius * 0.45, 0.03, sections=24),
        ]
    width, depth = rng.uniform(0.8, 1.8), rng.uniform(0.5, 1.0)
    parts = _legs(rng, width, depth, height - top_t, rng.uniform(0.04, 0.08))
    parts.append(_box((0, height - top_t / 2, 0), (width, top_t, depth)))
    return parts


def _lamp(rng: np.random.Generator) -> list[_Part]:
    base_r, base_t = rng.uniform(0.08, 0.16), rng.uniform(0.02, 0.05)
    stem_h, stem_r = rng.uniform(0.3, 0.9), rng.uniform(0.01, 0.025)
    shade_h = rng.uniform(0.12, 0.3)
    shade_bottom = rng.uniform(0.1, 0.25)
    shade_top = shade_bottom * rng.uniform(0.4, 0.9)
    return [
        _frustum((0, base_t / 2, 0), base_r, base_r * rng.uniform(0.7, 1.0), base_t),
        _frustum((0, base_t + stem_h / 2, 0), stem_r, stem_r, stem_h, sections=12),
        _frustum((0, base_t + stem_h + shade_h / 2 - 0.05, 0), shade_bottom, shade_top, shade_h),
    ]


def _sofa(rng: np.random.Generator) -> list[_Part]:
    width, depth = rng.uniform(1.4, 2.4), rng.uniform(0.7, 1.0)
    seat_h, back_h = rng.uniform(0.35, 0.45), rng.uniform(0.35, 0.55)
    arm_w, arm_h = rng.uniform(0.1, 0.25), rng.uniform(0.15, 0.3)
    back_t = rng.uniform(0.15, 0.25)
    foot = 0.08
    parts = [
        _box((0, foot + (seat_h - foot) / 2, 0), (width, seat_h - foot, depth)),
        _box((0, seat_h + back_h / 2, -depth / 2 + back_t / 2), (width, back_h, back_t)),
    ]
    for side in (-1, 1):
        parts.append(
            _box((side * (width / 2 - arm_w / 2), seat_h + arm_h / 2, 0), (arm_w, arm_h, depth))
        )
    parts += _legs(rng, width, depth, foot, 0.05)
    return parts


def _cabinet(rng: np.random.Generator) -> list[_Part]:
    width, depth, height = rng.uniform(0.5, 1.5), rng.uniform(0.3, 0.6), rng.uniform(0.6, 2.0)
    board = rng.uniform(0.015, 0.03)
    parts = [
        _box((-width / 2 + board / 2, height / 2, 0), (board, height, depth)),
        _box((width / 2 - board / 2, height / 2, 0), (board, height, depth)),
        _box((0, height / 2, -depth / 2 + board / 2), (width, height, board)),
    ]
    shelves = int(rng.integers(2, 6))
    for level in np.linspace(board / 2, height - board / 2, shelves + 1):
        parts.append(_box((0, level, 0), (width, board, depth)))
    if rng.random() < 0.5:  # doors closing the lower half
        door_h = height * rng.uniform(0.3, 0.6)
        parts.append(_box((0, door_h / 2, depth / 2 - board / 2), (width, door_h, board)))
    return parts


_BUILDERS: dict[str, Callable[[np.random.Generator], list[_Part]]] = {
    "chair": _chair,
    "table": _table,
    "lamp": _lamp,
    "sofa": _sofa,
    "cabinet": _cabinet,
}

CATEGORIES: tuple[str, ...] = tuple(_BUILDERS)
"""The procedural categories."""


def build_shape(category: str, seed: int, key: str) -> Geometry:
    """Build one procedural shape.

    Args:
        category: One of :data:`CATEGORIES`.
        seed: The dataset seed.
        key: The shape's key (``category/index``); with ``seed`` it fixes the proportions.

    Returns:
        The triangle mesh.
    """
    if category not in _BUILDERS:
        raise ValueError(f"unknown procedural category {category!r}")
    return _merge(_BUILDERS[category](shape_rng(seed, f"procedural-shape:{key}")))


def scan(count: int, categories: list[str] | None = None) -> Scan:
    """``count`` shapes of each procedural category.

    Args:
        count: Shapes per category.
        categories: A subset of :data:`CATEGORIES` (default: all).

    Returns:
        The scan (no split of its own).
    """
    items = []
    width = len(str(count - 1))
    for category in categories or CATEGORIES:
        for index in range(count):
            key = f"{category}/{index:0{width}d}"
            items.append(
                ShapeItem(
                    key=key,
                    name=f"{category}_{index:0{width}d}",
                    category=category,
                    path=f"procedural:{key}",
                    kind="procedural",
                )
            )
    return Scan(items=items)
