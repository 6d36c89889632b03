"""PCD files (PCL): ``DATA ascii``, ``binary`` and ``binary_compressed`` (LZF)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from pfnet import _core
from pfnet.errors import DataError, GeometryError
from pfnet.io.formats import (
    check_body_span,
    check_point_count,
    float32_columns,
    map_rest,
    read_header,
)
from pfnet.io.formats.lines import MAX_ASCII_LINES, parse_block, row_blocks

# Values of one point (the sum of COUNT): descriptors such as SHOT (352 values) fit, and an
# ASCII line of at most 64 KiB could hold no more than about 32,000. A 10 KB file declaring
# COUNT 10^8 for one field took 4.7 GB before its first line was parsed.
MAX_PCD_VALUES = 4096

_PCD_TYPES = {("F", 4): "f4", ("F", 8): "f8"}
_PCD_TYPES.update({("I", s): f"i{s}" for s in (1, 2, 4, 8)})
_PCD_TYPES.update({("U", s): f"u{s}" for s in (1, 2, 4, 8)})


def read_pcd(file: Path) -> np.ndarray:
    with open(file, "rb") as fh:
        header = read_header(fh, file, b"DATA")
        return _read_pcd_body(file, fh, header, len(header) + 1)


def _read_pcd_body(file: Path, fh, header: list[str], body_line: int) -> np.ndarray:
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
    if sum(counts_i) > MAX_PCD_VALUES:
        raise DataError(
            f"{file}: PCD header declares {sum(counts_i)} values a point (the sum of COUNT); "
            f"pfnet reads at most {MAX_PCD_VALUES}"
        )
    check_point_count(file, n_points)
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
        points = _read_pcd_ascii(file, fh, body_line, counts_i, n_points, columns)
    elif mode not in ("binary", "binary_compressed"):
        raise DataError(f"{file}: unsupported PCD DATA mode {mode!r}")
    elif mode == "binary":
        dtype = np.dtype(
            [
                (f"f{i}", dt, (c,) if c > 1 else ())
                for i, (dt, c) in enumerate(zip(dtypes, counts_i, strict=True))
            ]
        )
        check_body_span(file, dtype.itemsize * n_points, f"{n_points} PCD points")
        body = map_rest(fh, file)
        if len(body) < dtype.itemsize * n_points:
            raise DataError(
                f"{file}: truncated PCD data: {n_points} points need "
                f"{dtype.itemsize * n_points} bytes, found {len(body)}"
            )
        table = np.frombuffer(body.read(0, dtype.itemsize * n_points), dtype=dtype, count=n_points)
        points = float32_columns([_pcd_first(table[f"f{c}"]) for c in columns])
    else:
        points = _read_pcd_compressed(file, map_rest(fh, file), dtypes, counts_i, n_points, columns)
    return points[np.isfinite(points).all(axis=1)] if np.isnan(points).any() else points


def _pcd_first(column: np.ndarray) -> np.ndarray:
    return column[:, 0] if column.ndim == 2 else column


def _read_pcd_ascii(file, fh, body_line, counts, n_points, columns) -> np.ndarray:
    """The points of an ASCII body, a block of lines at a time; later lines unread.

    Only the values up to the last coordinate are parsed (a line's later values cost nothing).
    """
    starts = [int(s) for s in np.cumsum([0, *counts])]
    used = max(starts[c] for c in columns) + 1
    parts: list[np.ndarray] = []  # not one array of n_points rows: the count may be forged
    for block in row_blocks(
        fh, file, body_line, n_points, max_lines=MAX_ASCII_LINES, what="PCD data"
    ):
        table = parse_block("".join(line for _, line in block), used)
        if table is None:
            raise DataError(
                f"{file}: malformed PCD ascii data (non-numeric values, or fewer values than "
                "the FIELDS declare before z)"
            )
        parts.append(float32_columns([table[:, starts[c]] for c in columns]))
    return np.concatenate(parts) if parts else np.empty((0, 3))


# LZF gains at most about 90 times (a back reference of 264 bytes in 3); coordinates of real
# clouds barely compress. A file that claims more is refused before it is unpacked (a 2.7 MB
# file expanding to 240 MB took 1.9 GB and 20 s).
MAX_PCD_COMPRESSION = 32
# Bytes binary_compressed data may unpack to, whatever the file's size: 50,000,000 points of
# x y z, normals and colour (32 bytes each) fit.
MAX_PCD_UNPACKED = 1 << 31


def _read_pcd_compressed(file, body, dtypes, counts, n_points, columns) -> np.ndarray:
    if len(body) < 8:
        raise DataError(f"{file}: truncated PCD binary_compressed data")
    compressed, raw = (int(v) for v in np.frombuffer(body.read(0, 8), "<u4", 2))
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
    if raw > MAX_PCD_UNPACKED:
        raise DataError(
            f"{file}: PCD binary_compressed data declares {raw} bytes unpacked; pfnet unpacks "
            f"at most {MAX_PCD_UNPACKED}"
        )
    if raw > MAX_PCD_COMPRESSION * compressed + 65536:
        raise DataError(
            f"{file}: PCD binary_compressed data claims to expand {raw / max(compressed, 1):.0f} "
            f"times; point clouds do not compress beyond {MAX_PCD_COMPRESSION}"
        )
    try:  # in the Rust core: linear in the size, never beyond it
        data = _core.lzf_decompress(np.frombuffer(body.read(8, 8 + compressed), np.uint8), raw)
    except GeometryError as err:
        raise DataError(f"{file}: corrupt PCD binary_compressed data ({err})") from None
    out = []
    for c in columns:
        block = np.frombuffer(data, dtypes[c], n_points * counts[c], int(offsets[c]))
        out.append(block.reshape(n_points, counts[c])[:, 0])
    return float32_columns(out)
