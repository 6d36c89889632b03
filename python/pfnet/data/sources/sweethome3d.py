"""SweetHome3D furniture catalogues (``.sh3f``), read straight from their ZIP files.

Debian's ``sweethome3d-furniture`` package installs five catalogues (820 models) in
:data:`DEFAULT_PATH`. Each ``.sh3f`` is a ZIP holding ``PluginFurnitureCatalog.properties``
(``name#N=``, ``category#N=``, ``model#N=/folder/model.obj``, ``modelRotation#N=``...; Java
properties syntax, ISO-8859-1 with ``\\uXXXX`` escapes) and the OBJ/MTL files. Only the OBJ
geometry is read (materials and textures are ignored), with a vectorised parser.

Models are y-up and in centimetres; both are kept (normalisation removes the scale), and a
catalogue ``modelRotation`` is applied so that every model stands upright. Catalogue names
are mapped to categories with :data:`CATEGORY_KEYWORDS`; unmatched models get the category
``other``, which ``pfnet prepare`` leaves out unless asked for (``--categories all``).
Light sources smaller than :data:`MIN_LIGHT_SIZE_CM` (and entries named "light source")
are dropped.
"""

from __future__ import annotations

import functools
import os
import re
import warnings
import zipfile
from pathlib import Path
from urllib.parse import unquote

import numpy as np

from pfnet.data.sources import Geometry, Scan, ShapeItem, unique_names
from pfnet.errors import DataError

__all__ = [
    "CATEGORY_KEYWORDS",
    "DEFAULT_PATH",
    "MIN_LIGHT_SIZE_CM",
    "OTHER",
    "catalogue_entries",
    "category_for",
    "load_model",
    "looks_like",
    "parse_obj",
    "parse_properties",
    "scan",
]

DEFAULT_PATH = Path("/usr/share/sweethome3d/furniture")
"""Where Debian's ``sweethome3d-furniture`` package installs the catalogues."""

CATALOGUE_FILE = "PluginFurnitureCatalog.properties"

OTHER = "other"
"""The category of catalogue models no keyword matches."""

MIN_LIGHT_SIZE_CM = 10.0
"""Light-source entries whose largest catalogue dimension is below this are dropped."""

# Ordered: the first category with a keyword among the words of the catalogue name wins
# ("Seat Leon" is a car, not a chair; "Desk lamp" a lamp, not a table). Words, not
# substrings: "Bedside table" is a table, "Flashlight" is no lamp. A name containing one of
# the category's excluded words never gets that category ("Table tennis bat").
_KEYWORD_TABLE: tuple[tuple[str, str, str], ...] = (
    # category, keywords, excluded words
    ("car", "car sedan suv van bus truck chevrolet ford peugeot renault beetle leon", ""),
    ("lamp", "lamp lamps lamppost lantern chandelier light lights", ""),
    ("sofa", "sofa couch settee loveseat", ""),
    ("bed", "bed crib futon", ""),
    ("chair", "chair armchair stool seat", ""),
    ("table", "table desk", "bat fan football changing dressing"),
    (
        "cabinet",
        "cabinet cupboard wardrobe dresser bookcase bookshelf shelves shelf sideboard chest",
        "freezer",
    ),
    ("person", "male female man woman boy girl mannequin", "shoe shoes"),
)
CATEGORY_KEYWORDS: tuple[tuple[str, frozenset[str], frozenset[str]], ...] = tuple(
    (category, frozenset(keywords.split()), frozenset(excluded.split()))
    for category, keywords, excluded in _KEYWORD_TABLE
)
"""``(category, keywords, excluded words)`` in priority order (see :func:`category_for`)."""

_ESCAPES = {"t": "\t", "n": "\n", "r": "\r", "f": "\f"}


def looks_like(source: Path) -> bool:
    """Whether ``source`` is a ``.sh3f`` file or a folder holding some."""
    if source.is_file():
        return source.suffix.lower() == ".sh3f"
    return source.is_dir() and any(source.glob("*.sh3f"))


def category_for(name: str) -> str:
    """The category of a catalogue name (see :data:`CATEGORY_KEYWORDS`), or :data:`OTHER`."""
    words = set(re.findall(r"[a-z]+", name.lower()))
    for category, keywords, excluded in CATEGORY_KEYWORDS:
        if words & keywords and not words & excluded:
            return category
    return OTHER


