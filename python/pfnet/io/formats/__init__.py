"""The readers behind :func:`pfnet.io.clouds.read_point_cloud`, one module per family of formats.

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
from pfnet.io.formats.lines import MAX_LINE_BYTES

# The most points one input cloud may hold (``complete``, ``evaluate``, ``render``): real scans
# run to a few tens of millions of points, and 50,000,000 points take 600 MB as float32. A
# header declaring more is refused before anything is read (a 4 KB sparse file declaring 10^8
# honest vertices took 4.7 GB).
MAX_CLOUD_POINTS = 50_000_000


# Bytes of a binary body (PLY, PCD) walked to reach the points: the rows up to the last vertex.
# Reading x, y, z touches a page per row, so a row's width costs time and page cache even when
# only 12 bytes of it are used: 500,000 sparse rows of 8 KB took 2.2 s and 3.9 GB of cache,
# and at the point limit the same rows would span 400 GB. 2 GiB holds 50,000,000 points of
# x y z, normals and colour in float32 (28 bytes) or 44,000,000 of them in float64.
MAX_BODY_BYTES = 1 << 31


def check_body_span(file: Path, span: int, what: str) -> None:
    """Refuse a binary body whose rows up to the points span more than :data:`MAX_BODY_BYTES`."""
    if span > MAX_BODY_BYTES:
        raise DataError(
            f"{file}: {what} span {span} bytes; pfnet reads at most {MAX_BODY_BYTES:,} bytes "
            "of binary rows (drop the unused attributes, or thin the cloud)"
        )


def check_point_count(file: Path, count: int) -> None:
    """Refuse a declared number of points above :data:`MAX_CLOUD_POINTS`."""
    if count > MAX_CLOUD_POINTS:
        raise DataError(
            f"{file}: declares {count} points; pfnet reads at most {MAX_CLOUD_POINTS:,} points "
            "a cloud (thin the cloud first)"
        )


def float32_columns(columns: list[np.ndarray]) -> np.ndarray:
    """The columns side by side as one ``(N, k)`` array, converted one column at a time:
    float32, or float64 when a column holds more digits than float32 keeps (float64, 32- and
    64-bit integers, text parsed as float64), which ``read_point_cloud`` keeps when asked.

    No float64 copy of a float32 cloud is made; values beyond float32's range become ``inf``,
    which ``read_point_cloud`` then refuses by name.
    """
    wide = any(
        (c.dtype.kind == "f" and c.dtype.itemsize >= 8)
        or (c.dtype.kind in "iu" and c.dtype.itemsize >= 4)
        for c in columns
    )
    out = np.empty((len(columns[0]), len(columns)), dtype=np.float64 if wide else np.float32)
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


class FileBody:
    """The rest of an open file from its current position, read into memory as a reader asks.

    Never memory-mapped: a mapped body that shrinks while it is read (a file being rewritten
    or truncated) kills the process with SIGBUS, no message and the other inputs lost (issue
    36). The size is taken once, when the body is opened; a reader checks what it needs
    against ``len(body)`` and then reads just that (:meth:`read` for a span, :meth:`upto`
    for a walk from the start), so a file padded with gigabytes after its points costs no
    memory. A file that ends before the size it had is refused naming the file.
    """

    def __init__(self, fh, file: Path) -> None:
        self._fd = fh.fileno()
        self._start = fh.tell()
        self.file = file
        self.size = max(os.fstat(self._fd).st_size - self._start, 0)
        self._data = bytearray()

    def __len__(self) -> int:
        return self.size

    def _fill(self, buffer: bytearray, have: int, start: int) -> None:
        view = memoryview(buffer)
        try:
            while have < len(buffer):
                got = os.preadv(self._fd, [view[have:]], self._start + start + have)
                if got == 0:
                    raise DataError(
                        f"{self.file}: the file changed while pfnet read it (it held "
                        f"{self._start + self.size} bytes when opened, ends at "
                        f"{self._start + start + have} now); read it again once it is written"
                    )
                have += got
        finally:
            view.release()

    def read(self, start: int, stop: int) -> bytearray:
        """Bytes ``start:stop`` of the body (``stop`` at most ``len(body)``)."""
        stop = min(stop, self.size)
        buffer = bytearray(max(stop - start, 0))
        self._fill(buffer, 0, start)
        return buffer

    def upto(self, stop: int) -> bytearray:
        """Bytes ``0:stop`` of the body, at least (grown from what was read before, never
        resized in place, so arrays viewing an earlier result stay valid)."""
        stop = min(stop, self.size)
        have = len(self._data)
        if have < stop:
            grown = bytearray(stop)
            grown[:have] = self._data
            self._fill(grown, have, 0)
            self._data = grown
        return self._data


def map_rest(fh, file: Path) -> FileBody:
    """The rest of an open file as a :class:`FileBody` (read on demand, never mapped)."""
    return FileBody(fh, file)


# Columns a point table may have (x y z, normals, colours, intensity, labels, ...).
MAX_COLUMNS = 16


def check_table(file: Path, shape: tuple[int, ...], dtype: np.dtype) -> None:
    """Refuse a shape and dtype that are not a numeric ``(N, 3..MAX_COLUMNS)`` point table.

    Takes the declared shape and dtype, so a ``.npy`` header is checked before its data is
    loaded.
    """
    shape = tuple(shape)
    if len(shape) != 2 or shape[1] < 3:
        raise DataError(f"{file}: expected an (N, 3) array of points, got shape {shape}")
    if shape[1] > MAX_COLUMNS:
        # x, y, z plus a few attributes (normals, colours, intensity) is a point cloud;
        # a (3, 300) array is one stored transposed, a (1000, 100) one a table of features
        hint = "is the array transposed?" if shape[0] <= MAX_COLUMNS else "not points?"
        raise DataError(
            f"{file}: shape {shape} is {shape[1]} columns of {shape[0]} rows; "
            f"points are rows (N, 3) with at most {MAX_COLUMNS - 3} attribute columns: {hint}"
        )
    if dtype.kind not in "fiuc":  # not bool, not timedelta64 (an integer to numpy)
        raise DataError(f"{file}: expected numeric coordinates, got dtype {dtype}")
    if np.issubdtype(dtype, np.complexfloating):
        raise DataError(f"{file}: expected real coordinates, got dtype {dtype}")


def first_three_columns(file: Path, array: np.ndarray) -> np.ndarray:
    """Check a 2-D numeric array with at least three columns and return its first three."""
    check_table(file, array.shape, array.dtype)
    return array[:, :3]


POINT_CLOUD_SUFFIXES: tuple[str, ...] = (".npy", ".ply", ".xyz", ".pts", ".txt", ".pcd")
"""File suffixes :func:`pfnet.io.clouds.read_point_cloud` understands (lower case)."""
