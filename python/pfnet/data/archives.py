"""The ``.npz`` archives of a data set: written byte for byte reproducibly, and read with
every member's declared size checked against what it can hold before anything is unpacked.

A split (``<split>.npz``) holds only the members of :data:`MEMBERS`; a benchmark's side
files (``<split>.partial.npz``, ``test.boxes.npz``) hold the arrays their readers name
(:func:`load_side_file`). Members are stored uncompressed; a compressed one is bounded by its
uncompressed size and, for coordinates, by :data:`MAX_POINTS_COMPRESSION`.
"""

from __future__ import annotations

import zipfile
from collections.abc import Mapping
from pathlib import Path

import numpy as np

from pfnet.errors import DataError

# A fixed timestamp for every member of the .npz archives: the same arrays give the same bytes.
_ZIP_DATE = (1980, 1, 1, 0, 0, 0)


MEMBERS = frozenset({"points.npy", "category.npy", "name.npy", "extra.npy"})


# Float32 coordinates of real shapes hardly compress (about 1.1 times); a member that claims
# to expand far more is a decompression bomb (a 1.2 MB split once expanded to 2.8 GB).
MAX_POINTS_COMPRESSION = 16


# Characters of a category or a name (write_dataset's names are far shorter).
MAX_NAME_CHARS = 200


def check_members(path: Path, rows: int | None, points: int | None, *, source=None) -> None:
    """Check every ``.npy`` member's declared size against its stored size before loading.

    A member whose header claims 10^12 points would make numpy try to allocate terabytes.
    Members are stored uncompressed by :func:`write_npz`; a compressed member is checked
    against its uncompressed size, which the zip directory records, and the coordinates
    against :data:`MAX_POINTS_COMPRESSION`. Every member must hold the same number of
    shapes (the manifest's, when it records one), so the names cannot outgrow the points.
    ``source``, an open file of ``path``, is read instead of opening ``path`` again.
    """
    shapes: dict[str, tuple[int, ...]] = {}
    needed = 0
    with zipfile.ZipFile(path if source is None else source) as archive:
        for info in archive.infolist():
            if info.filename not in MEMBERS:  # numpy would read a member "points" unchecked
                raise DataError(
                    f"{path}: unexpected member {info.filename[:80]!r} (a split holds "
                    f"{', '.join(sorted(MEMBERS))})"
                )
            name = f"{path}: member {info.filename}"
            coordinates = info.filename in ("points.npy", "extra.npy")
            # names are at most 200 characters: a forged width of 10^8 made five names
            # take 3 GB before they were refused
            limit = None if coordinates else MAX_NAME_CHARS
            shape, dtype = member_header(path, archive, info, coordinates, limit)
            shapes[info.filename] = shape
            needed += int(np.prod(shape, dtype=object)) * dtype.itemsize
            # ... and against the manifest, before anything is unpacked (a deflated 8 MB
            # member of 300,000 zero clouds took 2.4 GB before the count was compared)
            if rows is not None and shape[:1] != (rows,):
                raise DataError(f"{name} holds {shape[:1]} shapes, the manifest says {rows}")
            if info.filename == "points.npy" and points is not None and shape[1:2] != (points,):
                raise DataError(f"{name} has clouds of shape {shape[1:]}, not {points} points")
            if coordinates and shape[2:] != (3,):
                raise DataError(f"{name} has points of shape {shape[2:]}, not (3,)")
    counts = {member: shape[:1] for member, shape in shapes.items()}
    if len(set(counts.values())) > 1:
        listed = ", ".join(f"{m} {c}" for m, c in sorted(counts.items()))
        raise DataError(f"{path}: members hold different numbers of shapes ({listed})")
    free = available_memory()
    if free is not None and needed > free:
        raise DataError(
            f"{path}: loading the split needs {needed / 1e6:,.1f} MB of memory; "
            f"{free / 1e6:,.1f} MB are available"
        )