def parse_properties(text: str) -> dict[str, str]:
    """Parse Java ``.properties`` text (comments, continuation lines, ``\\uXXXX`` escapes).

    Args:
        text: The decoded file (``.properties`` files are ISO-8859-1).

    Returns:
        ``{key: value}``.
    """
    logical: list[str] = []
    pending = ""
    for raw in text.splitlines():
        line = raw.lstrip()
        if not pending and (not line or line[0] in "#!"):
            continue
        trailing = len(line) - len(line.rstrip("\\"))
        if trailing % 2 == 1:  # an odd number of backslashes continues the line
            pending += line[:-1]
            continue
        logical.append(pending + line)
        pending = ""
    if pending:
        logical.append(pending)
    result: dict[str, str] = {}
    for line in logical:
        key, value = _split_key_value(line)
        result[_unescape(key)] = _unescape(value)
    return result


def _split_key_value(line: str) -> tuple[str, str]:
    index = 0
    while index < len(line):
        char = line[index]
        if char == "\\":
            index += 2
            continue
        if char in "=: \t\f":
            break
        index += 1
    key, rest = line[:index], line[index:].lstrip(" \t\f")
    if rest[:1] in ("=", ":"):
        rest = rest[1:].lstrip(" \t\f")
    return key, rest


def _unescape(text: str) -> str:
    if "\\" not in text:
        return text
    out: list[str] = []
    index = 0
    while index < len(text):
        char = text[index]
        if char != "\\" or index + 1 == len(text):
            out.append(char)
            index += 1
            continue
        code = text[index + 1]
        if code == "u" and re.fullmatch(r"[0-9a-fA-F]{4}", text[index + 2 : index + 6]):
            out.append(chr(int(text[index + 2 : index + 6], 16)))
            index += 6
            continue
        out.append(_ESCAPES.get(code, code))
        index += 2
    return "".join(out)


def _catalogues(source: Path) -> list[Path]:
    if source.is_file():
        return [source]
    files = sorted(source.glob("*.sh3f"))
    if not files:
        raise DataError(f"{source}: no .sh3f catalogue found")
    return files


def read_catalogue(
    path: Path,
    member: str = CATALOGUE_FILE,
    missing: str = f"not a furniture catalogue (no {CATALOGUE_FILE})",
    unreadable: str = "cannot read the catalogue",
) -> dict[str, str]:
    """The properties ``member`` of the ZIP ``path`` (a ``.sh3f`` catalogue, or the
    application's jar), bounded; errors name ``path`` with ``missing`` or ``unreadable``.

    Raises:
        DataError: No such member, or an unreadable or oversized archive.
    """
    try:
        with zipfile.ZipFile(path) as archive:
            raw = read_member(archive, member, MAX_CATALOGUE_BYTES)
    except KeyError as err:
        raise DataError(f"{path}: {missing}") from err
    except (OSError, zipfile.BadZipFile) as err:
        raise DataError(f"{path}: {unreadable}: {err}") from err
    return parse_properties(raw.decode("iso-8859-1"))


def _number(value: str | None) -> float:
    try:
        return float(value) if value is not None else 0.0
    except ValueError:
        return 0.0


def scan(source: Path, strict: bool = False) -> Scan:
    """Read the catalogues of ``source`` (a ``.sh3f`` file or a folder of them).

    Args:
        source: A catalogue or a folder of catalogues.
        strict: Raise on an unreadable catalogue instead of reporting it as skipped.

    Returns:
        The scan: one item per model (``other`` for unmatched names), the licence line of
        each catalogue, each model's creator, and the count of dropped light sources.
    """
    items: list[ShapeItem] = []
    licenses: list[dict] = []
    skipped: list[tuple[str, str]] = []
    dropped = {"light_source": 0}
    credits: dict[str, tuple[str, str]] = {}
    pending: list[tuple[str, str, str, str, tuple]] = []  # key, stem, category, path, args
    for path in _catalogues(source):
        try:
            properties = read_catalogue(path)
        except DataError as err:
            if strict:
                raise
            skipped.append((str(path), str(err).removeprefix(f"{path}: ")))
            continue
        pending += catalogue_entries(path, properties, dropped, credits)
        licenses.append(
            {
                "source": path.name,
                "catalogue": properties.get("name", path.stem),
                "license": properties.get("license", "see the catalogue's LICENSE.TXT"),
                "provider": properties.get("provider", ""),
            }
        )
    names = unique_names({key: stem for key, stem, *_ in pending})
    items = [
        ShapeItem(key=key, name=names[key], category=category, path=display, kind="sh3f", args=args)
        for key, _, category, display, args in pending
    ]
    return Scan(items=items, licenses=licenses, dropped=dropped, skipped=skipped, credits=credits)


