"""What a split file's bytes were when they were read: the digest ``predictions.json`` records.

``load_split`` hashes the open file it loads (:func:`remember_digest`), so a record says what
the predictions were made from even when ``prepare --overwrite`` replaced the data set after
it was read (issue 36: the digest was once taken at the end, of the new file).
"""

from __future__ import annotations

import hashlib
import os
from pathlib import Path

__all__ = ["loaded_split_digest", "remember_digest", "split_digest"]

# The SHA-256 of the bytes each split file had when this process loaded it.
_READ_DIGESTS: dict[tuple[str, str], str] = {}


def split_digest(root: str | os.PathLike[str], split: str) -> str:
    """The SHA-256 of a split's file as it is now (about 2 s a GB)."""
    with open(Path(root) / f"{split}.npz", "rb") as file:
        return hashlib.file_digest(file, "sha256").hexdigest()


def remember_digest(root: str | os.PathLike[str], split: str, digest: str) -> None:
    """Record the digest of the bytes of ``root``'s ``split`` this process has just read."""
    _READ_DIGESTS[(str(Path(root).resolve()), split)] = digest


def loaded_split_digest(root: str | os.PathLike[str], split: str) -> str:
    """The SHA-256 of the bytes ``load_split`` last read of a split in this process (of the
    file as it is now if it read none): what predictions are recorded as made from, so that
    they are never scored against other clouds under the same names."""
    read = _READ_DIGESTS.get((str(Path(root).resolve()), split))
    return read if read is not None else split_digest(root, split)
