"""Text point lists: ``.xyz``, ``.pts``, ``.txt``.

One point per line, ``x y z`` first (more columns such as normals or colours are ignored),
separated by spaces, tabs or commas; ``#`` starts a comment, as does ``//`` at a line's
start. A first line of column names ("x,y,z") or a Leica ``.pts`` point count is skipped.
The file is read a block of lines at a time (:mod:`pfnet.formats.lines`), at most
:data:`~pfnet.formats.lines.MAX_ASCII_LINES` lines of them, blank and comment lines included.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from pfnet.errors import DataError
from pfnet.formats import float32_columns
from pfnet.formats.lines import BLOCK_LINES, numbered_lines, parse_block

_SPLIT = re.compile(r"[,\s]+")
_COMMENTS = ("#", "//")


def _parse_floats(tokens: list[str]) -> list[float] | None:
    if any("_" in t for t in tokens):  # float() reads "1_0" as 10
        return None
    try:
        return [float(t) for t in tokens]
    except ValueError:
        return None


def _tokens(line: str) -> list[str]:
    """The values of one line, comments removed; empty for a blank or comment line."""
    line = line.split("#", 1)[0].strip()
    if not line or line.startswith("//"):
        return []
    return [t for t in _SPLIT.split(line) if t]


def read_text(file: Path) -> np.ndarray:
    blocks: list[np.ndarray] = []
    block: list[tuple[int, str]] = []
    first: tuple[int, list[str]] | None = None  # the first line with values, if skipped
    seen_values = False
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
                seen_values = True
                leica_count = len(tokens) == 1 and tokens[0].isdigit()
                column_names = all(_parse_floats([token]) is None for token in tokens)
                if leica_count or column_names:
                    first = (number, tokens)
                    continue
            block.append((number, line))
            if len(block) == BLOCK_LINES:
                blocks.append(_parse(file, block))
                block = []
    if block:
        blocks.append(_parse(file, block))
    points = np.concatenate(blocks) if blocks else np.empty((0, 3))
    if len(points) == 0:
        if first is not None and first[1][0].isdigit():  # a lone number is a point, not a count
            raise DataError(f"{file}: line {first[0]} has 1 column(s), expected x y z")
        raise DataError(f"{file}: the file holds no points")
    return points


def _parse(file: Path, block: list[tuple[int, str]]) -> np.ndarray:
    """The block's points (k, 3); names the first bad line."""
    text = "".join(line for _, line in block).replace(",", " ")
    table = parse_block(text, 3, _COMMENTS)
    if table is not None:
        return float32_columns([table[:, 0], table[:, 1], table[:, 2]])
    points = []  # uneven rows (x y z plus varying attributes) or a bad line: one at a time
    for number, line in block:
        row = _tokens(line)
        if not row:
            continue
        if len(row) < 3:
            raise DataError(f"{file}: line {number} has {len(row)} column(s), expected x y z")
        values = _parse_floats(row[:3])
        if values is None:
            raise DataError(f"{file}: line {number} is not numeric: {' '.join(row[:3])!r}")
        points.append(values)
    return np.array(points, dtype=np.float64).reshape(-1, 3)
