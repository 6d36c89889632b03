"""PLY files: ``ascii``, ``binary_little_endian`` and ``binary_big_endian``."""

from __future__ import annotations

import array
import struct
from pathlib import Path

import numpy as np

from pfnet.errors import DataError
from pfnet.io.formats import (
    check_body_span,
    check_point_count,
    float32_columns,
    map_rest,
    read_header,
)
from pfnet.io.formats.lines import MAX_ASCII_LINES, parse_block, row_blocks

# Rows of PLY elements with list properties have variable sizes and are walked one by one in
# Python, reading each list's length (about half a microsecond each; scalars between lists are
# skipped in one step): more lengths than this before the vertices are refused rather than
# taking minutes.
MAX_WALKED_LISTS = 2_000_000

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


def _ply_type(file: Path, name: str) -> str:
    try:
        return _PLY_TYPES[name]
    except KeyError:
        raise DataError(f"{file}: unknown PLY property type {name!r}") from None


def read_ply(file: Path) -> np.ndarray:
    with open(file, "rb") as fh:
        magic = fh.readline(8)  # bounded: a 1 GB sparse file of one "line" took 2.7 GB
        if magic.strip() != b"ply":
            raise DataError(f"{file}: not a PLY file (first line is not 'ply')")
        header = read_header(fh, file, b"end_header")
        elements, fmt = parse_header(file, header)
        vertex_index = [e[0] for e in elements].index("vertex")
        check_point_count(file, elements[vertex_index][1])
        if fmt == "ascii":
            body_line = len(header) + 2  # after "ply" and the header's lines
            return _read_ply_ascii(file, fh, elements, vertex_index, body_line)
        endian = "<" if fmt == "binary_little_endian" else ">"
        return _read_ply_binary(file, map_rest(fh, file), elements, vertex_index, endian)


def parse_header(file: Path, header: list[str]) -> tuple[list, str]:
    """The elements ``(name, count, [(property, dtype, list count dtype or None)])`` and format.

    Raises:
        DataError: A malformed header, or one without a vertex element with ``x y z``.
    """
    fmt = None
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
    return elements, fmt


def _read_ply_ascii(file, fh, elements, vertex_index: int, body_line: int) -> np.ndarray:
    """The vertices of an ASCII body, read a block of lines at a time; later lines unread."""
    needed = sum(count for _, count, _ in elements[: vertex_index + 1])
    if needed > MAX_ASCII_LINES:
        raise DataError(
            f"{file}: ASCII PLY declares {needed} lines up to the vertices; pfnet reads at "
            f"most {MAX_ASCII_LINES} (save large clouds as binary PLY)"
        )
    skip = sum(count for _, count, _ in elements[:vertex_index])
    _, count, props = elements[vertex_index]
    columns = [p[0] for p in props]
    axes = [columns.index("x"), columns.index("y"), columns.index("z")]
    parse = _ply_list_rows if any(p[2] is not None for p in props) else _ply_table_rows
    blocks = row_blocks(
        fh, file, body_line, count, skip=skip, max_lines=MAX_ASCII_LINES, what="PLY data"
    )
    parts = [parse(file, block, props, axes) for block in blocks]
    return np.concatenate(parts) if parts else np.empty((0, 3))


def _ply_table_rows(file, block, props, axes) -> np.ndarray:
    table = parse_block("".join(line for _, line in block), len(props))
    if table is None:
        raise DataError(
            f"{file}: malformed PLY vertex data (non-numeric values, or fewer values than "
            "properties)"
        )
    return float32_columns([table[:, axis] for axis in axes])


def _ply_list_rows(file, block, props, axes) -> np.ndarray:
    """Vertex lines with a list property: each line on its own."""
    rows = np.empty((len(block), 3), dtype=np.float64)
    for i, (number, line) in enumerate(block):
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
            rows[i] = (row["x"], row["y"], row["z"])
        except (ValueError, IndexError):
            raise DataError(f"{file}: malformed PLY vertex line {number}") from None
    return rows


def _read_ply_binary(file, body, elements, vertex_index: int, endian: str) -> np.ndarray:
    offset = 0
    walked = 0
    for name, count, props in elements[: vertex_index + 1]:
        is_vertex = name == "vertex"
        if all(p[2] is None for p in props):
            dtype = np.dtype([(p[0], endian + p[1]) for p in props])
            size = dtype.itemsize * count
            check_body_span(file, offset + size, f"the PLY rows up to the end of element {name!r}")
            if offset + size > len(body):
                raise DataError(
                    f"{file}: truncated PLY data: element {name!r} needs {size} bytes, "
                    f"{max(len(body) - offset, 0)} left"
                )
            if is_vertex:
                table = np.frombuffer(body.read(offset, offset + size), dtype=dtype, count=count)
                return float32_columns([table["x"], table["y"], table["z"]])
            offset += size
            continue
        # Elements with list properties have variable-size rows: walk them one by one. Every
        # row takes at least its scalars and list lengths, so a count the bytes left cannot
        # hold is refused before the walk (a forged count would otherwise loop for hours).
        layout = _row_layout(props, endian)
        walked += count * (len(layout) - 1)  # for all elements together, not each
        if walked > MAX_WALKED_LISTS:
            raise DataError(
                f"{file}: PLY element {name!r} brings the list lengths to read before the "
                f"vertices to {walked}; pfnet reads at most {MAX_WALKED_LISTS} (write the "
                "vertex element first)"
            )
        least = sum(np.dtype(p[2] if p[2] is not None else p[1]).itemsize for p in props)
        check_body_span(file, offset + count * least, f"the PLY rows of element {name!r}")
        if count * least > len(body) - offset:
            raise DataError(
                f"{file}: truncated PLY data: element {name!r} declares {count} rows of at "
                f"least {least} bytes, {max(len(body) - offset, 0)} bytes left"
            )
        offset, starts = _walk_rows(file, body, name, count, layout, offset, record=is_vertex)
        check_body_span(file, offset, f"the PLY rows up to the end of element {name!r}")
        if is_vertex:
            return _gather_columns(body.upto(offset), layout, starts, ("x", "y", "z"))
    raise DataError(f"{file}: PLY file has no vertex element")  # unreachable: checked above


