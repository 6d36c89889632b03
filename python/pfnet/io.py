"""Reading and writing point cloud files.

:func:`read_point_cloud` reads every format users bring to ``pfnet complete`` and
``pfnet evaluate`` into one float32 ``(N, 3)`` array:

* ``.npy`` — a numeric ``(N, C)`` array, ``C >= 3``; the first three columns are x, y, z.
* ``.ply`` — ``ascii``, ``binary_little_endian`` or ``binary_big_endian``; the ``x``, ``y``,
  ``z`` properties of the ``vertex`` element (any numeric type); faces and every other
  element or property are ignored.
* ``.xyz``, ``.pts``, ``.txt`` — one point per line, whitespace- or comma-separated, the
  first three columns are x, y, z. Blank lines and lines starting with ``#`` or ``//`` are
  skipped, as are a first line holding only the point count (the Leica ``.pts`` header) and
  a first line of column names (``x,y,z``).
* ``.pcd`` — ``DATA ascii``, ``binary`` or ``binary_compressed``; the ``x``, ``y``, ``z``
  fields. Points with a NaN coordinate are dropped: PCL marks the invalid points of an
  organised cloud that way.

Every problem (missing file, unknown suffix, truncated or malformed data, no points,
NaN/inf coordinates) raises :class:`~pfnet.errors.DataError` naming the file and the reason.
Writers go through :func:`atomic_path`, so a crash never leaves a half-written file.
"""

from __future__ import annotations

import contextlib
import os
import re
import secrets
from collections.abc import Iterable, Iterator
from pathlib import Path

import numpy as np

from pfnet.errors import ConfigError, DataError

# The geometry core's bound (pfnet._core.MAX_COORDINATE), repeated so that reading a file
# does not load the extension.
MAX_COORDINATE = 1e18
# Rows of PLY elements with list properties are walked one by one in Python (about a second
# per million): more than this many is refused rather than taking minutes.
MAX_WALKED_ROWS = 2_000_000

__all__ = [
    "POINT_CLOUD_SUFFIXES",
    "atomic_path",
    "read_point_cloud",
    "save_npy",
    "write_ply",
]

POINT_CLOUD_SUFFIXES: tuple[str, ...] = (".npy", ".ply", ".xyz", ".pts", ".txt", ".pcd")
"""File suffixes :func:`read_point_cloud` understands (lower case)."""

_PLY_TYPES: dict[str, str] = {
    "char": "i1",
    "int8": "i1",
    "uchar": "u1",
    "uint8": "u1",
    "short": "i2",
    "int16": "i2",
    "ushort": "u2",
    "uint16": "u2",
    "int": "i4",
    "int32": "i4",
    "uint": "u4",
    "uint32": "u4",
    "float": "f4",
    "float32": "f4",
    "double": "f8",
    "float64": "f8",
}


def refuse_overlap(
    out: str | os.PathLike[str], inputs: Iterable[str | os.PathLike[str]], *, flag: str = "--out"
) -> None:
    """Refuse an output location that is, contains or lies inside one of ``inputs``.

    Every command checks this before it changes anything: writing into (or replacing) a
    folder that holds the inputs could overwrite or delete them. Symbolic links are
    resolved, so another spelling of the same place is caught too.

    Raises:
        ConfigError: Naming the flag, the output and the input it overlaps.
    """
    target = Path(out).resolve()
    for item in inputs:
        source = Path(item).resolve()
        if target == source:
            relation = "is"
        elif source.is_relative_to(target):
            relation = "contains"
        elif target.is_relative_to(source):
            relation = "is inside"
        else:
            continue
        raise ConfigError(
            f"{flag} {out} {relation} the input {item}; "
            "write the output to a place apart from the inputs"
        )


