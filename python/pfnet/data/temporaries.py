"""The temporary folders ``OUT.tmp-<pid>`` that ``pfnet prepare`` writes a data set into.

Each is marked with :data:`TEMPORARY_MARK` from its creation until it becomes ``OUT``, so
that only such a folder is ever removed as a leftover: a SIGKILLed prepare left one behind,
never cleaned, and a later prepare deleted a user's folder that merely had that name.
"""

from __future__ import annotations

import contextlib
import glob
import os
import shutil
from collections.abc import Callable
from pathlib import Path

from pfnet.errors import DataError

__all__ = [
    "TEMPORARY_MARK",
    "make_temporary",
    "remove_stale_temporaries",
    "replace_through_temporary",
]

TEMPORARY_MARK = ".pfnet-prepare-temporary"
"""The file in a temporary folder of pfnet prepare (removed just before it becomes ``OUT``)."""


def make_temporary(tmp: Path) -> None:
    """Make the marked temporary folder ``tmp``, replacing only a marked one of this pid.

    Raises:
        DataError: ``tmp`` exists and is not pfnet's (no mark, or a link), naming it.
    """
    if tmp.exists() or tmp.is_symlink():
        if not (tmp / TEMPORARY_MARK).is_file() or tmp.is_symlink():
            raise DataError(
                f"{tmp} exists and is not a temporary folder of pfnet prepare; pfnet will not "
                "delete it: move it away"
            )
        shutil.rmtree(tmp)
    tmp.mkdir()
    (tmp / TEMPORARY_MARK).touch()


def remove_stale_temporaries(path: Path) -> list[Path]:
    """Remove the marked ``PATH.tmp-<pid>`` folders of processes that are gone; returns them."""
    removed = []
    for folder in path.parent.glob(f"{glob.escape(path.name)}.tmp-*"):
        pid = folder.name.rsplit("-", 1)[1]
        if not pid.isdigit() or not (folder / TEMPORARY_MARK).is_file() or folder.is_symlink():
            continue
        if int(pid) == os.getpid() or not _process_is_gone(int(pid)):
            continue
        shutil.rmtree(folder, ignore_errors=True)
        removed.append(folder)
    return removed


def _process_is_gone(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return True
    except OSError:  # alive, another user's
        return False
    return False


def replace_through_temporary(path: Path, fill: Callable[[Path], None]) -> None:
    """Make the folder ``path`` from what ``fill`` writes into ``PATH.tmp-<pid>``, atomically.

    The temporary folder is renamed onto ``path`` once complete (an existing ``path`` is
    moved aside to ``PATH.old-<pid>`` and deleted only after the rename). On any error the
    temporary folder is removed, the old ``path`` put back, and an ``OSError`` naming no
    file (a full disk) or a file in the temporary folder is made to name ``path``.
    """
    tmp = path.with_name(f"{path.name}.tmp-{os.getpid()}")
    old = path.with_name(f"{path.name}.old-{os.getpid()}")
    make_temporary(tmp)  # before the clean-up below: a folder it refuses is not pfnet's
    try:
        fill(tmp)
        (tmp / TEMPORARY_MARK).unlink()
        if path.exists():
            os.replace(path, old)
        os.replace(tmp, path)
    except BaseException as err:
        shutil.rmtree(tmp, ignore_errors=True)
        if isinstance(err, OSError) and (
            err.filename is None or str(err.filename).startswith(str(tmp))
        ):
            err.filename = str(path)
        if old.exists() and not path.exists():
            with contextlib.suppress(OSError):
                os.replace(old, path)
        raise
    shutil.rmtree(old, ignore_errors=True)
