"""Reading and writing point cloud files.

:func:`read_point_cloud` reads every format users bring to ``pfnet complete`` and
``pfnet evaluate`` into one float32 ``(N, 3)`` array:

* ``.npy`` — a numeric ``(N, C)`` array, ``C >= 3``; the first three columns are x, y, z.
* ``.ply`` — ``ascii``, ``binary_little_endian`` or ``binary_big_endian``; the ``x``, ``y``,
  ``z`` properties of the ``vertex`` element (any numeric type); faces and every other
  element or property are ignored.
* ``.xyz``, ``.pts``, ``.txt`` — one point per line, separated by whitespace, commas or
  semicolons (values with decimal commas, ``10,1257 19,7358 31,9213``, are read as
  decimals), the first three columns are x, y, z unless a line of names orders them.
  Blank lines and lines starting with ``#`` or ``//`` are
  skipped, as are a first line holding only the point count (the Leica ``.pts`` header) and
  a first line of column names (``x,y,z``).
* ``.pcd`` — ``DATA ascii``, ``binary`` or ``binary_compressed``; the ``x``, ``y``, ``z``
  fields. Points with a NaN coordinate are dropped: PCL marks the invalid points of an
  organised cloud that way.

A cloud may hold at most :data:`~pfnet.io.formats.MAX_CLOUD_POINTS` (50,000,000) points, and a
text one at most :data:`~pfnet.io.formats.lines.MAX_ASCII_LINES` lines up to its last point.
Every problem (missing file, unknown suffix, truncated or malformed data, too many points,
no points, NaN/inf coordinates) raises :class:`~pfnet.errors.DataError` naming the file and
the reason.
Writers go through :func:`pfnet.io.files.atomic_path`, so a crash never leaves a half-written
file.
"""

from __future__ import annotations

import os
import tokenize
from pathlib import Path

import numpy as np

from pfnet.errors import DataError
from pfnet.io.files import atomic_path
from pfnet.io.formats import POINT_CLOUD_SUFFIXES
from pfnet.io.formats.npy import read_npy
from pfnet.io.formats.pcd import read_pcd
from pfnet.io.formats.ply import read_ply
from pfnet.io.formats.text import read_text

# The geometry core's bound (pfnet._core.MAX_COORDINATE), repeated so that reading a file
# does not load the extension.
MAX_COORDINATE = 1e18

__all__ = [
    "read_point_cloud",
    "save_npy",
    "write_ply",
]


def save_npy(path: str | os.PathLike[str], array: np.ndarray) -> None:
    """Write ``array`` to ``path`` in ``.npy`` format, atomically."""
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as fh:
            np.save(fh, np.asarray(array), allow_pickle=False)


def write_ply(
    path: str | os.PathLike[str], points: np.ndarray, colors: np.ndarray | None = None
) -> None:
    """Write a point cloud as a binary little-endian PLY file, atomically.

    Args:
        path: Destination file.
        points: ``(N, 3)`` coordinates, stored as float32 ``x y z`` vertex properties, or
            as double for a float64 array (a survey scan's coordinates keep their precision).
        colors: Optional ``(N, 3)`` colours, either uint8 or floats in ``[0, 1]``; stored as
            uchar ``red green blue``.

    Raises:
        DataError: If the shapes are wrong or the coordinates are not finite.
    """
    pts = np.asarray(points)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise DataError(f"write_ply: points must have shape (N, 3), got {pts.shape} for {path}")
    if not np.issubdtype(pts.dtype, np.number) or not np.isfinite(pts).all():
        raise DataError(f"write_ply: points must be finite numbers for {path}")
    wide = pts.dtype == np.float64
    kind, ply_type = ("<f8", "double") if wide else ("<f4", "float")
    fields = [("x", kind), ("y", kind), ("z", kind)]
    if colors is not None:
        rgb = np.asarray(colors)
        if rgb.shape != pts.shape:
            raise DataError(
                f"write_ply: colors must have shape {pts.shape} like points, got {rgb.shape}"
            )
        if rgb.dtype != np.uint8:
            rgb = np.clip(np.rint(np.asarray(rgb, dtype=np.float64) * 255.0), 0, 255)
        fields += [("red", "u1"), ("green", "u1"), ("blue", "u1")]
    vertex = np.empty(len(pts), dtype=fields)
    vertex["x"], vertex["y"], vertex["z"] = pts[:, 0], pts[:, 1], pts[:, 2]
    header = ["ply", "format binary_little_endian 1.0", "comment written by pfnet"]
    header.append(f"element vertex {len(pts)}")
    header += [f"property {ply_type} {axis}" for axis in "xyz"]
    if colors is not None:
        vertex["red"], vertex["green"], vertex["blue"] = rgb[:, 0], rgb[:, 1], rgb[:, 2]
        header += ["property uchar red", "property uchar green", "property uchar blue"]
    header.append("end_header")
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as fh:
            fh.write(("\n".join(header) + "\n").encode("ascii"))
            fh.write(vertex.tobytes())