def refuse_input_overwrite(
    outputs: Iterable[str | os.PathLike[str]],
    inputs: Iterable[str | os.PathLike[str]],
    *,
    flag: str = "--out",
) -> None:
    """Refuse output files that are input files, or existing folders, before any work.

    Raises:
        ConfigError: Naming the output and the input it would replace.
    """
    sources = {Path(item).resolve(): item for item in inputs}
    for output in outputs:
        path = Path(output)
        if path.is_dir():
            raise ConfigError(f"{flag}: {path} is a folder; name a file to write")
        if path.resolve() in sources:
            raise ConfigError(
                f"{flag}: writing {path} would overwrite the input "
                f"{sources[path.resolve()]}; choose another output"
            )


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike[str]) -> Iterator[Path]:
    """Yield a temporary path beside ``path`` that replaces ``path`` when the block succeeds.

    The temporary name lives in the same folder (so :func:`os.replace` is atomic) and keeps
    the suffix of ``path`` (so writers that pick a format from the suffix, such as
    ``np.save`` or matplotlib's ``savefig``, behave as they would on ``path``). If the block
    raises, the temporary file is removed and ``path`` is left untouched.

    Args:
        path: The final destination; its parent folder must exist.

    Yields:
        The temporary path to write to.
    """
    final = Path(path)
    tmp = final.with_name(f".{final.stem}.{secrets.token_hex(6)}.tmp{final.suffix}")
    try:
        yield tmp
        os.replace(tmp, final)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            tmp.unlink()
        raise


def save_npy(path: str | os.PathLike[str], array: np.ndarray) -> None:
    """Write ``array`` to ``path`` in ``.npy`` format, atomically."""
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as fh:
            np.save(fh, np.asarray(array), allow_pickle=False)


def write_ply(
    path: str | os.PathLike[str], points: np.ndarray, colors: np.ndarray | None = None
) -> None:
    """Write a point cloud as a binary little-endian PLY file, atomically.

    Args:
        path: Destination file.
        points: ``(N, 3)`` coordinates, stored as float32 ``x y z`` vertex properties.
        colors: Optional ``(N, 3)`` colours, either uint8 or floats in ``[0, 1]``; stored as
            uchar ``red green blue``.

    Raises:
        DataError: If the shapes are wrong or the coordinates are not finite.
    """
    pts = np.asarray(points)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise DataError(f"write_ply: points must have shape (N, 3), got {pts.shape} for {path}")
    if not np.issubdtype(pts.dtype, np.number) or not np.isfinite(pts).all():
        raise DataError(f"write_ply: points must be finite numbers for {path}")
    fields = [("x", "<f4"), ("y", "<f4"), ("z", "<f4")]
    if colors is not None:
        rgb = np.asarray(colors)
        if rgb.shape != pts.shape:
            raise DataError(
                f"write_ply: colors must have shape {pts.shape} like points, got {rgb.shape}"
            )
        if rgb.dtype != np.uint8:
            rgb = np.clip(np.rint(np.asarray(rgb, dtype=np.float64) * 255.0), 0, 255)
        fields += [("red", "u1"), ("green", "u1"), ("blue", "u1")]
    vertex = np.empty(len(pts), dtype=fields)
    vertex["x"], vertex["y"], vertex["z"] = pts[:, 0], pts[:, 1], pts[:, 2]
    header = ["ply", "format binary_little_endian 1.0", "comment written by pfnet"]
    header.append(f"element vertex {len(pts)}")
    header += ["property float x", "property float y", "property float z"]
    if colors is not None:
        vertex["red"], vertex["green"], vertex["blue"] = rgb[:, 0], rgb[:, 1], rgb[:, 2]
        header += ["property uchar red", "property uchar green", "property uchar blue"]
    header.append("end_header")
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as fh:
            fh.write(("\n".join(header) + "\n").encode("ascii"))
            fh.write(vertex.tobytes())


