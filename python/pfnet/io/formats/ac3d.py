"""AC3D meshes (``.ac``, and TORCS' ``.acc`` variant), read into one triangle mesh.

AC3D is line-oriented text (the format is described at ``ac3d.org``): a ``AC3D<version>``
header, ``MATERIAL`` lines (ignored here), then one tree of ``OBJECT`` blocks. An object
holds optional ``name``/``data``/``texture``/``texrep``/``texoff``/``crease``/``url`` lines,
an optional ``rot`` (3×3, nine numbers) and ``loc`` (three numbers), ``numvert N`` followed by
``N`` vertex lines, ``numsurf M`` followed by ``M`` surfaces (``SURF flags``, ``mat i``,
``refs K`` and ``K`` lines ``index u v``), and ends with ``kids C``, after which its ``C``
child objects follow.

What this reader does:

- **Transforms.** An object's vertices, and its children, are placed by its ``rot`` then its
  ``loc``: ``v' = v @ R + loc``, with ``R`` the nine numbers read row by row, composed from the
  leaf up to the root (plib's ``ssgLoadAC`` and FlightGear's loader do the same; every
  ``rot`` of the Debian packages is a signed permutation, most the identity).
- **Surfaces.** The low four bits of ``SURF`` flags give the type: 0 is a polygon,
  triangulated as a fan from its first vertex (exact for convex polygons, which is what
  modellers export; a concave one gets some triangles outside it); 1 (closed line) and 2
  (line) draw no surface and are skipped, and counted; 4 is TORCS' triangle strip (``.acc``),
  split into its triangles. Other types are skipped and counted as unknown. A polygon of fewer
  than three references has no area and is dropped.
- **TORCS ``.acc``.** Vertex lines may carry a normal after the position (six numbers), a
  ``refs`` line up to four texture-coordinate pairs, and an object up to four ``texture`` lines
  (``base``/``tiled``/``skids``/``shad``); only the position and the vertex index are used.
- **Bounds.** The file is at most :data:`MAX_AC3D_BYTES` and :data:`MAX_AC3D_LINES` lines;
  every declared count (``numvert``, ``numsurf``, ``refs``, ``kids``, ``data``) is checked
  against the lines the file still has before anything is allocated, objects nest at most
  :data:`MAX_DEPTH` deep, and a reference must name a vertex of its own object. A broken file
  is one :class:`~pfnet.errors.DataError` naming the file and the line.

Coordinates are returned as the file has them: AC3D's convention is y-up, which FlightGear's
models and TORCS' cars follow in their files (the programs rotate them on loading).
"""

from __future__ import annotations

import bisect
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from pfnet.errors import DataError

__all__ = [
    "MAX_AC3D_BYTES",
    "MAX_AC3D_LINES",
    "MAX_DEPTH",
    "AC3DMesh",
    "parse_ac3d",
    "read_ac3d",
]

MAX_AC3D_BYTES = 64 << 20
"""Bytes of an AC3D file (the largest of the Debian packages' 2,945 files has 21 MB)."""

MAX_AC3D_LINES = 4_000_000
"""Lines of an AC3D file."""

MAX_DEPTH = 64
"""How deep objects may nest."""

# The surface types of the low four bits of SURF flags.
_POLYGON, _CLOSED_LINE, _LINE, _STRIP = 0, 1, 2, 4


@dataclass
class AC3DMesh:
    """A flattened AC3D file.

    Attributes:
        vertices: float64 ``(V, 3)``, every object's vertices placed by its transforms.
        faces: int64 ``(F, 3)`` triangles into ``vertices``.
        objects: ``OBJECT`` blocks read (the root ``world`` included).
        skipped: Surfaces that are not polygons, by kind (``line``, ``closed_line``,
            ``unknown``), and ``degenerate`` polygons of fewer than three references.
    """

    vertices: np.ndarray
    faces: np.ndarray
    objects: int = 0
    skipped: dict[str, int] = field(default_factory=dict)


def read_ac3d(path: str | Path) -> AC3DMesh:
    """Read an AC3D file (``.ac``/``.acc``) into one triangle mesh.

    Args:
        path: The file.

    Returns:
        The mesh (see :func:`parse_ac3d`).

    Raises:
        DataError: The file is missing, too large, or malformed, naming it and the line.
    """
    file = Path(path)
    try:
        size = file.stat().st_size
        if size > MAX_AC3D_BYTES:
            raise DataError(
                f"{file}: {size} bytes; pfnet reads AC3D files of at most {MAX_AC3D_BYTES:,} bytes"
            )
        with open(file, "rb") as fh:
            data = fh.read(MAX_AC3D_BYTES + 1)
    except OSError as err:
        raise DataError(f"{file}: cannot read: {err.strerror or err}") from err
    if len(data) > MAX_AC3D_BYTES:  # grew since stat
        raise DataError(f"{file}: more than {MAX_AC3D_BYTES:,} bytes")
    return parse_ac3d(data, str(file))


