"""Text point lists: ``.xyz``, ``.pts``, ``.txt``."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from pfnet.errors import DataError

_SPLIT = re.compile(r"[,\s]+")


def _parse_floats(tokens: list[str]) -> list[float] | None:
    if any("_" in t for t in tokens):  # float() reads "1_0" as 10
        return None
    try:
        return [float(t) for t in tokens]
    except ValueError:
        return None


def read_text(file: Path) -> np.ndarray:
    try:
        text = file.read_text(encoding="utf-8-sig")  # a byte-order mark is not a point
    except UnicodeDecodeError as err:
        raise DataError(f"{file}: not a text file (cannot decode as UTF-8)") from err
    rows: list[list[str]] = []
    line_numbers: list[int] = []
    for number, raw in enumerate(text.splitlines(), start=1):
        line = raw.split("#", 1)[0].strip()  # comments, whole-line or after the values
        if not line or line.startswith("//"):
            continue
        rows.append([t for t in _SPLIT.split(line) if t])
        line_numbers.append(number)
    if rows:
        first = rows[0]
        if len(first) == 1 and first[0].isdigit() and len(rows) > 1:
            # Leica .pts: the first line is the number of points.
            rows, line_numbers = rows[1:], line_numbers[1:]
        elif all(_parse_floats([token]) is None for token in first):
            # A header of column names such as "x,y,z" (no value in it is a number).
            rows, line_numbers = rows[1:], line_numbers[1:]
    if not rows:
        raise DataError(f"{file}: the file holds no points")
    widths = {len(r) for r in rows}
    if len(widths) == 1 and min(widths) >= 3 and not any("_" in t for r in rows for t in r):
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
