"""``.npy`` files, and the header check that ``.npz`` members share."""

from __future__ import annotations

import os
import threading
import tokenize
from pathlib import Path

import numpy as np

from pfnet.errors import DataError
from pfnet.io.formats import FileBody, check_body_span, check_point_count, check_table

# What numpy's header reader raises on hostile bytes: besides ValueError and EOFError, its
# fallback for Python-2 headers tokenizes the text (tokenize.TokenError, SyntaxError on an
# unclosed bracket) and ast.literal_eval may fail with TypeError, MemoryError or
# RecursionError (the ninth audit's fuzzing found 12 such headers in 8,000 mutations).
_HEADER_ERRORS = (
    ValueError,
    EOFError,
    SyntaxError,
    TypeError,
    KeyError,
    IndexError,
    OverflowError,
    RecursionError,
    MemoryError,
    tokenize.TokenError,
    UnicodeError,
)


# A .npy header is a short Python literal (numpy writes under 200 bytes, and reads at most
# 10,000 unless told otherwise).
MAX_HEADER_BYTES = 1 << 16


# numpy parses a header with ast.literal_eval, which CPython 3.11 does not run safely in two
# threads at once ("SystemError: AST constructor recursion depth mismatch", CPython
# gh-106905): evaluate reads prediction files on a thread pool.
HEADER_LOCK = threading.Lock()


def check_npy_header(
    name: str, fh, available: int, *, max_chars: int | None = None
) -> tuple[tuple[int, ...], np.dtype]:
    """Refuse a ``.npy`` stream whose header claims more data than ``available`` bytes.

    Reads the header from ``fh`` (positioned at the start) before numpy allocates anything:
    a forged header claiming 10^12 points made ``np.load`` fail with ``MemoryError``.
    Returns the declared shape and dtype. ``max_chars`` bounds the width of string arrays.

    Raises:
        DataError: Naming ``name``, the declared shape and the bytes there are.
    """
    from numpy.lib import format as npy_format

    try:
        version = npy_format.read_magic(fh)
        # The header's own length first: numpy reads that many bytes at once (a forged 4 GiB
        # length in a tiny file was a 4 GiB allocation).
        start = fh.tell()
        size_bytes = 2 if version == (1, 0) else 4
        header_len = int.from_bytes(fh.read(size_bytes), "little")
        if header_len > min(available - start - size_bytes, MAX_HEADER_BYTES):
            raise DataError(
                f"{name}: not a valid .npy array file (its header claims {header_len} bytes, "
                f"the file holds {max(available - start - size_bytes, 0)} after it; at most "
                f"{MAX_HEADER_BYTES} are read)"
            )
        fh.seek(start)
        with HEADER_LOCK:
            if version == (1, 0):
                shape, _, dtype = npy_format.read_array_header_1_0(fh)
            else:
                shape, _, dtype = npy_format.read_array_header_2_0(fh)
    except DataError:
        raise
    except _HEADER_ERRORS as err:
        said = err.args[0] if err.args and isinstance(err.args[0], str) else ""
        detail = said.splitlines()[0][:120] if said.strip() else type(err).__name__
        raise DataError(f"{name}: not a valid .npy array file (bad header: {detail})") from None
    width = dtype.itemsize // 4 if dtype.kind == "U" else dtype.itemsize
    if max_chars is not None and dtype.kind in "US" and width > max_chars:
        # checked before the size: a forged width of 10^8 deflates to almost nothing
        raise DataError(f"{name} declares strings of {width} characters")
    needed = int(np.prod(shape, dtype=object)) * dtype.itemsize
    if needed > available - fh.tell():
        raise DataError(
            f"{name}: the .npy header declares shape {shape} ({needed} bytes) but the file "
            f"holds {max(available - fh.tell(), 0)} bytes of data"
        )
    return tuple(shape), dtype


def read_npy(file: Path) -> np.ndarray:
    with open(file, "rb") as fh:
        shape, dtype = check_npy_header(str(file), fh, os.fstat(fh.fileno()).st_size)
        return _checked_columns(file, fh, shape, dtype)


def _checked_columns(file: Path, fh, shape: tuple[int, ...], dtype: np.dtype) -> np.ndarray:
    # the declared shape and dtype are checked before anything is loaded: a 4 KB sparse
    # file declaring shape (2, 5·10^8) took 3.9 GB before its columns were refused
    if dtype.hasobject:  # np.load would refuse it too (allow_pickle=False)
        raise DataError(f"{file}: not a valid .npy array file (pickled objects are not read)")
    check_table(file, shape, dtype)
    check_point_count(file, shape[0])
    # the rows are walked (mapped) as a PLY or PCD body is: the same bound on their bytes
    check_body_span(file, shape[0] * shape[1] * dtype.itemsize, f"the .npy rows {shape}")
    return _read_columns(file, fh, shape, dtype)


# Rows read at a time from a .npy body: bounds the memory beyond the three columns kept.
_NPY_BLOCK_BYTES = 1 << 24


def _read_columns(file: Path, fh, shape: tuple[int, ...], dtype: np.dtype) -> np.ndarray:
    """The first three columns of a checked ``.npy`` table, read a block of rows at a time.

    Read from the open file whose header was checked, never memory-mapped: a mapped file
    truncated while it is read kills the process with SIGBUS (issue 36). A file that ends
    early is refused naming it. Only the header's order flag is read again here.
    """
    from numpy.lib import format as npy_format

    rows, columns = shape
    data_start = fh.tell()
    fh.seek(0)
    try:
        with HEADER_LOCK:
            version = npy_format.read_magic(fh)
            if version == (1, 0):
                _, fortran, _ = npy_format.read_array_header_1_0(fh)
            else:
                _, fortran, _ = npy_format.read_array_header_2_0(fh)
    except _HEADER_ERRORS as err:
        raise DataError(f"{file}: not a valid .npy array file ({err})") from None
    fh.seek(data_start)
    body = FileBody(fh, file)
    if len(body) < rows * columns * dtype.itemsize:
        raise DataError(
            f"{file}: the .npy header declares shape {shape} but the file holds "
            f"{len(body)} bytes of data"
        )
    if fortran:  # column-major: the first three columns are the first 3·N values
        data = np.frombuffer(body.read(0, 3 * rows * dtype.itemsize), dtype=dtype)
        return data.reshape(3, rows).T.copy()
    out = np.empty((rows, 3), dtype=dtype)
    row_bytes = columns * dtype.itemsize
    step = max(_NPY_BLOCK_BYTES // max(row_bytes, 1), 1)
    for first in range(0, rows, step):
        last = min(first + step, rows)
        block = body.read(first * row_bytes, last * row_bytes)
        out[first:last] = np.frombuffer(block, dtype=dtype).reshape(-1, columns)[:, :3]
    return out
