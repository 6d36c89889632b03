"""The readers behind :func:`pfnet.io.read_point_cloud`, one module per family of formats.

Each reader takes a path, returns a numeric ``(N, 3)`` array (any float dtype) and raises
:class:`~pfnet.errors.DataError` naming the file for what it recognises as wrong; anything
else a parser raises on hostile bytes is turned into a named "malformed file" error by
``read_point_cloud``, the readers' single error boundary. Sizes a file declares are checked
against the bytes it has before anything is allocated or walked.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from pfnet.errors import DataError
from pfnet.formats.lines import MAX_LINE_BYTES

# The most points one input cloud may hold (``complete``, ``evaluate``, ``render``): real scans
# run to a few tens of millions of points, and 50,000,000 points take 600 MB as float32. A
# header declaring more is refused before anything is read (a 4 KB sparse file declaring 10^8
# honest vertices took 4.7 GB).
MAX_CLOUD_POINTS = 50_000_000


def check_point_count(file: Path, count: int) -> None:
    """Refuse a declared number of points above :data:`MAX_CLOUD_POINTS`."""
    if count > MAX_CLOUD_POINTS:
        raise DataError(
            f"{file}: declares {count} points; pfnet reads at most {MAX_CLOUD_POINTS:,} points "
            "a cloud (thin the cloud first)"
        )


def float32_columns(columns: list[np.ndarray]) -> np.ndarray:
    """The columns side by side as one float32 ``(N, k)`` array, converted one column at a time.

    No float64 copy of the whole cloud is made; values beyond float32's range become ``inf``,
    which ``read_point_cloud`` then refuses by name.
    """
    out = np.empty((len(columns[0]), len(columns)), dtype=np.float32)
    with np.errstate(over="ignore", invalid="ignore"):
        for k, column in enumerate(columns):
            out[:, k] = column
    return out


def read_header(fh, file: Path, end: bytes, max_lines: int = 10_000) -> list[str]:
    """Read text header lines up to and including ``end``; return them without it."""
    lines: list[str] = []
    for number in range(1, max_lines + 1):
        raw = fh.readline(MAX_LINE_BYTES + 1)
        if not raw:
            raise DataError(f"{file}: truncated header (no {end.decode()!r} line)")
        if len(raw) > MAX_LINE_BYTES:  # a 3 GB sparse file of one "line" took 6.4 GB
            raise DataError(f"{file}: header line {number} is longer than {MAX_LINE_BYTES} bytes")
        try:
            line = raw.decode("ascii").strip()
        except UnicodeDecodeError as err:
            raise DataError(f"{file}: header is not ASCII text") from err
        if raw.strip().startswith(end):
            lines.append(line)
            return lines
        lines.append(line)
    raise DataError(f"{file}: header longer than {max_lines} lines")


def map_rest(fh) -> np.ndarray | bytes:
    """The rest of an open file as a read-only memory map (bytes when nothing is left).

    Binary bodies are read through the map: only the pages a reader touches are loaded, so
    a file padded with gigabytes after its points (or a sparse one) costs no memory.
    """
    start = fh.tell()
    if os.fstat(fh.fileno()).st_size <= start:
        return b""
    return np.memmap(fh, dtype=np.uint8, mode="r", offset=start)


# Columns a point table may have (x y z, normals, colours, intensity, labels, ...).
MAX_COLUMNS = 16


def first_three_columns(file: Path, array: np.ndarray) -> np.ndarray:
    """Check a 2-D numeric array with at least three columns and return its first three."""
    if array.ndim != 2 or array.shape[1] < 3:
        raise DataError(f"{file}: expected an (N, 3) array of points, got shape {array.shape}")
    if array.shape[1] > MAX_COLUMNS:
        # x, y, z plus a few attributes (normals, colours, intensity) is a point cloud;
        # a (3, 300) array is one stored transposed, a (1000, 100) one a table of features
        hint = "is the array transposed?" if array.shape[0] <= MAX_COLUMNS else "not points?"
        raise DataError(
            f"{file}: shape {array.shape} is {array.shape[1]} columns of {array.shape[0]} rows; "
            f"points are rows (N, 3) with at most {MAX_COLUMNS - 3} attribute columns: {hint}"
        )
    if array.dtype.kind not in "fiuc":  # not bool, not timedelta64 (an integer to numpy)
        raise DataError(f"{file}: expected numeric coordinates, got dtype {array.dtype}")
    if np.issubdtype(array.dtype, np.complexfloating):
        raise DataError(f"{file}: expected real coordinates, got dtype {array.dtype}")
    return array[:, :3]
