"""Mesh folders: ``ROOT/<category>/<any name>.<suffix>``, read with trimesh.

Meshes (``.obj .off .ply .stl .glb .gltf``, and AC3D ``.ac .acc`` read by
:mod:`pfnet.io.formats.ac3d`) are sampled on their surface; point clouds
(``.xyz .pts .npy .pcd``, and ``.ply`` files without faces) are resampled to the point count.
Files may sit in sub-folders of a category folder; other suffixes (``.mtl``, textures,
notes) are ignored. Hidden files and folders (starting with ``.``) are ignored.
"""

from __future__ import annotations

from pathlib import Path

from pfnet.data.sources import Geometry, Scan, ShapeItem, safe_name, unique_names
from pfnet.errors import DataError
from pfnet.io.formats.meshes import check_mesh_file
from pfnet.io.paths import shown, walk_files

__all__ = ["CLOUD_SUFFIXES", "MESH_SUFFIXES", "load_mesh_file", "looks_like", "scan"]

MESH_SUFFIXES: tuple[str, ...] = (".obj", ".off", ".ply", ".stl", ".glb", ".gltf", ".ac", ".acc")
CLOUD_SUFFIXES: tuple[str, ...] = (".xyz", ".pts", ".npy", ".pcd")


def _shape_files(folder: Path) -> list[Path]:
    suffixes = MESH_SUFFIXES + CLOUD_SUFFIXES
    # walked iteratively to a bounded depth (rglob died in a RecursionError 1,500 deep);
    # hidden files and folders are left out
    return [path for path in walk_files(folder) if path.suffix.lower() in suffixes]


def looks_like(root: Path) -> bool:
    """Whether ``root`` has at least one category folder holding a mesh or point cloud file."""
    return root.is_dir() and any(
        _shape_files(folder) for folder in root.iterdir() if folder.is_dir()
    )


def scan(root: Path) -> Scan:
    """Find the shape files of a mesh folder.

    Args:
        root: The folder with one sub-folder per category.

    Returns:
        The scan (no split of its own); names come from the paths inside each category.

    Raises:
        DataError: No category folder holds a shape file.
    """
    found: list[tuple[str, Path]] = []
    for folder in sorted(root.iterdir()):
        if folder.is_dir() and not folder.name.startswith("."):
            found += [(safe_name(folder.name), path) for path in _shape_files(folder)]
    if not found:
        suffixes = " ".join(MESH_SUFFIXES + CLOUD_SUFFIXES)
        raise DataError(
            f"{root}: no shapes found; expected {root}/<category>/<file> "
            f"with a suffix in: {suffixes}"
        )
    keys = {path: path.relative_to(root).as_posix() for _, path in found}
    # wanted name: the category, then the path inside its folder without the suffix
    stems = {}
    for category, path in found:
        inside = path.relative_to(root).with_suffix("").as_posix().split("/", 1)[1]
        stems[keys[path]] = f"{category}_{inside}"
    names = unique_names(stems)
    items = [
        ShapeItem(
            key=keys[path],
            name=names[keys[path]],
            category=category,
            path=str(path),
            kind="cloud-file" if path.suffix.lower() in CLOUD_SUFFIXES else "mesh-file",
        )
        for category, path in found
    ]
    return Scan(items=items)


def load_mesh_file(path: str) -> Geometry:
    """Read a mesh with trimesh (scenes are flattened with their transforms).

    The file is first checked against the bounds of :mod:`pfnet.io.formats.meshes` (size, lines,
    declared counts), so that trimesh's time and memory follow the geometry. A ``.ply``
    without faces is read as a point cloud with :func:`pfnet.io.clouds.read_point_cloud`.

    Args:
        path: The file.

    Returns:
        The mesh, or the point cloud.

    Raises:
        DataError: The file breaks a bound, naming it and the bound.
    """
    import numpy as np
    import trimesh

    suffix = Path(path).suffix.lower()
    if suffix in (".ac", ".acc"):  # trimesh does not read AC3D
        from pfnet.data.sources.ac3d_trees import load_ac3d_item

        return load_ac3d_item(path, None)
    check_mesh_file(Path(path))
    options = {"skip_materials": True} if suffix == ".obj" else {}
    if shown(path) != str(path):
        # a name whose bytes are not UTF-8: trimesh names the geometry after the file and
        # hashes that name as UTF-8 (UnicodeEncodeError), so it gets the bytes, not the name
        from trimesh.resolvers import FilePathResolver

        with open(path, "rb") as fh:
            mesh = trimesh.load(
                fh,
                file_type=suffix[1:],
                force="mesh",
                process=False,
                resolver=FilePathResolver(str(Path(path).parent)),
                **options,
            )
    else:
        mesh = trimesh.load(path, force="mesh", process=False, **options)
    faces = np.asarray(mesh.faces, dtype=np.int64).reshape(-1, 3)
    if suffix == ".ply" and len(faces) == 0:
        from pfnet.io.clouds import read_point_cloud

        return Geometry(read_point_cloud(path))
    return Geometry(np.asarray(mesh.vertices, dtype=np.float64).reshape(-1, 3), faces)