def catalogue_entries(
    path: Path,
    properties: dict[str, str],
    dropped: dict[str, int],
    credits: dict[str, tuple[str, str]],
) -> list[tuple[str, str, str, str, tuple]]:
    """The models of one catalogue's properties (a ``.sh3f``, or the application's jar).

    Light sources are counted in ``dropped["light_source"]``; each model's creator is put in
    ``credits`` under its key, with the catalogue's file name as the licence source.

    Returns:
        ``(key, id, category, display path, load_model arguments)`` per model.
    """
    entries: dict[int, dict[str, str]] = {}
    found: list[tuple[str, str, str, str, tuple]] = []
    for key, value in properties.items():
        match = re.fullmatch(r"(\w+)#(\d+)", key)
        if match:
            entries.setdefault(int(match.group(2)), {})[match.group(1)] = value
    for number in sorted(entries):
        entry = entries[number]
        model = entry.get("model")
        name = entry.get("name", f"model {number}")
        if not model:
            continue
        size = max(_number(entry.get(k)) for k in ("width", "depth", "height"))
        is_light = any(k.startswith("lightSource") for k in entry)
        if "light source" in name.lower() or (is_light and size < MIN_LIGHT_SIZE_CM):
            dropped["light_source"] += 1
            continue
        member = unquote(model.split("!/")[-1]).lstrip("/")
        rotation = _rotation(entry.get("modelRotation"))
        stem = entry.get("id", f"{path.stem}#{number}")
        key = f"{path.name}:{stem}"
        display = f"{path}:/{member}"
        found.append((key, stem, category_for(name), display, (str(path), member, rotation)))
        credits[key] = (path.name, entry.get("creator", "").strip())
    return found


def _rotation(value: str | None) -> tuple[float, ...] | None:
    """A catalogue ``modelRotation`` (9 numbers, row-major) or None."""
    if not value:
        return None
    numbers = value.split()
    try:
        matrix = tuple(float(n) for n in numbers)
    except ValueError:
        return None
    return matrix if len(matrix) == 9 else None


# A catalogue's largest OBJ is a few MB; a member that inflates beyond these is refused as
# it is read, whatever its header claims (an 820 KB zip bomb once took 9 GB of memory).
MAX_MODEL_BYTES = 256 << 20
MAX_CATALOGUE_BYTES = 16 << 20


def read_member(archive: zipfile.ZipFile, name: str, limit: int) -> bytes:
    """The bytes of ``name`` in ``archive``, refusing more than ``limit`` of them.

    Raises:
        KeyError: No such member.
        DataError: The member declares or inflates to more than ``limit`` bytes.
    """
    info = archive.getinfo(name)
    if info.file_size > limit:
        raise DataError(f"{name} is {info.file_size} bytes unpacked, above the {limit} accepted")
    with archive.open(info) as member:
        data = member.read(limit + 1)  # the directory's size is data too: cap the read
    if len(data) > limit:
        raise DataError(f"{name} inflates beyond the {limit} bytes accepted")
    return data


@functools.lru_cache(maxsize=8)
def _open_archive(path: str, version: tuple[int, int]) -> zipfile.ZipFile:
    return zipfile.ZipFile(path)


def _archive(path: str) -> zipfile.ZipFile:
    """The open ZIP of a catalogue, cached per process so its directory is read once (a
    rewritten file, with another modification time or size, is opened afresh)."""
    stat = os.stat(path)
    return _open_archive(path, (stat.st_mtime_ns, stat.st_size))


def load_model(path: str, member: str, rotation: tuple[float, ...] | None) -> Geometry:
    """Load one catalogue model's OBJ geometry from its ZIP.

    Args:
        path: The ``.sh3f`` file.
        member: The OBJ's path inside the ZIP.
        rotation: The catalogue ``modelRotation`` (row-major 3×3) or None.

    Returns:
        The triangle mesh, rotated upright.
    """
    if not member.lower().endswith(".obj"):
        raise DataError(f"unsupported model format {Path(member).suffix!r} (only OBJ is read)")
    try:
        data = read_member(_archive(path), member, MAX_MODEL_BYTES)
    except KeyError as err:
        raise DataError("the model file is not in the catalogue") from err
    vertices, faces = parse_obj(data)
    if rotation is not None:
        # SweetHome3D applies the matrix to column vectors: v' = R v
        vertices = vertices @ np.asarray(rotation, dtype=np.float64).reshape(3, 3).T
    return Geometry(vertices, faces)