def read_point_cloud(path: str | os.PathLike[str], *, keep_float64: bool = False) -> np.ndarray:
    """Read a point cloud file into a float32 ``(N, 3)`` array.

    Args:
        path: A ``.npy``, ``.ply``, ``.xyz``, ``.pts``, ``.txt`` or ``.pcd`` file (see the
            module docstring for what each may hold).
        keep_float64: Return float64 where the file holds float64 or text (a survey or LiDAR
            scan in UTM coordinates: 512,345.0 and 512,345.1 are one float32), float32
            otherwise.

    Returns:
        float32 ``(N, 3)`` array of x, y, z, ``N >= 1``, all finite (float64 as told).

    Raises:
        DataError: Naming ``path`` and the reason: not found, unknown suffix, unreadable or
            malformed, no points, NaN/inf coordinates, or distinct points that float32 makes
            one (far from the origin), which the message says.
    """
    file = Path(path)
    suffix = file.suffix.lower()
    if file.is_dir():  # before the suffix, which a folder seldom has
        raise DataError(f"{file}: a folder, not a point cloud file; give the files in it")
    if suffix not in POINT_CLOUD_SUFFIXES:
        raise DataError(
            f"{file}: unsupported point cloud suffix {file.suffix!r} "
            f"(expected one of {', '.join(POINT_CLOUD_SUFFIXES)})"
        )
    if not file.exists():
        raise DataError(f"{file}: no such file")
    if not file.is_file():
        raise DataError(f"{file}: not a regular file")
    try:
        if suffix == ".npy":
            points = read_npy(file)
        elif suffix == ".ply":
            points = read_ply(file)
        elif suffix == ".pcd":
            points = read_pcd(file)
        else:
            points = read_text(file)
    except DataError:
        raise
    except OSError as err:
        raise DataError(f"{file}: cannot read: {err.strerror or err}") from err
    except MemoryError:
        raise DataError(f"{file}: too large to load into memory") from None
    except (
        ValueError,
        IndexError,
        KeyError,
        OverflowError,
        TypeError,
        RecursionError,
        SyntaxError,
        tokenize.TokenError,
    ) as err:
        # The readers' single boundary: whatever hostile bytes make a parser raise is a
        # malformed file, named, so that batch commands skip it and go on.
        raise DataError(f"{file}: malformed {suffix[1:]} file ({err})") from None
    wide = np.asarray(points).dtype == np.float64
    read = points
    with np.errstate(over="ignore", invalid="ignore"):
        points = np.ascontiguousarray(
            points, dtype=np.float64 if keep_float64 and wide else np.float32
        )
    if points.shape[0] == 0:
        raise DataError(f"{file}: the file holds no points")
    if not np.isfinite(points).all():
        bad = int((~np.isfinite(points).all(axis=1)).sum())
        raise DataError(f"{file}: {bad} point(s) have NaN or infinite coordinates")
    if np.abs(points).max() > MAX_COORDINATE:
        raise DataError(
            f"{file}: coordinates beyond ±{MAX_COORDINATE:g}, which no distance computation "
            "in float32 survives; scale the cloud down"
        )
    if wide and points.dtype == np.float32 and len(points) > 1:
        _refuse_collapse(file, np.asarray(read, dtype=np.float64), points)
    return points


def _refuse_collapse(file: Path, read: np.ndarray, points: np.ndarray) -> None:
    """Refuse float64 points that are apart but one point in float32 (every point ``2^-24``
    of its distance from the origin away from the next float32): said so, never reported
    later as a cloud whose points all coincide."""
    if np.ptp(points, axis=0).max() > 0:
        return
    extent = float(np.ptp(read, axis=0).max())
    if extent > 0:
        offset = float(np.abs(read).max())
        raise DataError(
            f"{file}: the points span {extent:.6g} but lie {offset:.6g} from the origin, "
            "where float32 cannot tell them apart; subtract an offset (a survey origin) "
            "before saving, or read the file in float64"
        )
