"""The data sources ``pfnet prepare`` reads, each turned into a list of :class:`ShapeItem`.

A source module has a ``scan(...) -> Scan`` that finds the shapes without loading them, and
the worker processes call :func:`~pfnet.data.sources.registry.load_item` to load one shape as
a mesh or a point cloud. This module holds what every source shares (the items, the scans,
the names); :mod:`pfnet.data.sources.registry` is the list of sources, and imports them.
"""

from __future__ import annotations

import re
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from pfnet.data.format import RECORD_NAME
from pfnet.errors import ConfigError

__all__ = [
    "Geometry",
    "Scan",
    "ShapeItem",
    "pick_source",
    "safe_name",
    "unique_names",
]


_UNSAFE = re.compile(r"[^a-z0-9._-]+")
_MAX_NAME = 96


@dataclass(frozen=True)
class ShapeItem:
    """One shape to prepare; small and picklable, so it can be sent to a worker process.

    Attributes:
        key: Stable identity in the source (e.g. a relative path); seeds the shape's sampling.
        name: Unique, filesystem-safe name in the dataset.
        category: Category label.
        path: Where the shape comes from, for reports (a file, or ``CATALOGUE.sh3f:/model.obj``).
        kind: How to load it: ``"mesh-file"``, ``"cloud-file"``, ``"sh3f"``, ``"ac3d"`` or
            ``"procedural"``.
        split: ``"train"``/``"val"``/``"test"`` when the source defines it, else None.
        args: Loader arguments for ``kind``.
    """

    key: str
    name: str
    category: str
    path: str
    kind: str
    split: str | None = None
    args: tuple = ()


@dataclass
class Scan:
    """What a source holds: the shapes, and what was dropped or unreadable before loading.

    Attributes:
        items: The shapes to prepare.
        licenses: Licence/credit records copied into the manifest.
        dropped: Counts of shapes left out on purpose, by reason.
        skipped: ``(path, reason)`` of entries that cannot be prepared (e.g. a file listed in a
            split but missing).
        has_splits: Whether the source defines the train/val/test split.
        credits: ``{key: (licence source, creator)}`` for sources that credit each model;
            the licence source is the ``"source"`` of a record in ``licenses``.
    """

    items: list[ShapeItem]
    licenses: list[dict] = field(default_factory=list)
    dropped: dict[str, int] = field(default_factory=dict)
    skipped: list[tuple[str, str]] = field(default_factory=list)
    has_splits: bool = False
    credits: dict[str, tuple[str, str]] = field(default_factory=dict)


@dataclass(frozen=True)
class Geometry:
    """A loaded shape: a triangle mesh (``faces`` given) or a point cloud (``faces`` None)."""

    vertices: np.ndarray
    faces: np.ndarray | None = None


def pick_source(
    source: Path | None,
    *,
    procedural: bool,
    default: Path,
    hint: str,
    say: Callable[[str], None],
) -> Path | None:
    """The model source a command uses: ``source`` if given, else ``default`` when it holds
    catalogues, else ``None`` for procedural shapes (saying so to ``say``, with how to get
    real data: the command prints it).

    Raises:
        ConfigError: ``source`` does not exist.
    """
    if procedural:
        return None
    if source is not None:
        if not Path(source).exists():
            raise ConfigError(f"model source {source} does not exist")
        return Path(source)
    if default.is_dir() and any(default.glob("*.sh3f")):
        return default
    say(
        f"SweetHome3D furniture not found in {default}; for real data run\n"
        f"    {hint}\nand start again. Using procedural shapes now."
    )
    return None


def safe_name(text: str) -> str:
    """A lower-case, filesystem-safe version of ``text`` (``[a-z0-9._-]``, no leading dot,
    never ``predictions.json``)."""
    name = _UNSAFE.sub("_", text.lower()).strip("._-")
    name = name[:_MAX_NAME].rstrip("._-") or "shape"
    return "predictions_json" if name == RECORD_NAME else name  # predict's record keeps its name


def unique_names(wanted: Mapping[str, str]) -> dict[str, str]:
    """Safe names, unique among all shapes, from the name wanted for each key.

    Args:
        wanted: ``{key: wanted name}``; keys are distinct, wanted names may clash.

    Returns:
        ``{key: name}``: :func:`safe_name` of the wanted name, with ``-2``, ``-3``... appended
        on a clash (in key order, so the result does not depend on the input order).
    """
    names: dict[str, str] = {}
    taken: set[str] = set()
    # The next suffix to try for each base: every smaller one is taken, so N shapes wanting
    # one name cost O(N), not O(N^2) (20,000 took 31 s when each search began at -2).
    next_suffix: dict[str, int] = {}
    for key in sorted(wanted):
        base = safe_name(wanted[key])
        name, suffix = base, next_suffix.get(base, 2)
        if name in taken:
            name = f"{base}-{suffix}"
            while name in taken:
                suffix += 1
                name = f"{base}-{suffix}"
            next_suffix[base] = suffix + 1
        taken.add(name)
        names[key] = name
    return names
