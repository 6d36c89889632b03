"""``.npy`` files, and the header check that ``.npz`` members share."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from pfnet.errors import DataError
from pfnet.formats import check_point_count, first_three_columns


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
        if version == (1, 0):
            shape, _, dtype = npy_format.read_array_header_1_0(fh)
        else:
            shape, _, dtype = npy_format.read_array_header_2_0(fh)
    except (ValueError, EOFError) as err:
        raise DataError(f"{name}: not a valid .npy array file ({err})") from None
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
        shape, _ = check_npy_header(str(file), fh, file.stat().st_size)
    if shape:
        check_point_count(file, shape[0])
    try:
        array = np.load(file, allow_pickle=False)
    except ValueError as err:  # object arrays, bad headers, truncated data
        raise DataError(f"{file}: not a valid .npy array file ({err})") from err
    except EOFError as err:
        raise DataError(f"{file}: not a valid .npy array file (empty or truncated)") from err
    if not isinstance(array, np.ndarray):
        raise DataError(f"{file}: not a .npy array file")
    return first_three_columns(file, array)