# A row of an element with list properties, as runs of scalars each followed by a list (the
# last run by none): (run bytes, {scalar: (offset in the run, dtype)}, list length struct or
# None, list item bytes).
_Run = tuple[int, dict[str, tuple[int, np.dtype]], struct.Struct | None, int]


def _row_layout(props, endian: str) -> list[_Run]:
    layout: list[_Run] = []
    run, scalars = 0, {}
    for pname, ptype, list_type in props:
        if list_type is None:
            scalars[pname] = (run, np.dtype(endian + ptype))
            run += np.dtype(ptype).itemsize
        else:
            length = struct.Struct(endian + np.dtype(list_type).char)
            layout.append((run, scalars, length, np.dtype(ptype).itemsize))
            run, scalars = 0, {}
    layout.append((run, scalars, None, 0))
    return layout


# Bytes read at a time, doubling, while rows of variable size are walked.
_WALK_CHUNK = 1 << 20


def _walk_rows(file, body, name, count, layout, offset, *, record: bool):
    """The offset after ``count`` rows from ``offset``, and with ``record`` where each run of
    ``layout`` starts in every row (one int64 array per run)."""
    end = len(body)
    data = body.upto(min(offset + _WALK_CHUNK, end))
    starts = [array.array("q") for _ in layout] if record else []
    for _ in range(count):
        for k, (run, _, length, item) in enumerate(layout):
            if record:
                starts[k].append(offset)
            offset += run
            if length is not None:
                if offset + length.size > len(data):
                    if offset + length.size > end:
                        raise DataError(f"{file}: truncated PLY data in element {name!r}")
                    data = body.upto(max(offset + length.size, 2 * len(data)))
                n = length.unpack_from(data, offset)[0]
                if n < 0:
                    raise DataError(f"{file}: negative list length {n} in element {name!r}")
                offset += length.size + n * item
    if offset > end:
        raise DataError(f"{file}: truncated PLY data in element {name!r}")
    return offset, [np.frombuffer(s, dtype=np.int64) for s in starts]


def _gather_columns(body, layout, starts, names) -> np.ndarray:
    """The scalars ``names`` of every walked row, gathered at once (float32 ``(rows, k)``)."""
    data = np.frombuffer(body, dtype=np.uint8)
    columns = []
    for pname in names:
        k = next(k for k, run in enumerate(layout) if pname in run[1])
        at, dtype = layout[k][1][pname]
        index = (starts[k] + at)[:, None] + np.arange(dtype.itemsize)
        columns.append(data[index].view(dtype)[:, 0])
    return float32_columns(columns)


# The vertex properties of a colour, and the largest value of each integer type (its white).
COLOR_PROPERTIES = ("red", "green", "blue")
_COLOR_SCALE = {"u1": 255.0, "u2": 65535.0, "i1": 127.0, "i2": 32767.0, "u4": 2**32 - 1.0}


def read_ply_colors(file: Path) -> np.ndarray | None:
    """The vertex colours of a PLY file (``red green blue``), float32 ``(N, 3)`` in ``[0, 1]``,
    or ``None`` when its vertices have none (``pfnet complete`` writes them as ``uchar``).

    The colour columns are read by the same readers as the coordinates (each format, list
    properties, the same limits), with the colour properties in the place of ``x y z``.

    Raises:
        DataError: As :func:`read_ply`.
    """
    with open(file, "rb") as fh:
        magic = fh.readline(8)
        if magic.strip() != b"ply":
            raise DataError(f"{file}: not a PLY file (first line is not 'ply')")
        header = read_header(fh, file, b"end_header")
        elements, fmt = parse_header(file, header)
        vertex_index = [e[0] for e in elements].index("vertex")
        name, count, props = elements[vertex_index]
        types = {p[0]: p[1] for p in props if p[2] is None}
        if not all(c in types for c in COLOR_PROPERTIES):
            return None
        check_point_count(file, count)
        swap = {**dict(zip(COLOR_PROPERTIES, "xyz")), "x": "\0x", "y": "\0y", "z": "\0z"}
        renamed = [(swap.get(p[0], p[0]), p[1], p[2]) for p in props]
        elements = [*elements[:vertex_index], (name, count, renamed), *elements[vertex_index + 1 :]]
        if fmt == "ascii":
            values = _read_ply_ascii(file, fh, elements, vertex_index, len(header) + 2)
        else:
            endian = "<" if fmt == "binary_little_endian" else ">"
            values = _read_ply_binary(file, map_rest(fh, file), elements, vertex_index, endian)
    scale = np.array([_COLOR_SCALE.get(types[c], 1.0) for c in COLOR_PROPERTIES], np.float32)
    return np.clip(values / scale, 0.0, 1.0).astype(np.float32)