class _Lines:
    """The file's lines with a cursor; errors name the file and the 1-based line."""

    def __init__(self, data: bytes, name: str) -> None:
        self.name = name
        text = data.decode("latin-1")  # names and data blocks may hold any byte
        self.raw = text.splitlines()
        if len(self.raw) > MAX_AC3D_LINES:
            raise DataError(
                f"{name}: {len(self.raw)} lines; pfnet reads AC3D files of at most "
                f"{MAX_AC3D_LINES:,} lines"
            )
        # blank and comment lines carry nothing (exporters leave blank ones inside reference
        # blocks, and plib skips '#' lines): the parser walks the others, and errors give the
        # file's own line numbers
        self.numbers = [
            k for k, line in enumerate(self.raw) if line.strip() and line.lstrip()[0] != "#"
        ]
        self.lines = [self.raw[k] for k in self.numbers]
        self.at = 0

    def error(self, message: str, line: int | None = None) -> DataError:
        at = self.at if line is None else line
        number = self.numbers[at] + 1 if at < len(self.numbers) else len(self.raw)
        return DataError(f"{self.name}: line {number}: {message}")

    def left(self) -> int:
        return len(self.lines) - self.at

    def next_statement(self) -> tuple[str, str]:
        """The next non-blank line as ``(keyword, rest)``; the cursor stays on it."""
        if self.at < len(self.lines):
            keyword, _, rest = self.lines[self.at].strip().partition(" ")
            return keyword, rest.strip()
        raise DataError(
            f"{self.name}: truncated file (ends at line {len(self.raw)} inside an object)"
        )

    def count(self, rest: str, what: str, per_line: int = 1) -> int:
        """A declared count, checked against the lines left after the current one."""
        try:
            value = int(rest.split()[0], 0)
        except (ValueError, IndexError):
            raise self.error(f"{what} is not a count: {rest[:40]!r}") from None
        if value < 0:
            raise self.error(f"{what} {value} is negative")
        if value * per_line > self.left() - 1:
            raise self.error(
                f"{what} {value} declares more than the {self.left() - 1} lines left in the file"
            )
        return value


def _floats(lines: _Lines, rest: str, n: int, what: str) -> np.ndarray:
    try:
        values = [float(token) for token in rest.split()[:n]]
    except ValueError:
        values = []
    if len(values) != n:
        raise lines.error(f"{what} needs {n} numbers, got {rest[:60]!r}")
    return np.array(values, dtype=np.float64)


def _vertex_block(lines: _Lines, start: int, n: int) -> np.ndarray:
    """The positions of ``n`` vertex lines from ``start`` (3 numbers, or 6 with a normal)."""
    block = lines.lines[start : start + n]
    flat = np.array(" ".join(block).split(), dtype=object)
    if flat.size in (3 * n, 6 * n):
        try:
            return flat.astype(np.float64).reshape(n, -1)[:, :3]
        except ValueError:
            pass
    # mixed widths or a bad token: find the line
    out = np.empty((n, 3), dtype=np.float64)
    for k, line in enumerate(block):
        tokens = line.split()
        try:
            if len(tokens) not in (3, 6):
                raise ValueError
            out[k] = [float(t) for t in tokens[:3]]
        except ValueError:
            raise lines.error(
                f"a vertex line needs 3 numbers (or 6 with a normal), got {line.strip()[:60]!r}",
                start + k,
            ) from None
    return out


