"""The one list of data sources: the formats ``pfnet prepare`` reads, which one a path is
(:func:`detect_format`), and loading a shape of any of them (:func:`load_item`)."""

from __future__ import annotations

import os
from pathlib import Path

from pfnet.data.sources import Geometry, Scan, ShapeItem
from pfnet.errors import DataError

__all__ = ["FORMATS", "OPEN_SHAPE_FORMATS", "detect_format", "load_item", "scan_open_shapes"]

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
        One of :data:`pfnet.data.sources.registry.FORMATS` or
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
