"""Text point lists: ``.xyz``, ``.pts``, ``.txt``.

One point per line, ``x y z`` first (more columns such as normals or colours are ignored),
separated by spaces, tabs, commas or semicolons; values written with a decimal comma
(``10,1257 19,7358 31,9213``, a European export) are read as decimals when the first line
of values is written so; ``#`` starts a comment, as does ``//`` at a line's
start. A Leica ``.pts`` point count is skipped, and a line of column names is skipped and
orders the columns when it names x, y and z (``z,y,x``, ``id x y z intensity``).
The file is read a block of lines at a time (:mod:`pfnet.io.formats.lines`), at most
:data:`~pfnet.io.formats.lines.MAX_ASCII_LINES` lines of them, blank and comment lines included.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from pfnet.errors import DataError
from pfnet.io.formats.lines import BLOCK_LINES, numbered_lines, parse_block

_SPLIT = re.compile(r"[,;\s]+")
_COMMENTS = ("#", "//")


def _parse_floats(tokens: list[str]) -> list[float] | None:
    if any("_" in t for t in tokens):  # float() reads "1_0" as 10
        return None
    try:
        return [float(t) for t in tokens]
    except ValueError:
        return None


def _tokens(line: str, decimal_comma: bool = False) -> list[str]:
    """The values of one line, comments removed; empty for a blank or comment line.

    With ``decimal_comma`` values are separated by whitespace or ``;`` and a comma is the
    decimal mark (``10,1257 19,7358 31,9213``), read as a point.
    """
    line = line.split("#", 1)[0].strip()
    if not line or line.startswith("//"):
        return []
    if decimal_comma:
        return [t.replace(",", ".") for t in _DECIMAL_COMMA_SPLIT.split(line) if t]
    return [t for t in _SPLIT.split(line) if t]


_DECIMAL_COMMA_SPLIT = re.compile(r"[;\s]+")
# A value written with a decimal comma (a common European export): digits, a comma, digits.
_DECIMAL_COMMA = re.compile(r"[+-]?\d+,\d+(?:[eE][+-]?\d+)?")
_INTEGER = re.compile(r"[+-]?\d+")


def _uses_decimal_comma(line: str) -> bool:
    """Whether a line's values are written with decimal commas: at least three values
    separated by whitespace or ``;``, x y z each digits, one comma, digits (later ones may be
    integers: an intensity). ``1,2,3`` (one value of two commas) and ``1, 2, 3`` are
    comma-separated as before."""
    line = line.split("#", 1)[0].strip()
    values = [t for t in _DECIMAL_COMMA_SPLIT.split(line) if t]
    return (
        len(values) >= 3
        and all(_DECIMAL_COMMA.fullmatch(v) for v in values[:3])
        and all(_DECIMAL_COMMA.fullmatch(v) or _INTEGER.fullmatch(v) for v in values[3:])
    )


def _named_axes(file: Path, number: int, names: list[str]) -> tuple[int, int, int]:
    """The columns of x, y and z in a line of column names (``z,y,x`` reorders them); the
    first three when the names are not coordinates (``a b c``).

    Raises:
        DataError: The names give some of x, y, z but not all.
    """
    lowered = [n.strip("\"'").lower() for n in names]
    found = {axis: lowered.index(axis) for axis in "xyz" if axis in lowered}
    if not found:
        return 0, 1, 2
    if len(found) < 3:
        missing = ", ".join(a for a in "xyz" if a not in found)
        raise DataError(
            f"{file}: line {number} names the columns {' '.join(names[:8])!r} but no "
            f"{missing}; name all of x, y, z or none"
        )
    return found["x"], found["y"], found["z"]


def read_text(file: Path) -> np.ndarray:
    """The points of a text table, float64 ``(N, 3)`` (the file's digits, not float32's):
    columns as a first line of names orders them, decimal commas read when the first line
    of values is written with them."""
    blocks: list[np.ndarray] = []
    block: list[tuple[int, str]] = []
    first: tuple[int, list[str]] | None = None  # the first line with values, if skipped
    seen_values = False
    headers = 0  # lines skipped before the values: a count, then column names, at most
    axes = (0, 1, 2)
    decimal_comma = False
    with open(file, "rb") as fh:
        for number, raw in numbered_lines(fh, file):
            try:  # a byte-order mark is not a point
                line = raw.decode("utf-8-sig" if number == 1 else "utf-8")
            except UnicodeDecodeError:
                raise DataError(f"{file}: not a text file (cannot decode as UTF-8)") from None
            if not seen_values:
                tokens = _tokens(line)
                if not tokens:
                    continue
                leica_count = len(tokens) == 1 and tokens[0].isdigit() and headers == 0
                column_names = all(_parse_floats([token]) is None for token in tokens)
                if leica_count or (column_names and headers < 2):
                    if first is None:
                        first = (number, tokens)
                    headers = 2 if column_names else 1  # names end the header
                    if column_names:
                        axes = _named_axes(file, number, tokens)
                    continue
                # the first line of values decides how values are written
                seen_values = True
                decimal_comma = _uses_decimal_comma(line)
            block.append((number, line))
            if len(block) == BLOCK_LINES:
                blocks.append(_parse(file, block, axes, decimal_comma))
                block = []
    if block:
        blocks.append(_parse(file, block, axes, decimal_comma))
    points = np.concatenate(blocks) if blocks else np.empty((0, 3))
    if len(points) == 0:
        if first is not None and first[1][0].isdigit():  # a lone number is a point, not a count
            raise DataError(f"{file}: line {first[0]} has 1 column(s), expected x y z")
        raise DataError(f"{file}: the file holds no points")
    return points


def _parse(
    file: Path, block: list[tuple[int, str]], axes: tuple[int, int, int], decimal_comma: bool
) -> np.ndarray:
    """The block's points (k, 3), float64, columns ``axes``; names the first bad line."""
    text = "".join(line for _, line in block)
    if decimal_comma:
        text = text.replace(";", " ").replace(",", ".")
    else:
        text = text.replace(",", " ").replace(";", " ")
    table = parse_block(text, max(axes) + 1, _COMMENTS)
    if table is not None:
        return np.ascontiguousarray(table[:, list(axes)])
    points = []  # uneven rows (x y z plus varying attributes) or a bad line: one at a time
    for number, line in block:
        row = _tokens(line, decimal_comma)
        if not row:
            continue
        if len(row) < max(axes) + 1:
            expected = "x y z" if axes == (0, 1, 2) else f"{max(axes) + 1} (as its header names)"
            raise DataError(f"{file}: line {number} has {len(row)} column(s), expected {expected}")
        values = _parse_floats([row[a] for a in axes])
        if values is None:
            shown = " ".join(row[a] for a in axes)
            raise DataError(f"{file}: line {number} is not numeric: {shown!r}")
        points.append(values)
    return np.array(points, dtype=np.float64).reshape(-1, 3)