def read_point_cloud(path: str | os.PathLike[str]) -> np.ndarray:
    """Read a point cloud file into a float32 ``(N, 3)`` array.

    Args:
        path: A ``.npy``, ``.ply``, ``.xyz``, ``.pts``, ``.txt`` or ``.pcd`` file (see the
            module docstring for what each may hold).

    Returns:
        float32 ``(N, 3)`` array of x, y, z, ``N >= 1``, all finite.

    Raises:
        DataError: Naming ``path`` and the reason: not found, unknown suffix, unreadable or
            malformed, no points, or NaN/inf coordinates.
    """
    file = Path(path)
    suffix = file.suffix.lower()
    if suffix not in POINT_CLOUD_SUFFIXES:
        raise DataError(
            f"{file}: unsupported point cloud suffix {file.suffix!r} "
            f"(expected one of {', '.join(POINT_CLOUD_SUFFIXES)})"
        )
    if not file.exists():
        raise DataError(f"{file}: no such file")
    if not file.is_file():
        raise DataError(f"{file}: not a regular file")
    try:
        if suffix == ".npy":
            points = _read_npy(file)
        elif suffix == ".ply":
            points = _read_ply(file)
        elif suffix == ".pcd":
            points = _read_pcd(file)
        else:
            points = _read_text(file)
    except DataError:
        raise
    except OSError as err:
        raise DataError(f"{file}: cannot read: {err.strerror or err}") from err
    except MemoryError:
        raise DataError(f"{file}: too large to load into memory") from None
    except (ValueError, IndexError, OverflowError, TypeError, RecursionError) as err:
        # The readers' single boundary: whatever hostile bytes make a parser raise is a
        # malformed file, named, so that batch commands skip it and go on.
        raise DataError(f"{file}: malformed {suffix[1:]} file ({err})") from None
    with np.errstate(over="ignore", invalid="ignore"):
        points = np.ascontiguousarray(points, dtype=np.float32)
    if points.shape[0] == 0:
        raise DataError(f"{file}: the file holds no points")
    if not np.isfinite(points).all():
        bad = int((~np.isfinite(points).all(axis=1)).sum())
        raise DataError(f"{file}: {bad} point(s) have NaN or infinite coordinates")
    if np.abs(points).max() > MAX_COORDINATE:
        raise DataError(
            f"{file}: coordinates beyond ±{MAX_COORDINATE:g}, which no distance computation "
            "in float32 survives; scale the cloud down"
        )
    return points


def _first_three_columns(file: Path, array: np.ndarray) -> np.ndarray:
    """Check a 2-D numeric array with at least three columns and return its first three."""
    if array.ndim != 2 or array.shape[1] < 3:
        raise DataError(f"{file}: expected an (N, 3) array of points, got shape {array.shape}")
    if array.dtype == np.bool_ or not np.issubdtype(array.dtype, np.number):
        raise DataError(f"{file}: expected numeric coordinates, got dtype {array.dtype}")
    if np.issubdtype(array.dtype, np.complexfloating):
        raise DataError(f"{file}: expected real coordinates, got dtype {array.dtype}")
    return array[:, :3]


def check_npy_header(name: str, fh, available: int) -> None:
    """Refuse a ``.npy`` stream whose header claims more data than ``available`` bytes.

    Reads the header from ``fh`` (positioned at the start) before numpy allocates anything:
    a forged header claiming 10^12 points made ``np.load`` fail with ``MemoryError``.

    Raises:
        DataError: Naming ``name``, the declared shape and the bytes there are.
    """
    from numpy.lib import format as npy_format

    try:
        version = npy_format.read_magic(fh)
        if version == (1, 0):
            shape, _, dtype = npy_format.read_array_header_1_0(fh)
        else:
            shape, _, dtype = npy_format.read_array_header_2_0(fh)
    except (ValueError, EOFError) as err:
        raise DataError(f"{name}: not a valid .npy array file ({err})") from None
    needed = int(np.prod(shape, dtype=object)) * dtype.itemsize
    if needed > available - fh.tell():
        raise DataError(
            f"{name}: the .npy header declares shape {shape} ({needed} bytes) but the file "
            f"holds {max(available - fh.tell(), 0)} bytes of data"
        )


def _read_npy(file: Path) -> np.ndarray:
    with open(file, "rb") as fh:
        check_npy_header(str(file), fh, file.stat().st_size)
    try:
        array = np.load(file, allow_pickle=False)
    except ValueError as err:  # object arrays, bad headers, truncated data
        raise DataError(f"{file}: not a valid .npy array file ({err})") from err
    except EOFError as err:
        raise DataError(f"{file}: not a valid .npy array file (empty or truncated)") from err
    if not isinstance(array, np.ndarray):
        raise DataError(f"{file}: not a .npy array file")
    return _first_three_columns(file, array)


# --------------------------------------------------------------------------- text formats

_SPLIT = re.compile(r"[,\s]+")


def _parse_floats(tokens: list[str]) -> list[float] | None:
    try:
        return [float(t) for t in tokens]
    except ValueError:
        return None


