"""Paths as pfnet shows, stores and walks them, whatever bytes they hold.

A POSIX file name is bytes. Python decodes one that is not UTF-8 (a Latin-1 ``é``, byte
``0xe9``) into a string with a lone surrogate (``'\\udce9'``), which no UTF-8 stream or file
accepts: under a real ``en_US.UTF-8`` locale every ``print`` of such a path raised
``UnicodeEncodeError`` (``C.UTF-8`` hides it, as Python escapes there). pfnet therefore

* prints through streams that escape what they cannot encode (:func:`tolerant_streams`, set
  up once by :func:`pfnet.cli.main` for every command),
* shows a path in messages and stored text with :func:`shown` (the undecodable bytes as
  ``\\xe9``), and stores names in JSON as ASCII (``\\udce9``, which reads back to the same
  bytes),
* walks folders with :func:`walk_files`, iteratively and to a bounded depth: ``rglob`` on a
  folder 1,500 levels deep died in a ``RecursionError``.
"""

from __future__ import annotations

import codecs
import contextlib
import os
import sys
from collections.abc import Iterator
from pathlib import Path

from pfnet.errors import DataError

__all__ = ["MAX_FOLDER_DEPTH", "shown", "tolerant_streams", "walk_files"]

# Folders below a data folder that pfnet walks: real data sets nest a few levels (ShapeNet's
# category/model/models/); a deeper tree is refused by name rather than walked.
MAX_FOLDER_DEPTH = 64


def _escape(err: UnicodeError) -> tuple[str, int]:
    """A codec error handler: a byte Python kept as a surrogate (``'\\udce9'``) is shown as
    the byte (``\\xe9``), anything else a stream cannot encode as ``\\uXXXX``."""
    if not isinstance(err, UnicodeEncodeError):
        raise err
    bad = err.object[err.start : err.end]
    text = "".join(
        f"\\x{ord(c) - 0xDC00:02x}"
        if 0xDC80 <= ord(c) <= 0xDCFF
        else f"\\u{ord(c):04x}"
        if ord(c) <= 0xFFFF
        else f"\\U{ord(c):08x}"
        for c in bad
    )
    return text, err.end


ESCAPE_ERRORS = "pfnet-escape"
codecs.register_error(ESCAPE_ERRORS, _escape)


def shown(path: str | os.PathLike[str] | bytes) -> str:
    """``path`` as text any stream can print: bytes that are not UTF-8 become ``\\xNN``."""
    raw = os.fsencode(path)
    return raw.decode("utf-8", errors="backslashreplace")


@contextlib.contextmanager
def tolerant_streams() -> Iterator[None]:
    """Within the block, ``sys.stdout`` and ``sys.stderr`` escape what they cannot encode
    (bytes kept as surrogates as ``\\xNN``) instead of raising; their error handlers are
    restored after."""
    saved = []
    for stream in (sys.stdout, sys.stderr):
        errors = getattr(stream, "errors", None)
        reconfigure = getattr(stream, "reconfigure", None)
        if reconfigure is None or errors is None:
            continue
        with contextlib.suppress(ValueError, OSError, TypeError):
            reconfigure(errors=ESCAPE_ERRORS)
            saved.append((reconfigure, errors))
    try:
        yield
    finally:
        for reconfigure, errors in saved:
            with contextlib.suppress(ValueError, OSError, TypeError):
                reconfigure(errors=errors)


def walk_files(folder: str | os.PathLike[str], *, max_depth: int = MAX_FOLDER_DEPTH) -> list[Path]:
    """Every regular file below ``folder``, hidden files and folders (``.name``) left out.

    Walked iteratively (``os.scandir``, one folder at a time, no recursion), symbolic links to
    folders not followed, sorted.

    Raises:
        DataError: A folder lies more than ``max_depth`` levels below ``folder``, named.
    """
    root = Path(folder)
    found: list[Path] = []
    pending: list[tuple[Path, int]] = [(root, 0)]
    while pending:
        current, depth = pending.pop()
        with os.scandir(current) as entries:
            for entry in entries:
                if entry.name.startswith("."):
                    continue
                path = current / entry.name
                if entry.is_dir(follow_symlinks=False):
                    if depth + 1 > max_depth:
                        raise DataError(
                            f"{shown(root)}: folders nest more than {max_depth} levels deep "
                            f"(at {shown(path)[:200]}...); pfnet walks at most {max_depth}"
                        )
                    pending.append((path, depth + 1))
                elif entry.is_file():
                    found.append(path)
    return sorted(found)
