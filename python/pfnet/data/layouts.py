"""What the benchmark readers share (PCN and ShapeNet-55/34 in :mod:`pfnet.data.benchmarks`,
KITTI in :mod:`pfnet.data.kitti`): index files read within a bound, index entries checked
before the file system is touched, entries listed twice, the categories kept, and the side
file of partial scans."""

from __future__ import annotations

import stat
from collections import Counter
from pathlib import Path

from pfnet.data.format import unsafe_component
from pfnet.errors import DataError

PARTIAL_SUFFIX = ".partial.npz"
"""The side file of a split's partial scans: ``<split>.partial.npz``."""
# PCN.json is about 1 MB and a ShapeNet-55 list under 2 MB; 2 GiB sparse ones took 4 GB.
MAX_INDEX_BYTES = 16 << 20


def read_index(path: Path, what: str) -> str:
    """The text of an index file (PCN.json, KITTI.json, a ShapeNet split list), refused
    beyond :data:`MAX_INDEX_BYTES` before it is read whole."""
    try:
        with open(path, "rb") as fh:
            data = fh.read(MAX_INDEX_BYTES + 1)
    except OSError as err:
        raise DataError(f"{path}: cannot read the {what}: {err.strerror or err}") from None
    if len(data) > MAX_INDEX_BYTES:
        raise DataError(f"{path}: larger than {MAX_INDEX_BYTES >> 20} MB; not a {what}")
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError:
        raise DataError(f"{path}: cannot read the {what}: not UTF-8 text") from None


def shown(text: str) -> str:
    """An untrusted name for messages: control characters escaped, cut to 100 characters."""
    return ascii(text[:100])[1:-1] + ("..." if len(text) > 100 else "")


def bad_entry(index: Path, *parts: str) -> tuple[str, str] | None:
    """The ``(where, why)`` to skip an index entry whose parts cannot be file names (too
    long, ``/``, control characters...), decided before the file system is touched."""
    for part in parts:
        why = unsafe_component(part)
        if why is not None:
            return f"{index}: entry {shown(part)}", f"the name {why}"
    return None


def file_id(path: Path) -> tuple[int, int] | None:
    """``(device, inode)`` of a regular file, or None (missing, or a name the system
    refuses, such as one over 255 bytes)."""
    try:
        status = path.stat()
    except (OSError, ValueError):
        return None
    return (status.st_dev, status.st_ino) if stat.S_ISREG(status.st_mode) else None


def repeated(repeats: Counter, first: dict, index: str) -> list[tuple[str, str]]:
    """One skipped line for each file an index lists more than once (read once)."""
    return [
        (first[key][0], f"listed {n + 1} times in {index}; read once, as {first[key][1]}")
        for key, n in repeats.items()
    ]


def keep_categories(entries: list, categories: list[str] | None) -> list:
    """The index entries of ``categories`` (all of them with None).

    Raises:
        ConfigError: A category that no entry has, naming the ones there are.
    """
    if categories is None:
        return entries
    keep = {c.lower() for c in categories}
    available = sorted({e.category for e in entries})
    unknown = sorted(keep - set(available))
    if unknown:
        from pfnet.errors import ConfigError

        raise ConfigError(
            f"categories: {', '.join(unknown)} not in the source; available: {', '.join(available)}"
        )
    return [e for e in entries if e.category in keep]