def _read_text(file: Path) -> np.ndarray:
    try:
        text = file.read_text(encoding="utf-8")
    except UnicodeDecodeError as err:
        raise DataError(f"{file}: not a text file (cannot decode as UTF-8)") from err
    rows: list[list[str]] = []
    line_numbers: list[int] = []
    for number, raw in enumerate(text.splitlines(), start=1):
        line = raw.strip()
        if not line or line.startswith(("#", "//")):
            continue
        if "_" in line:  # float() would read "1_0" as 10
            raise DataError(f"{file}: line {number} is not numeric: {line[:60]!r}")
        rows.append([t for t in _SPLIT.split(line) if t])
        line_numbers.append(number)
    if rows:
        first = rows[0]
        if len(first) == 1 and first[0].isdigit() and len(rows) > 1:
            # Leica .pts: the first line is the number of points.
            rows, line_numbers = rows[1:], line_numbers[1:]
        elif _parse_floats(first) is None:
            # A header of column names such as "x,y,z".
            rows, line_numbers = rows[1:], line_numbers[1:]
    if not rows:
        raise DataError(f"{file}: the file holds no points")
    widths = {len(r) for r in rows}
    if len(widths) == 1 and min(widths) >= 3:
        # Fast path: every line has the same number of columns.
        try:
            table = np.array([t for r in rows for t in r], dtype=np.float64)
            return table.reshape(len(rows), -1)[:, :3]
        except ValueError:
            pass  # fall through to find and name the bad line
    points = np.empty((len(rows), 3), dtype=np.float64)
    for i, (row, number) in enumerate(zip(rows, line_numbers, strict=True)):
        if len(row) < 3:
            raise DataError(f"{file}: line {number} has {len(row)} column(s), expected x y z")
        values = _parse_floats(row[:3])
        if values is None:
            raise DataError(f"{file}: line {number} is not numeric: {' '.join(row[:3])!r}")
        points[i] = values
    return points


# --------------------------------------------------------------------------------- PLY


def _read_header(fh, file: Path, end: bytes, max_lines: int = 10_000) -> list[str]:
    """Read text header lines up to and including ``end``; return them without it."""
    lines: list[str] = []
    for _ in range(max_lines):
        raw = fh.readline()
        if not raw:
            raise DataError(f"{file}: truncated header (no {end.decode()!r} line)")
        try:
            line = raw.decode("ascii").strip()
        except UnicodeDecodeError as err:
            raise DataError(f"{file}: header is not ASCII text") from err
        if raw.strip().startswith(end):
            lines.append(line)
            return lines
        lines.append(line)
    raise DataError(f"{file}: header longer than {max_lines} lines")


def _ply_type(file: Path, name: str) -> str:
    try:
        return _PLY_TYPES[name]
    except KeyError:
        raise DataError(f"{file}: unknown PLY property type {name!r}") from None


def _read_ply(file: Path) -> np.ndarray:
    with open(file, "rb") as fh:
        magic = fh.readline()
        if magic.strip() != b"ply":
            raise DataError(f"{file}: not a PLY file (first line is not 'ply')")
        header = _read_header(fh, file, b"end_header")
        body = fh.read()
    fmt = None
    # Each element: (name, count, [(prop name, dtype, list count dtype or None)])
    elements: list[tuple[str, int, list[tuple[str, str, str | None]]]] = []
    for line in header[:-1]:
        words = line.split()
        if not words or words[0] in ("comment", "obj_info"):
            continue
        if words[0] == "format":
            if len(words) < 2 or words[1] not in (
                "ascii",
                "binary_little_endian",
                "binary_big_endian",
            ):
                raise DataError(f"{file}: unsupported PLY format line {line!r}")
            fmt = words[1]
        elif words[0] == "element":
            if len(words) != 3 or not words[2].isdigit() or len(words[2]) > 15:
                raise DataError(f"{file}: malformed PLY element line {line[:80]!r}")
            elements.append((words[1], int(words[2]), []))
        elif words[0] == "property":
            if not elements:
                raise DataError(f"{file}: PLY property before any element: {line!r}")
            if len(words) == 5 and words[1] == "list":
                prop = (words[4], _ply_type(file, words[3]), _ply_type(file, words[2]))
                if prop[2][0] not in "iu":
                    raise DataError(f"{file}: PLY list length type must be an integer: {line!r}")
            elif len(words) == 3:
                prop = (words[2], _ply_type(file, words[1]), None)
            else:
                raise DataError(f"{file}: malformed PLY property line {line!r}")
            if prop[0] in [p[0] for p in elements[-1][2]]:
                raise DataError(f"{file}: PLY property {prop[0]!r} declared twice: {line!r}")
            elements[-1][2].append(prop)
        else:
            raise DataError(f"{file}: unexpected PLY header line {line!r}")
    if fmt is None:
        raise DataError(f"{file}: PLY header has no format line")
    names = [e[0] for e in elements]
    if "vertex" not in names:
        raise DataError(f"{file}: PLY file has no vertex element")
    vertex_index = names.index("vertex")
    props = elements[vertex_index][2]
    prop_names = [p[0] for p in props]
    for axis in ("x", "y", "z"):
        if axis not in prop_names:
            raise DataError(f"{file}: PLY vertex element has no {axis!r} property")
    for name, _dtype, list_type in props:
        if name in ("x", "y", "z") and list_type is not None:
            raise DataError(f"{file}: PLY vertex property {name!r} is a list")
    if fmt == "ascii":
        return _read_ply_ascii(file, body, elements, vertex_index)
    endian = "<" if fmt == "binary_little_endian" else ">"
    return _read_ply_binary(file, body, elements, vertex_index, endian)