def _surfaces(
    lines: _Lines, n_surfaces: int, n_vertices: int, skipped: dict[str, int]
) -> np.ndarray:
    """Read ``n_surfaces`` surfaces; return their triangles (local vertex indices)."""
    fans: list[tuple[int, int]] = []  # (offset into refs, count) of each polygon
    strips: list[tuple[int, int]] = []
    ref_lines: list[str] = []
    offsets: list[int] = []  # each surface's first reference: its offset, and its file line
    first_lines: list[int] = []
    for _ in range(n_surfaces):
        keyword, rest = lines.next_statement()
        if keyword != "SURF":
            raise lines.error(f"expected SURF, got {keyword[:40]!r}")
        try:
            kind = int(rest.split()[0], 0) & 0x0F
        except (ValueError, IndexError):
            raise lines.error(f"SURF flags are not a number: {rest[:40]!r}") from None
        lines.at += 1
        while True:
            keyword, rest = lines.next_statement()
            if keyword == "mat":
                lines.at += 1
                continue
            if keyword != "refs":
                raise lines.error(f"expected mat or refs in a surface, got {keyword[:40]!r}")
            break
        n_refs = lines.count(rest, "refs")
        lines.at += 1
        offset = len(ref_lines)
        offsets.append(offset)
        first_lines.append(lines.at)
        ref_lines += lines.lines[lines.at : lines.at + n_refs]
        lines.at += n_refs
        if kind in (_POLYGON, _STRIP):
            if n_refs < 3:
                skipped["degenerate"] = skipped.get("degenerate", 0) + 1
            else:
                (fans if kind == _POLYGON else strips).append((offset, n_refs))
        else:
            reason = {_CLOSED_LINE: "closed_line", _LINE: "line"}.get(kind, "unknown")
            skipped[reason] = skipped.get(reason, 0) + 1
    if not ref_lines:
        return np.zeros((0, 3), dtype=np.int64)

    def file_line(index: int) -> int:
        surface = bisect.bisect_right(offsets, index) - 1
        return first_lines[surface] + index - offsets[surface]

    try:
        refs = np.array([line.split(None, 1)[0] for line in ref_lines], dtype=np.int64)
    except (ValueError, IndexError):
        bad = next(k for k, line in enumerate(ref_lines) if not _is_int(line))
        raise lines.error(
            f"a reference line must start with a vertex index, got {ref_lines[bad][:40]!r}",
            file_line(bad),
        ) from None
    if refs.min() < 0 or refs.max() >= n_vertices:
        bad = int(np.flatnonzero((refs < 0) | (refs >= n_vertices))[0])
        raise lines.error(
            f"reference to vertex {refs[bad]}, but the object has {n_vertices} vertices",
            file_line(bad),
        )
    return np.concatenate([_fan(refs, fans), _strip(refs, strips)])


def _is_int(line: str) -> bool:
    try:
        int(line.split(None, 1)[0])
        return True
    except (ValueError, IndexError):
        return False


def _triangle_steps(runs: list[tuple[int, int]]) -> tuple[np.ndarray, np.ndarray]:
    """For runs of ``(offset, count)`` references (a polygon or a strip each), every triangle's
    run offset and its index ``0 .. count - 3`` within the run."""
    offsets = np.array([r[0] for r in runs], dtype=np.int64)
    n_tri = np.array([r[1] for r in runs], dtype=np.int64) - 2
    step = np.arange(n_tri.sum()) - np.repeat(np.cumsum(n_tri) - n_tri, n_tri)
    return np.repeat(offsets, n_tri), step


def _fan(refs: np.ndarray, polygons: list[tuple[int, int]]) -> np.ndarray:
    if not polygons:
        return np.zeros((0, 3), dtype=np.int64)
    first, step = _triangle_steps(polygons)
    return np.stack([refs[first], refs[first + step + 1], refs[first + step + 2]], axis=1)


def _strip(refs: np.ndarray, strips: list[tuple[int, int]]) -> np.ndarray:
    if not strips:
        return np.zeros((0, 3), dtype=np.int64)
    start, step = _triangle_steps(strips)
    a, b, c = refs[start + step], refs[start + step + 1], refs[start + step + 2]
    odd = (step % 2).astype(bool)  # every other triangle of a strip is wound the other way
    faces = np.stack([a, np.where(odd, c, b), np.where(odd, b, c)], axis=1)
    # strips join with repeated vertices: those triangles have no area
    keep = (
        (faces[:, 0] != faces[:, 1]) & (faces[:, 1] != faces[:, 2]) & (faces[:, 0] != faces[:, 2])
    )
    return faces[keep]