def parse_obj(data: bytes) -> tuple[np.ndarray, np.ndarray]:
    """Parse the geometry of an OBJ file: ``v`` and ``f`` lines; everything else is ignored.

    Polygons are fan-triangulated; faces with fewer than three vertices (which some
    catalogue models contain) are dropped, as trimesh does; negative (relative) indices are
    resolved. Vectorised with numpy: several times faster than trimesh's OBJ loader on the
    catalogue (which mixes triangles, quads and n-gons).

    Args:
        data: The file's bytes.

    Returns:
        ``(vertices, faces)``: float64 ``(V, 3)`` and int64 ``(F, 3)``.

    Raises:
        DataError: Malformed vertex or face lines, or face indices out of range.
    """
    if not data:
        raise DataError("the OBJ file is empty")
    if not data.endswith(b"\n"):
        data += b"\n"
    text = np.frombuffer(data, dtype=np.uint8).copy()
    newlines = np.flatnonzero(text == 10)
    starts = np.concatenate(([0], newlines[:-1] + 1))
    spaced = text[np.minimum(starts + 1, text.size - 1)] <= 32  # "v x", not "vt x"
    is_vertex = (text[starts] == ord("v")) & spaced
    is_face = (text[starts] == ord("f")) & spaced
    n_vertices = int(is_vertex.sum())
    if n_vertices == 0:
        raise DataError("the OBJ file has no vertices")
    text[starts[is_vertex | is_face]] = 32  # blank the keyword: lines become lists of numbers
    kind = np.repeat(is_vertex.astype(np.uint8) + 2 * is_face, newlines - starts + 1)
    values = _numbers(text[kind == 1], np.float64, "vertex")
    width = values.size // n_vertices
    if width * n_vertices != values.size or width < 3:
        raise DataError("malformed vertex lines (expected 'v x y z' on every vertex line)")
    vertices = values.reshape(n_vertices, width)[:, :3]
    if not is_face.any():
        return vertices, np.zeros((0, 3), dtype=np.int64)
    faces_text = text[kind == 2]
    line_ends = np.flatnonzero(faces_text == 10)
    # each "v/vt/vn" reference is one token; its numbers are the tokens once "/" is a space
    refs = _tokens_per_line(faces_text, line_ends)
    numbers_text = np.where(faces_text == ord("/"), np.uint8(32), faces_text)
    numbers = _tokens_per_line(numbers_text, line_ends)
    per_ref = numbers // np.maximum(refs, 1)
    if (per_ref * refs != numbers).any():
        raise DataError("malformed face lines (mixed index formats on one line)")
    values = _numbers(numbers_text, np.int64, "face")
    if values.size != numbers.sum():
        raise DataError("malformed face lines")
    ref_width = np.repeat(per_ref, refs)
    indices = values[np.cumsum(ref_width) - ref_width]  # the vertex index of each reference
    if (indices < 0).any():
        defined = np.repeat(np.cumsum(is_vertex)[is_face], refs)
        indices = np.where(indices < 0, defined + indices, indices - 1)
    else:
        indices = indices - 1
    triangles = np.maximum(refs - 2, 0)
    first = np.cumsum(refs) - refs
    face_of = np.repeat(np.arange(refs.size), triangles)
    step = np.arange(triangles.sum()) - np.repeat(np.cumsum(triangles) - triangles, triangles)
    base = first[face_of]
    faces = np.stack([indices[base], indices[base + step + 1], indices[base + step + 2]], axis=1)
    if faces.size and (faces.min() < 0 or faces.max() >= n_vertices):
        raise DataError("a face refers to a vertex that does not exist")
    return vertices, faces


def _tokens_per_line(text: np.ndarray, line_ends: np.ndarray) -> np.ndarray:
    """Whitespace-separated tokens of each line (``text`` starts with a blank)."""
    space = text <= 32
    token_starts = np.flatnonzero(~space[1:] & space[:-1]) + 1
    return np.diff(np.searchsorted(token_starts, line_ends), prepend=0)


def _numbers(text: np.ndarray, dtype: type, what: str) -> np.ndarray:
    """Parse whitespace-separated numbers; a token that is no number is a DataError."""
    with warnings.catch_warnings():
        # numpy warns (DeprecationWarning) and stops at the first token it cannot parse
        warnings.simplefilter("error", DeprecationWarning)
        try:
            return np.fromstring(text.tobytes(), dtype=dtype, sep=" ")
        except (DeprecationWarning, ValueError) as err:
            raise DataError(f"malformed {what} lines (a value is not a number)") from err