def _read_ply_ascii(file, body: bytes, elements, vertex_index: int) -> np.ndarray:
    lines = body.decode("ascii", errors="replace").splitlines()
    lines = [ln for ln in lines if ln.strip()]
    start = sum(count for _, count, _ in elements[:vertex_index])
    name, count, props = elements[vertex_index]
    if len(lines) < start + count:
        raise DataError(
            f"{file}: truncated PLY data: expected {start + count} element lines before the "
            f"end of the vertices, found {len(lines)}"
        )
    columns = [p[0] for p in props]
    if count == 0:
        return np.empty((0, 3))
    if any(p[2] is not None for p in props):
        # A list property in the vertex element: parse each line on its own.
        out = np.empty((count, 3), dtype=np.float64)
        for i, line in enumerate(lines[start : start + count]):
            values = line.split()
            pos, row = 0, {}
            try:
                for pname, _, list_type in props:
                    if list_type is None:
                        row[pname] = float(values[pos])
                        pos += 1
                    else:
                        length = int(values[pos])
                        if length < 0:
                            raise ValueError
                        pos += length + 1
                out[i] = (row["x"], row["y"], row["z"])
            except (ValueError, IndexError):
                raise DataError(f"{file}: malformed PLY vertex line {start + i + 1}") from None
        return out
    try:
        table = np.array([line.split() for line in lines[start : start + count]], dtype=np.float64)
    except ValueError:
        raise DataError(
            f"{file}: malformed PLY vertex data (non-numeric values or uneven rows)"
        ) from None
    if table.ndim != 2 or table.shape[1] < len(columns):
        raise DataError(f"{file}: PLY vertex lines have fewer values than properties")
    return table[:, [columns.index("x"), columns.index("y"), columns.index("z")]]


