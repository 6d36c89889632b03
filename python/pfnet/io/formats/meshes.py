"""Bounds on mesh files, checked before trimesh reads them.

trimesh reads a whole file and parses every line of it: a 45 MB ASCII PLY of four vertices
followed by five million junk lines took 1.3 GB, an OBJ of five million ``vn`` lines 0.7 GB
(the fourteenth audit). :func:`check_mesh_file` refuses, in one cheap pass that allocates
nothing in proportion to the file, what would make trimesh's cost run away:

- every mesh file is at most :data:`MAX_MESH_BYTES`;
- text files (OBJ, OFF, ASCII PLY and STL) have at most :data:`MAX_MESH_LINES` lines of at
  most :data:`~pfnet.io.formats.lines.MAX_LINE_BYTES` each;
- a PLY's declared element counts match its body: an ASCII one has one line a row and at
  most :data:`MAX_EXTRA_LINES` more, a binary one at least the bytes its rows need;
- a binary STL's triangle count matches its size (otherwise it must be ASCII STL);
- a glTF's external buffers are regular files counted towards the size limit;
- a glTF's scene graph has at most :data:`MAX_GLTF_NODES` nodes, nested at most
  :data:`MAX_GLTF_DEPTH` deep without cycles, and instances its meshes (one copy for every
  node using one, as trimesh flattens it) to at most :data:`MAX_GLTF_INSTANCED` vertices and
  indices.

A file at the limits costs trimesh at most about 1 GB and 13 s (an ASCII PLY of two million
rows; an OBJ of as many lines 0.5 GB and 7 s), per file and per ``prepare`` worker. The
largest model of Debian's SweetHome3D catalogues (820 OBJ files) has 8.8 MB, 283,832 lines
(115,528 vertices, 166,014 faces) and a longest line of 2,692 bytes: the limits leave seven
times the bytes and lines and 24 times the line length.
"""

from __future__ import annotations

import json
import struct
from pathlib import Path
from urllib.parse import unquote

import numpy as np

from pfnet.errors import DataError
from pfnet.io.formats import read_header
from pfnet.io.formats.lines import MAX_LINE_BYTES
from pfnet.io.formats.ply import parse_header

__all__ = [
    "MAX_EXTRA_LINES",
    "MAX_GLTF_DEPTH",
    "MAX_GLTF_INSTANCED",
    "MAX_GLTF_NODES",
    "MAX_MESH_BYTES",
    "MAX_MESH_LINES",
    "check_mesh_file",
]

MAX_MESH_BYTES = 64 << 20
"""Bytes of a mesh file (a glTF with its external buffers)."""

MAX_MESH_LINES = 2_000_000
"""Lines of a text mesh file (OBJ, OFF, ASCII PLY and STL)."""

MAX_EXTRA_LINES = 1000
"""Lines an ASCII PLY may have after its declared rows (trimesh parses every one)."""

MAX_GLTF_NODES = 10_000
"""Nodes of a glTF scene graph."""

MAX_GLTF_DEPTH = 64
"""Levels of nested glTF nodes."""

MAX_GLTF_INSTANCED = 20_000_000
"""Vertices and indices of a glTF scene once trimesh has copied each mesh for every node
using it (its accessors' declared ``count``)."""

_CHUNK = 1 << 20
_TEXT_SUFFIXES = (".obj", ".off")


def check_mesh_file(file: Path) -> None:
    """Refuse a mesh file whose reading by trimesh would not be bounded by its geometry.

    Args:
        file: A mesh file (``.obj .off .ply .stl .glb .gltf``; other suffixes pass).

    Raises:
        DataError: Naming the file and the limit it breaks, or the declared size that its
            bytes disagree with.
    """
    size = file.stat().st_size
    if size > MAX_MESH_BYTES:
        raise DataError(
            f"{file}: {size} bytes, above the {MAX_MESH_BYTES} accepted for a mesh "
            "(simplify or decimate it)"
        )
    suffix = file.suffix.lower()
    with open(file, "rb") as fh:
        if suffix in _TEXT_SUFFIXES:
            _check_lines(fh, file)
            if suffix == ".obj":
                fh.seek(0)
                _check_obj_vertices(fh, file)
        elif suffix == ".ply":
            _check_ply(fh, file, size)
        elif suffix == ".stl":
            _check_stl(fh, file, size)
        elif suffix in (".gltf", ".glb"):
            _check_gltf(fh, file, size, binary=suffix == ".glb")