def member_header(
    path: Path,
    archive: zipfile.ZipFile,
    info: zipfile.ZipInfo,
    coordinates: bool,
    max_chars: int | None,
) -> tuple[tuple[int, ...], np.dtype]:
    """The declared shape and dtype of one ``.npy`` member, checked against the bytes the
    member can hold (its stored size, and :data:`MAX_POINTS_COMPRESSION` for coordinates)."""
    from pfnet.io.formats.npy import check_npy_header

    # The directory's sizes are data too: bound them by the archive's real size
    # (deflate expands at most about 1032 times).
    if info.compress_size > path.stat().st_size:
        raise DataError(f"{path}: member {info.filename[:80]!r} is larger than the archive")
    name = f"{path}: member {info.filename[:80]}"
    if info.compress_type == zipfile.ZIP_STORED:
        ratio = 1
    else:
        ratio = MAX_POINTS_COMPRESSION if coordinates else 1032
    available = min(info.file_size, info.compress_size * ratio)
    if coordinates and info.file_size > info.compress_size * ratio + 4096:
        raise DataError(
            f"{name} claims to expand {info.file_size / max(info.compress_size, 1):.0f} "
            f"times; point coordinates do not compress beyond {MAX_POINTS_COMPRESSION} "
            "(a decompression bomb?)"
        )
    with archive.open(info) as member:
        return check_npy_header(name, member, available, max_chars=max_chars)


def load_side_file(
    path: Path, expected: Mapping[str, tuple[type, tuple[int | None, ...]]], what: str
) -> dict[str, np.ndarray]:
    """Load a benchmark's side file (``<split>.partial.npz``, ``test.boxes.npz``) with the
    checks of :func:`pfnet.data.format.load_split`: every member's header is read and compared with
    ``expected`` (``{array: (dtype, shape)}``, ``None`` for a length the file decides) and
    with the bytes it can hold before anything is unpacked.

    Raises:
        DataError: Naming ``path`` and the problem (``what`` says what the file holds).
    """
    try:
        needed = 0
        with zipfile.ZipFile(path) as archive:
            infos = archive.infolist()
            if sorted(i.filename for i in infos) != sorted(f"{key}.npy" for key in expected):
                raise DataError(f"{path}: expected the arrays {' and '.join(expected)}")
            for info in infos:
                key = info.filename.removesuffix(".npy")
                dtype, wanted = expected[key]
                coordinates = np.dtype(dtype).kind == "f"
                shape, found = member_header(path, archive, info, coordinates, None)
                if (
                    found != np.dtype(dtype)
                    or len(shape) != len(wanted)
                    or any(w is not None and w != s for w, s in zip(wanted, shape, strict=True))
                ):
                    spelled = "(" + ", ".join("N" if w is None else str(w) for w in wanted)
                    spelled += ",)" if len(wanted) == 1 else ")"
                    raise DataError(
                        f"{path}: {key} must be {np.dtype(dtype)} {spelled}, got {found} {shape}"
                    )
                needed += int(np.prod(shape, dtype=object)) * found.itemsize
        free = available_memory()
        if free is not None and needed > free:
            raise DataError(
                f"{path}: loading the {what} needs {needed / 1e6:,.1f} MB of memory; "
                f"{free / 1e6:,.1f} MB are available"
            )
        with np.load(path, allow_pickle=False) as data:
            return {key: data[key] for key in expected}
    except DataError:
        raise
    except (OSError, ValueError, zipfile.BadZipFile, MemoryError) as err:
        raise DataError(f"{path}: cannot read the {what}: {err or type(err).__name__}") from None


def available_memory() -> int | None:
    """Bytes of memory the system can still give (MemAvailable), if it says."""
    try:
        with open("/proc/meminfo", encoding="ascii") as fh:
            for line in fh:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    return None


def write_npz(path: Path, arrays: Mapping[str, np.ndarray]) -> None:
    """``np.savez`` with a fixed member timestamp, so equal arrays give byte-identical files."""
    with zipfile.ZipFile(path, "w", compression=zipfile.ZIP_STORED) as archive:
        for key, array in arrays.items():
            info = zipfile.ZipInfo(f"{key}.npy", date_time=_ZIP_DATE)
            with archive.open(info, "w", force_zip64=True) as member:
                np.lib.format.write_array(member, np.ascontiguousarray(array), allow_pickle=False)