def parse_ac3d(data: bytes, name: str = "<ac3d>") -> AC3DMesh:
    """Parse AC3D text into one triangle mesh (see the module docstring).

    Args:
        data: The file's bytes.
        name: The file's name, for error messages.

    Returns:
        The mesh, with the count of objects read and of surfaces skipped.

    Raises:
        DataError: Not AC3D, a truncated file, a count that disagrees with the file, a
            reference to a missing vertex, a malformed number, objects nested too deep.
    """
    if len(data) > MAX_AC3D_BYTES:
        raise DataError(f"{name}: more than {MAX_AC3D_BYTES:,} bytes")
    lines = _Lines(data, name)
    if not lines.lines or not lines.lines[0].lstrip().startswith("AC3D"):
        raise DataError(f"{name}: not an AC3D file (no 'AC3D' header on line 1)")
    lines.at = 1
    vertices: list[np.ndarray] = []
    faces: list[np.ndarray] = []
    skipped: dict[str, int] = {}
    n_vertices_total = 0
    objects = 0
    while True:  # the palette, up to the root object
        if lines.left() == 0:
            raise DataError(f"{name}: no OBJECT in the file")
        keyword, _ = lines.next_statement()
        if keyword != "MATERIAL":
            break
        lines.at += 1
    # the open objects: [kids still to read, rotation, location], both in world terms
    stack: list[list] = []
    while True:
        if stack and lines.left() == 0:
            # a parent declaring more kids than the file has (exporters do it; plib and
            # FlightGear read such files): what was read is the model
            skipped["missing_kids"] = sum(entry[0] for entry in stack)
            break
        keyword, rest = lines.next_statement()
        if keyword != "OBJECT":
            raise lines.error(f"expected OBJECT, got {keyword[:40]!r}")
        if len(stack) >= MAX_DEPTH:
            raise lines.error(f"objects nest more than {MAX_DEPTH} deep")
        objects += 1
        object_type = (rest.split() or [""])[0].lower()
        lines.at += 1
        rotation, location = np.eye(3), np.zeros(3)
        local_vertices = np.zeros((0, 3))
        local_faces = np.zeros((0, 3), dtype=np.int64)
        while True:
            keyword, rest = lines.next_statement()
            if keyword == "kids":
                n_kids = lines.count(rest, "kids")
                lines.at += 1
                break
            if keyword == "numvert":
                n = lines.count(rest, "numvert")
                lines.at += 1
                local_vertices = _vertex_block(lines, lines.at, n)
                lines.at += n
            elif keyword == "numsurf":
                n = lines.count(rest, "numsurf", per_line=3)  # SURF, refs and a reference
                lines.at += 1
                local_faces = _surfaces(lines, n, len(local_vertices), skipped)
            elif keyword == "rot":
                rotation = _floats(lines, rest, 9, "rot").reshape(3, 3)
                lines.at += 1
            elif keyword == "loc":
                location = _floats(lines, rest, 3, "loc")
                lines.at += 1
            elif keyword == "data":
                _skip_data(lines, lines.count(rest, "data", per_line=0))
            elif keyword in ("OBJECT", "SURF"):
                raise lines.error(f"{keyword} before the object's kids line")
            elif keyword[:1].isdigit() or keyword[:1] in "-+.":
                raise lines.error(
                    f"{lines.lines[lines.at].strip()[:40]!r} is no statement (more vertices "
                    "or references than declared?)"
                )
            else:  # name, texture, texrep, texoff, crease, url, subdiv, hidden, locked, and
                # the odd MATERIAL line some exporters put inside the root object
                lines.at += 1
        if stack:  # the parent's transform applies after this object's own
            _, parent_rotation, parent_location = stack[-1]
            rotation, location = (
                rotation @ parent_rotation,
                location @ parent_rotation + parent_location,
            )
        if object_type != "light" and len(local_faces):
            vertices.append(local_vertices @ rotation + location)
            faces.append(local_faces + n_vertices_total)
            n_vertices_total += len(local_vertices)
        stack.append([n_kids, rotation, location])
        while stack and stack[-1][0] == 0:  # done with this object and its children
            stack.pop()
            if stack:
                stack[-1][0] -= 1
        if not stack:
            break  # the root is complete; what follows it is ignored
    if not vertices:
        return AC3DMesh(np.zeros((0, 3)), np.zeros((0, 3), dtype=np.int64), objects, skipped)
    return AC3DMesh(np.concatenate(vertices), np.concatenate(faces), objects, skipped)


def _skip_data(lines: _Lines, n_chars: int) -> None:
    """Step over a ``data`` block: ``n_chars`` characters, newlines included, then a newline."""
    raw = lines.numbers[lines.at] + 1  # the block's first line in the file
    taken = 0
    while taken < n_chars:
        if raw >= len(lines.raw):
            raise lines.error(f"data {n_chars} runs past the end of the file")
        taken += len(lines.raw[raw]) + 1
        raw += 1
    lines.at = bisect.bisect_left(lines.numbers, raw)