def _check_lines(fh, file: Path, first_number: int = 1) -> int:
    """Count the lines from ``fh``'s position to the end, refusing too many or an overlong one.

    Reads a chunk at a time and finds the line ends with numpy (about 20 ms for 45 MB).
    """
    lines = 0  # complete lines before the current chunk
    start = 0  # where the current line began, from the position at the call
    offset = 0  # where the current chunk begins
    while chunk := fh.read(_CHUNK):
        ends = offset + np.flatnonzero(np.frombuffer(chunk, dtype=np.uint8) == 10) + 1
        lengths = np.diff(ends, prepend=start)
        if len(ends) and lengths.max() > MAX_LINE_BYTES:
            number = first_number + lines + int(np.argmax(lengths > MAX_LINE_BYTES))
            raise DataError(f"{file}: line {number} is longer than {MAX_LINE_BYTES} bytes")
        if len(ends):
            start = int(ends[-1])
        lines += len(ends)
        offset += len(chunk)
        if offset - start > MAX_LINE_BYTES:
            raise DataError(
                f"{file}: line {first_number + lines} is longer than {MAX_LINE_BYTES} bytes"
            )
        if lines > MAX_MESH_LINES:
            raise DataError(
                f"{file}: more than {MAX_MESH_LINES} lines, above the limit for a text mesh "
                "(save large meshes as binary PLY or STL)"
            )
    return lines + (offset > start)  # a last line without a line end


def _check_obj_vertices(fh, file: Path) -> None:
    """Refuse an OBJ whose ``v`` lines hold different numbers of values: trimesh reshapes
    them all to one width, so ``v 1 2 3`` beside ``v 1 2 3 0.5 0.5 0.5`` became wrong
    vertices, stored without a word. Names the first line that differs."""
    width = first = None
    for number, raw in enumerate(fh, start=1):
        if not raw.startswith((b"v ", b"v\t")):
            continue
        values = len(raw.split(b"#", 1)[0].split()) - 1
        if width is None:
            width, first = values, number
        elif values != width:
            raise DataError(
                f"{file}: line {number} is a vertex of {values} values, line {first} one of "
                f"{width}; an OBJ's vertex lines must all have one width (x y z, optionally "
                "w or r g b)"
            )


def _check_ply(fh, file: Path, size: int) -> None:
    if fh.readline(MAX_LINE_BYTES + 1).strip() != b"ply":
        raise DataError(f"{file}: not a PLY file (first line is not 'ply')")
    header = read_header(fh, file, b"end_header")
    elements, fmt = parse_header(file, header)
    rows = sum(count for _, count, _ in elements)
    if fmt == "ascii":
        lines = _check_lines(fh, file, first_number=len(header) + 2)
        if lines < rows:
            raise DataError(
                f"{file}: truncated PLY data: the header declares {rows} rows, the body has "
                f"{lines} lines"
            )
        if lines > rows + MAX_EXTRA_LINES:
            raise DataError(
                f"{file}: {lines - rows} lines after the {rows} rows its header declares "
                f"(at most {MAX_EXTRA_LINES} accepted): junk after the geometry"
            )
        return
    body = size - fh.tell()
    # every row takes at least its scalars and its list lengths
    needed = sum(
        count * sum(np.dtype(list_type or dtype).itemsize for _, dtype, list_type in props)
        for _, count, props in elements
    )
    if needed > body:
        raise DataError(
            f"{file}: truncated PLY data: the header declares rows of at least {needed} "
            f"bytes, the body has {body}"
        )


def _check_stl(fh, file: Path, size: int) -> None:
    head = fh.read(84)
    if len(head) < 84:
        return  # shorter than a binary header: nothing to bound
    # trimesh reads a binary STL when its size is the one its triangle count gives, and
    # parses anything else as text
    triangles = struct.unpack("<I", head[80:])[0]
    if 84 + 50 * triangles == size:
        return
    if not head.lstrip().startswith(b"solid"):
        raise DataError(
            f"{file}: binary STL declaring {triangles} triangles ({84 + 50 * triangles} "
            f"bytes) but the file has {size}; not ASCII STL either (no 'solid' at its start)"
        )
    fh.seek(0)
    _check_lines(fh, file)


def _check_gltf(fh, file: Path, size: int, *, binary: bool) -> None:
    if binary:
        head = fh.read(20)
        if len(head) < 20 or head[:4] != b"glTF":
            return  # not a GLB: trimesh refuses it, reading at most MAX_MESH_BYTES
        length, chunk_length, chunk_type = struct.unpack("<II4s", head[8:])
        if length > size or 20 + chunk_length > size or chunk_type != b"JSON":
            raise DataError(
                f"{file}: damaged GLB: it declares {length} bytes and a JSON chunk of "
                f"{chunk_length}, the file has {size}"
            )
        text = fh.read(chunk_length)
    else:
        text = fh.read()
    try:
        document = json.loads(text)
    except (ValueError, RecursionError) as err:
        raise DataError(f"{file}: not a glTF file ({type(err).__name__})") from None
    buffers = document.get("buffers") if isinstance(document, dict) else None
    total = size
    for buffer in buffers if isinstance(buffers, list) else []:
        uri = buffer.get("uri") if isinstance(buffer, dict) else None
        if not isinstance(uri, str) or uri.startswith("data:"):
            continue  # embedded: counted in the file's size
        target = file.parent / unquote(uri)
        if not target.is_file():
            raise DataError(f"{file}: buffer {uri[:80]!r} is not a file beside it")
        total += target.stat().st_size
        if total > MAX_MESH_BYTES:
            raise DataError(
                f"{file}: with its buffers {total} bytes or more, above the "
                f"{MAX_MESH_BYTES} accepted for a mesh"
            )
    if isinstance(document, dict):
        _check_scene_graph(document, file)