def _read_ply_binary(file, body: bytes, elements, vertex_index: int, endian: str) -> np.ndarray:
    offset = 0
    for name, count, props in elements[: vertex_index + 1]:
        is_vertex = name == "vertex"
        if all(p[2] is None for p in props):
            dtype = np.dtype([(p[0], endian + p[1]) for p in props])
            size = dtype.itemsize * count
            if offset + size > len(body):
                raise DataError(
                    f"{file}: truncated PLY data: element {name!r} needs {size} bytes, "
                    f"{max(len(body) - offset, 0)} left"
                )
            if is_vertex:
                table = np.frombuffer(body, dtype=dtype, count=count, offset=offset)
                return np.stack([table["x"], table["y"], table["z"]], axis=1).astype(np.float64)
            offset += size
            continue
        # Elements with list properties have variable-size rows: walk them one by one. Every
        # row takes at least its scalars and list lengths, so a count the bytes left cannot
        # hold is refused before the walk (a forged count would otherwise loop for hours).
        if count > MAX_WALKED_ROWS:
            raise DataError(
                f"{file}: PLY element {name!r} has {count} rows with list properties before "
                f"the vertices are read; pfnet walks at most {MAX_WALKED_ROWS} (write the "
                "vertex element first)"
            )
        least = sum(np.dtype(p[2] if p[2] is not None else p[1]).itemsize for p in props)
        if count * least > len(body) - offset:
            raise DataError(
                f"{file}: truncated PLY data: element {name!r} declares {count} rows of at "
                f"least {least} bytes, {max(len(body) - offset, 0)} bytes left"
            )
        coords = np.empty((count, 3), dtype=np.float64) if is_vertex else None
        for i in range(count):
            row: dict[str, float] = {}
            for pname, ptype, list_type in props:
                if list_type is not None:
                    ldt = np.dtype(endian + list_type)
                    if offset + ldt.itemsize > len(body):
                        raise DataError(f"{file}: truncated PLY data in element {name!r}")
                    n = int(np.frombuffer(body, ldt, 1, offset)[0])
                    if n < 0:
                        raise DataError(f"{file}: negative list length {n} in element {name!r}")
                    offset += ldt.itemsize + n * np.dtype(ptype).itemsize
                else:
                    pdt = np.dtype(endian + ptype)
                    if offset + pdt.itemsize > len(body):
                        raise DataError(f"{file}: truncated PLY data in element {name!r}")
                    if is_vertex:
                        row[pname] = float(np.frombuffer(body, pdt, 1, offset)[0])
                    offset += pdt.itemsize
            if coords is not None:
                coords[i] = (row["x"], row["y"], row["z"])
        if offset > len(body):
            raise DataError(f"{file}: truncated PLY data in element {name!r}")
        if coords is not None:
            return coords
    raise DataError(f"{file}: PLY file has no vertex element")  # unreachable: checked above


# --------------------------------------------------------------------------------- PCD

_PCD_TYPES = {("F", 4): "f4", ("F", 8): "f8"}
_PCD_TYPES.update({("I", s): f"i{s}" for s in (1, 2, 4, 8)})
_PCD_TYPES.update({("U", s): f"u{s}" for s in (1, 2, 4, 8)})


def _read_pcd(file: Path) -> np.ndarray:
    with open(file, "rb") as fh:
        header = _read_header(fh, file, b"DATA")
        body = fh.read()
    fields: dict[str, list[str]] = {}
    for line in header:
        words = line.split()
        if not words or words[0].startswith("#"):
            continue
        fields[words[0].upper()] = words[1:]
    for key in ("FIELDS", "SIZE", "TYPE", "DATA"):
        if key not in fields or not fields[key]:
            raise DataError(f"{file}: PCD header has no {key} line")
    names = fields["FIELDS"]
    n = len(names)
    counts = fields.get("COUNT", ["1"] * n)
    if not (len(fields["SIZE"]) == len(fields["TYPE"]) == len(counts) == n):
        raise DataError(f"{file}: PCD header FIELDS, SIZE, TYPE and COUNT differ in length")
    try:
        sizes = [int(s) for s in fields["SIZE"]]
        counts_i = [int(c) for c in counts]
        if "POINTS" in fields:
            n_points = int(fields["POINTS"][0])
        else:
            width, height = int(fields["WIDTH"][0]), int(fields["HEIGHT"][0])
            n_points = width * height if min(width, height) >= 0 else -1
    except (ValueError, KeyError, IndexError):
        raise DataError(f"{file}: PCD header has a malformed SIZE/COUNT/POINTS line") from None
    if min(counts_i) < 1 or n_points < 0:
        raise DataError(f"{file}: PCD header has a COUNT below 1 or a negative point count")
    dtypes = []
    for name, size, kind in zip(names, sizes, fields["TYPE"], strict=True):
        key = (kind.upper(), size)
        if key not in _PCD_TYPES:
            raise DataError(f"{file}: unsupported PCD type {kind}{size} for field {name!r}")
        dtypes.append("<" + _PCD_TYPES[key])
    for axis in ("x", "y", "z"):
        if axis not in names:
            raise DataError(f"{file}: PCD file has no {axis!r} field")
    columns = [names.index(a) for a in ("x", "y", "z")]
    mode = fields["DATA"][0].lower()
    if mode == "ascii":
        points = _read_pcd_ascii(file, body, names, counts_i, n_points, columns)
    elif mode == "binary":
        dtype = np.dtype(
            [
                (f"f{i}", dt, (c,) if c > 1 else ())
                for i, (dt, c) in enumerate(zip(dtypes, counts_i, strict=True))
            ]
        )
        if len(body) < dtype.itemsize * n_points:
            raise DataError(
                f"{file}: truncated PCD data: {n_points} points need "
                f"{dtype.itemsize * n_points} bytes, found {len(body)}"
            )
        table = np.frombuffer(body, dtype=dtype, count=n_points)
        points = np.stack([_pcd_first(table[f"f{c}"]) for c in columns], axis=1)
    elif mode == "binary_compressed":
        points = _read_pcd_compressed(file, body, dtypes, counts_i, n_points, columns)
    else:
        raise DataError(f"{file}: unsupported PCD DATA mode {mode!r}")
    points = np.asarray(points, dtype=np.float64)
    return points[np.isfinite(points).all(axis=1)] if np.isnan(points).any() else points


