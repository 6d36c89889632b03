"""The data sources ``pfnet prepare`` reads, each turned into a list of :class:`ShapeItem`.

A source module has a ``scan(...) -> Scan`` that finds the shapes without loading them, and
the worker processes call :func:`load_item` to load one shape as a mesh or a point cloud.
"""

from __future__ import annotations

import os
import re
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from pfnet.data.format import RECORD_NAME
from pfnet.errors import ConfigError, DataError

__all__ = [
    "FORMATS",
    "OPEN_SHAPE_FORMATS",
    "Geometry",
    "Scan",
    "ShapeItem",
    "detect_format",
    "load_item",
    "pick_source",
    "safe_name",
    "scan_open_shapes",
    "unique_names",
]

FORMATS: tuple[str, ...] = (
    "meshes",
    "shapenet-part",
    "sweethome3d",
    "procedural",
    "flightgear",
    "torcs",
    "crrcsim",
    "sweethome3d-app",
)
"""The source formats ``pfnet prepare --format`` accepts (besides ``auto``)."""

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


def pick_source(source: Path | None, *, procedural: bool, default: Path, hint: str) -> Path | None:
    """The model source a command uses: ``source`` if given, else ``default`` when it holds
    catalogues, else ``None`` for procedural shapes (saying so, and how to get real data).

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
    print(
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


def load_item(item: ShapeItem, seed: int) -> Geometry:
    """Load one shape (runs in a worker process).

    Args:
        item: The shape.
        seed: The dataset seed (procedural shapes are built from it).

    Returns:
        The shape's geometry.
    """
    if item.kind == "mesh-file":
        from pfnet.data.sources.meshes import load_mesh_file

        return load_mesh_file(item.path)
    if item.kind == "cloud-file":
        from pfnet.io.clouds import read_point_cloud

        return Geometry(read_point_cloud(item.path))
    if item.kind == "sh3f":
        from pfnet.data.sources.sweethome3d import load_model

        return load_model(*item.args)
    if item.kind == "ac3d":
        from pfnet.data.sources.ac3d_trees import load_ac3d_item

        return load_ac3d_item(*item.args)
    if item.kind == "procedural":
        from pfnet.data.sources.procedural import build_shape

        return build_shape(item.category, seed, item.key)
    raise ValueError(f"unknown shape kind {item.kind!r}")


def detect_format(source: str | os.PathLike[str] | None) -> str:
    """Guess the source format.

    Args:
        source: ``None`` or ``"procedural"``, a ``.sh3f`` file, or a folder.

    Returns:
        One of :data:`pfnet.data.sources.FORMATS` or
        :data:`pfnet.data.benchmarks.BENCHMARK_FORMATS`.

    Raises:
        DataError: The source does not exist or matches no format.
    """
    from pfnet.data.benchmarks import detect_benchmark
    from pfnet.data.sources import meshes, shapenet_part, sweethome3d

    if source is None or str(source) == "procedural":
        return "procedural"
    path = Path(source)
    if not path.exists():
        raise DataError(f"{path}: no such file or folder")
    if sweethome3d.looks_like(path):
        return "sweethome3d"
    for name, module in _open_shape_sources().items():
        if module.looks_like(path):
            return name
    if shapenet_part.looks_like(path):
        return "shapenet-part"
    benchmark = detect_benchmark(path)
    if benchmark is not None:
        return benchmark
    if meshes.looks_like(path):
        return "meshes"
    if path.is_dir() and not any(path.iterdir()):
        raise DataError(f"{path}: the source folder is empty")
    raise DataError(
        f"{path}: cannot detect the format (expected *.sh3f catalogues, a ShapeNet-Part tree "
        f"with {shapenet_part.CATEGORY_FILE}, or <category>/<mesh file> folders); "
        "give the format (meshes, shapenet-part or sweethome3d)"
    )


OPEN_SHAPE_FORMATS = ("flightgear", "torcs", "crrcsim", "sweethome3d-app")
"""The formats of the open-shapes sources (:func:`scan_open_shapes`)."""


def scan_open_shapes(fmt: str, path: Path) -> Scan:
    """Scan a FlightGear, TORCS or crrcsim tree or the SweetHome3D application."""
    return _open_shape_sources()[fmt].scan(path)


def _open_shape_sources() -> dict:
    """The sources of the open-shapes corpus, by format name (FlightGear, TORCS, crrcsim, the
    SweetHome3D application's catalogue)."""
    from pfnet.data.sources import crrcsim, flightgear, sweethome3d_app, torcs

    return {
        "flightgear": flightgear,
        "torcs": torcs,
        "crrcsim": crrcsim,
        "sweethome3d-app": sweethome3d_app,
    }