def _check_scene_graph(document: dict, file: Path) -> None:
    """Bound a glTF scene graph as trimesh will flatten it: nodes, depth and instanced size.

    trimesh concatenates one copy of a mesh for every node path that reaches it, so a 1.9 MB
    GLB of one 20,000-triangle mesh used by 20,000 nodes took 65 s and 5.6 GB, and a 50,000-deep
    chain of nodes did not finish in 90 s. The instanced size is summed over the scene graph
    (from every scene's roots) by a walk that visits each node once, memoising each subtree's
    size, so a graph whose paths multiply costs no more to check than its nodes and edges.
    """
    nodes = document.get("nodes", [])
    nodes = nodes if isinstance(nodes, list) else []
    if len(nodes) > MAX_GLTF_NODES:
        raise DataError(
            f"{file}: glTF with {len(nodes)} nodes; pfnet reads at most {MAX_GLTF_NODES}"
        )
    mesh_size = [_gltf_mesh_size(document, mesh) for mesh in _list(document, "meshes")]
    children: list[list[int]] = []
    own: list[int] = []
    for index, node in enumerate(nodes):
        node = node if isinstance(node, dict) else {}
        kids = node.get("children", [])
        kids = kids if isinstance(kids, list) else []
        for kid in kids:
            if not _is_index(kid, len(nodes)):
                raise DataError(
                    f"{file}: glTF node {index} has a child {str(kid)[:20]!r} out of range"
                )
        children.append(kids)
        mesh = node.get("mesh")
        own.append(mesh_size[mesh] if _is_index(mesh, len(mesh_size)) else 0)
    roots: list[int] = []
    for scene in _list(document, "scenes"):
        scene_nodes = scene.get("nodes") if isinstance(scene, dict) else None
        if isinstance(scene_nodes, list):
            roots += [n for n in scene_nodes if _is_index(n, len(nodes))]
    if not roots:  # no scene: every node that is nobody's child
        children_of = {kid for kids in children for kid in kids}
        roots = [n for n in range(len(nodes)) if n not in children_of]
    # an iterative post-order walk: size[n] (the instanced size of n's subtree) and depth[n]
    # (the nodes on its longest path down) once each of n's children has both
    size: list[int | None] = [None] * len(nodes)
    depth = [0] * len(nodes)
    on_path = [False] * len(nodes)
    for root in roots:
        if size[root] is not None:
            continue
        stack = [(root, 0)]
        on_path[root] = True
        while stack:
            node, next_child = stack[-1]
            if next_child < len(children[node]):
                stack[-1] = (node, next_child + 1)
                kid = children[node][next_child]
                if on_path[kid]:
                    raise DataError(f"{file}: glTF node {kid} is its own ancestor (a cycle)")
                if size[kid] is None:
                    if len(stack) >= MAX_GLTF_DEPTH:
                        raise DataError(
                            f"{file}: glTF nodes nested more than {MAX_GLTF_DEPTH} deep; pfnet "
                            f"reads at most {MAX_GLTF_DEPTH} levels"
                        )
                    on_path[kid] = True
                    stack.append((kid, 0))
                continue
            stack.pop()
            on_path[node] = False
            kids = children[node]
            depth[node] = 1 + max((depth[k] for k in kids), default=0)
            if depth[node] > MAX_GLTF_DEPTH:  # reached through children already walked
                raise DataError(
                    f"{file}: glTF nodes nested more than {MAX_GLTF_DEPTH} deep; pfnet reads "
                    f"at most {MAX_GLTF_DEPTH} levels"
                )
            size[node] = min(own[node] + sum(size[k] for k in kids), MAX_GLTF_INSTANCED + 1)
    total = sum(size[root] for root in roots)
    if total > MAX_GLTF_INSTANCED:
        raise DataError(
            f"{file}: glTF scene instances its meshes to more than {MAX_GLTF_INSTANCED:,} "
            "vertices and indices (one copy for every node using a mesh); pfnet reads at most "
            f"{MAX_GLTF_INSTANCED:,}"
        )


def _list(document: dict, key: str) -> list:
    value = document.get(key, [])
    return value if isinstance(value, list) else []


def _is_index(value, length: int) -> bool:
    return isinstance(value, int) and not isinstance(value, bool) and 0 <= value < length


def _gltf_mesh_size(document: dict, mesh) -> int:
    """The vertices and indices a glTF mesh declares: its primitives' accessor counts."""
    accessors = _list(document, "accessors")
    primitives = mesh.get("primitives", []) if isinstance(mesh, dict) else []
    total = 0
    for primitive in primitives if isinstance(primitives, list) else []:
        if not isinstance(primitive, dict):
            continue
        attributes = primitive.get("attributes")
        used = [attributes.get("POSITION")] if isinstance(attributes, dict) else []
        used.append(primitive.get("indices"))
        for index in used:
            if _is_index(index, len(accessors)) and isinstance(accessors[index], dict):
                count = accessors[index].get("count")
                if isinstance(count, int) and not isinstance(count, bool) and count > 0:
                    total += count
    return total
