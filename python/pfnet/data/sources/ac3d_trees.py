"""What the AC3D sources (FlightGear, TORCS, crrcsim) share: items, rules and loading.

Each of :mod:`~pfnet.data.sources.flightgear`, :mod:`~pfnet.data.sources.torcs` and
:mod:`~pfnet.data.sources.crrcsim` walks its tree, decides per file a category or a reason to
leave it out, and hands the list to :func:`make_scan`. Shapes are read with
:func:`pfnet.io.formats.ac3d.read_ac3d` in the worker processes (item kind ``"ac3d"``).

Up axis: the three programs model in AC3D's own frame, y up, and rotate on loading (TORCS'
``grloadac.cpp`` swaps y and z as it reads; crrcsim and FlightGear go through plib/OSG). The
files are therefore y-up like the SweetHome3D data, which was measured: the smallest extent
of the bounding box is y for 40 of 40 FlightGear AI aircraft, 17 of 17 TORCS cars and 34 of
40 crrcsim models (the others are flying wings and helicopters, as tall as they are long), and
the lowest vertices (wheels, keels) are at negative or zero y. A source can still rotate its
shapes with :data:`UP_ROTATIONS`.
"""

from __future__ import annotations

import re
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pfnet.data.sources import Geometry, Scan, ShapeItem, unique_names
from pfnet.errors import DataError

__all__ = ["UP_ROTATIONS", "Found", "first_match", "load_ac3d_item", "make_scan"]

UP_ROTATIONS: dict[str, tuple[float, ...] | None] = {
    "y": None,
    # z-up to y-up: (x, y, z) -> (x, z, -y), row vectors times this matrix
    "z": (1.0, 0.0, 0.0, 0.0, 0.0, -1.0, 0.0, 1.0, 0.0),
}
"""Rotations (row-major 3×3, applied as ``v @ R``) taking a source's up axis to y."""


@dataclass(frozen=True)
class Found:
    """One file a source found: its category, or why it is left out.

    Attributes:
        path: The file.
        key: Its path relative to the source root (the shape's stable identity).
        category: The category, or None when the file is left out.
        reason: Why it is left out (a key of :attr:`Scan.dropped`), else "".
    """

    path: Path
    key: str
    category: str | None
    reason: str = ""


def first_match(text: str, rules: Iterable[tuple[str, re.Pattern[str]]]) -> str | None:
    """The label of the first rule whose pattern is found in ``text``, or None."""
    for label, pattern in rules:
        if pattern.search(text):
            return label
    return None


def compile_rules(table: Iterable[tuple[str, str]]) -> tuple[tuple[str, re.Pattern[str]], ...]:
    """``(label, regex)`` pairs compiled case-insensitively, order kept."""
    return tuple((label, re.compile(pattern, re.IGNORECASE)) for label, pattern in table)


def make_scan(
    source: str,
    found: list[Found],
    licenses: list[dict],
    up: str = "y",
) -> Scan:
    """The scan of an AC3D tree: one ``"ac3d"`` item per kept file, dropped files counted.

    Args:
        source: The source's name (the first part of every key, e.g. ``flightgear``).
        found: What the walk found.
        licenses: The licence records for the manifest.
        up: The files' up axis (a key of :data:`UP_ROTATIONS`).

    Raises:
        DataError: Nothing is kept.
    """
    dropped: dict[str, int] = {}
    kept = [f for f in found if f.category is not None]
    for f in found:
        if f.category is None:
            dropped[f.reason] = dropped.get(f.reason, 0) + 1
    if not kept:
        raise DataError(f"{source}: no models found")
    keys = {f.key: f for f in kept}
    names = unique_names({key: f"{source}_{Path(key).with_suffix('').as_posix()}" for key in keys})
    rotation = UP_ROTATIONS[up]
    items = [
        ShapeItem(
            key=f"{source}:{key}",
            name=names[key],
            category=f.category,
            path=str(f.path),
            kind="ac3d",
            args=(str(f.path), rotation),
        )
        for key, f in sorted(keys.items())
    ]
    credits = {item.key: (licenses[0]["source"], "") for item in items}
    return Scan(items=items, licenses=licenses, dropped=dropped, credits=credits)


def load_ac3d_item(path: str, rotation: tuple[float, ...] | None) -> Geometry:
    """Read one AC3D file as a mesh, rotated to y-up (runs in a worker process).

    Raises:
        DataError: The file is malformed, or has no surface (lines only).
    """
    from pfnet.io.formats.ac3d import read_ac3d

    mesh = read_ac3d(path)
    if len(mesh.faces) == 0:
        raise DataError(f"{path}: no polygon surfaces (lines only, or empty)")
    vertices = mesh.vertices
    if rotation is not None:
        vertices = vertices @ np.asarray(rotation, dtype=np.float64).reshape(3, 3)
    return Geometry(vertices, mesh.faces)