def _pcd_first(column: np.ndarray) -> np.ndarray:
    return column[:, 0] if column.ndim == 2 else column


def _read_pcd_ascii(file, body, names, counts, n_points, columns) -> np.ndarray:
    starts = np.cumsum([0, *counts])
    if n_points == 0:
        return np.empty((0, 3))
    lines = [ln.split() for ln in body.decode("ascii", errors="replace").splitlines()]
    lines = [ln for ln in lines if ln]
    if len(lines) < n_points:
        raise DataError(f"{file}: truncated PCD data: {n_points} points, {len(lines)} lines")
    try:
        table = np.array(lines[:n_points], dtype=np.float64)
    except ValueError:
        raise DataError(f"{file}: malformed PCD ascii data (non-numeric or uneven rows)") from None
    if n_points and (table.ndim != 2 or table.shape[1] < starts[-1]):
        raise DataError(f"{file}: PCD ascii rows have fewer values than the FIELDS declare")
    return table.reshape(n_points, -1)[:, [starts[c] for c in columns]]


def _read_pcd_compressed(file, body, dtypes, counts, n_points, columns) -> np.ndarray:
    if len(body) < 8:
        raise DataError(f"{file}: truncated PCD binary_compressed data")
    compressed, raw = (int(v) for v in np.frombuffer(body, "<u4", 2))
    if len(body) < 8 + compressed:
        raise DataError(f"{file}: truncated PCD binary_compressed data")
    # binary_compressed stores the data field by field (all x, then all y, ...).
    offsets = np.cumsum(
        [0] + [np.dtype(d).itemsize * c * n_points for d, c in zip(dtypes, counts, strict=True)]
    )
    if raw != offsets[-1]:  # checked before decompressing anything
        raise DataError(
            f"{file}: PCD binary_compressed data declares {raw} bytes, the header's "
            f"{n_points} points need {int(offsets[-1])}"
        )
    data = _lzf_decompress(file, body[8 : 8 + compressed], raw)
    out = []
    for c in columns:
        block = np.frombuffer(data, dtypes[c], n_points * counts[c], int(offsets[c]))
        out.append(block.reshape(n_points, counts[c])[:, 0])
    return np.stack(out, axis=1)


def _lzf_decompress(file: Path, src: bytes, size: int) -> bytes:
    """Decompress LZF (liblzf's format, used by PCL's ``binary_compressed``)."""
    out = bytearray()
    i, n = 0, len(src)
    try:
        while i < n:
            ctrl = src[i]
            i += 1
            if ctrl < 32:  # literal run of ctrl + 1 bytes
                out += src[i : i + ctrl + 1]
                i += ctrl + 1
            else:  # back reference
                length = ctrl >> 5
                if length == 7:
                    length += src[i]
                    i += 1
                ref = len(out) - ((ctrl & 0x1F) << 8) - src[i] - 1
                i += 1
                if ref < 0:
                    raise IndexError
                length += 2
                if ref + length <= len(out):  # the common case: copy a slice at once
                    out += out[ref : ref + length]
                else:  # overlapping run: byte by byte
                    for k in range(length):
                        out.append(out[ref + k])
            if len(out) > size:  # never expand beyond the declared size
                raise DataError(
                    f"{file}: corrupt PCD binary_compressed data (expands beyond the "
                    f"declared {size} bytes)"
                )
    except IndexError:
        raise DataError(f"{file}: corrupt PCD binary_compressed data") from None
    if len(out) != size:
        raise DataError(
            f"{file}: corrupt PCD binary_compressed data ({len(out)} bytes, expected {size})"
        )
    return bytes(out)
