"""Reading numeric text tables line by line, in bounded memory.

Text point formats (``.xyz``, ASCII PLY and PCD) are read a block of lines at a time, each block
parsed by numpy's C parser; no line may exceed :data:`MAX_LINE_BYTES`. Memory then stays
proportional to the points a file holds, whatever its lines hold: a 60 MB file of twenty
million short lines once took 2.2 GB as Python strings, and one line of 400 million tokens
5.2 GB.
"""

from __future__ import annotations

import io
import warnings
from collections.abc import Iterator
from pathlib import Path
from typing import BinaryIO

import numpy as np

from pfnet.errors import DataError

# A line of a point table holds a few numbers; a megabyte-long line is not a point.
MAX_LINE_BYTES = 1 << 16
# Lines parsed at once: bounds the Python objects alive at any time.
BLOCK_LINES = 1 << 16
# Lines of a text cloud (``.xyz``, ASCII PLY or PCD) up to the end of its points, blank and
# comment lines included (each costs about a microsecond): more are refused rather than taking
# minutes.
MAX_ASCII_LINES = 20_000_000


def numbered_lines(
    fh: BinaryIO, file: Path, first_number: int = 1, *, max_lines: int | None = None
) -> Iterator[tuple[int, bytes]]:
    """Yield ``(line number, line)`` for every line of ``fh``.

    Raises:
        DataError: A line is longer than :data:`MAX_LINE_BYTES`, or the caller reads more than
            ``max_lines`` lines (default :data:`MAX_ASCII_LINES`), whatever they hold: blank
            and comment lines take time too.
    """
    max_lines = MAX_ASCII_LINES if max_lines is None else max_lines
    number = first_number
    while True:
        raw = fh.readline(MAX_LINE_BYTES + 1)
        if not raw:
            return
        if len(raw) > MAX_LINE_BYTES:
            raise DataError(
                f"{file}: line {number} is longer than {MAX_LINE_BYTES} bytes; not a point table"
            )
        if number - first_number >= max_lines:
            raise DataError(
                f"{file}: more than {max_lines} lines before the end of the points, blank and "
                "comment lines included (save large clouds in a binary format)"
            )
        yield number, raw
        number += 1


def row_blocks(
    fh: BinaryIO,
    file: Path,
    first_number: int,
    count: int,
    *,
    skip: int = 0,
    max_lines: int,
    what: str,
) -> Iterator[list[tuple[int, str]]]:
    """The ``count`` non-blank lines after ``skip`` non-blank ones, as ``(line number, text)``
    in blocks of at most :data:`BLOCK_LINES`; the lines after them are not read.

    Raises:
        DataError: The file ends first (naming ``what``, e.g. "PLY data"), or holds more than
            ``max_lines`` lines, blank ones included (they take time too), before the end.
    """
    block: list[tuple[int, str]] = []
    seen = taken = 0
    if count == 0:
        return
    for number, raw in numbered_lines(fh, file, first_number, max_lines=max_lines):
        if not raw.strip():
            continue
        seen += 1
        if seen <= skip:
            continue
        block.append((number, raw.decode("ascii", errors="replace")))
        taken += 1
        if len(block) == BLOCK_LINES or taken == count:
            yield block
            block = []
            if taken == count:
                return
    raise DataError(
        f"{file}: truncated {what}: expected {skip + count} lines of data, found {seen}"
    )


def parse_block(text: str, columns: int, comments: tuple[str, ...] = ()) -> np.ndarray | None:
    """Parse the first ``columns`` numbers of every line as one float64 table (N, columns).

    Values after them are neither parsed nor kept (a wide row costs no memory). Returns
    ``None`` when a line has fewer values or one that is not a number, so that the caller
    can find and name the bad line. Underscores ("1_0") and hexadecimal are not numbers
    here, as in the line-by-line fallbacks.
    """
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)  # "input contained no data"
        try:
            return np.loadtxt(
                io.StringIO(text),
                dtype=np.float64,
                comments=list(comments) or None,
                ndmin=2,
                usecols=range(columns),
            )
        except ValueError:
            return None
