"""Folder locks that keep two pfnet runs apart (issue 36).

Every command that writes a folder holds an exclusive lock on it for as long as it writes
(``train --out``, ``predict --out``, ``complete --out``, ``prepare --out`` while it replaces
one); a command that reads a folder another may rewrite holds a shared one (``predict
--data``, ``evaluate`` on the predictions and the data set). A second writer, or a writer
while someone reads, is refused at once with a message that names the folder and the other
process (its pid and command line), never left to interleave its files with the first's.

The lock is ``flock`` on the folder itself: no lock file is written (nothing to clean up,
nothing left in the user's folder), the kernel releases it when the process dies however it
dies (a SIGKILLed run never leaves a folder locked), and the holders are found in
``/proc/locks`` to be named.
"""

from __future__ import annotations

import contextlib
import os
from collections.abc import Iterator
from pathlib import Path

from pfnet.errors import DataError

__all__ = ["folder_lock", "holders", "reading", "take", "writing"]


def holders(folder: str | os.PathLike[str]) -> list[tuple[int, str]]:
    """The processes holding a ``flock`` on ``folder``: ``(pid, command line)`` (Linux's
    ``/proc/locks``; empty where it cannot be read)."""
    try:
        stat = os.stat(folder)
        lines = Path("/proc/locks").read_text().splitlines()
    except OSError:
        return []
    found = []
    for line in lines:
        words = line.split()
        if "->" in words or len(words) < 6 or words[1] != "FLOCK":
            continue
        try:
            pid = int(words[4])
            major, minor, inode = words[5].split(":")
        except ValueError:
            continue
        if int(inode) != stat.st_ino or (
            (int(major, 16), int(minor, 16)) != (os.major(stat.st_dev), os.minor(stat.st_dev))
        ):
            continue
        if pid != os.getpid() and pid not in [p for p, _ in found]:
            found.append((pid, _command_line(pid)))
    return found


def _command_line(pid: int) -> str:
    try:
        raw = Path(f"/proc/{pid}/cmdline").read_bytes()
    except OSError:
        return ""
    words = [os.fsdecode(word) for word in raw.split(b"\0") if word]
    if len(words) > 1 and Path(words[0]).name.startswith("python"):
        words = words[1:]  # "python -m pfnet.cli train ..." reads as "pfnet.cli train ..."
    line = " ".join(words)
    return line if len(line) <= 160 else line[:157] + "..."


def _who(folder: Path) -> str:
    found = holders(folder)
    if not found:
        return "another process"
    return "; ".join(f"pid {pid}" + (f" ({line})" if line else "") for pid, line in found)


def take(folder: str | os.PathLike[str], doing: str, *, shared: bool = False) -> int:
    """Lock the existing ``folder`` (see :func:`folder_lock`) until the returned descriptor
    is closed.

    Raises:
        DataError: Another process holds the folder, naming the folder and the process.
    """
    import fcntl

    from pfnet.io.paths import shown

    path = Path(folder)
    fd = os.open(path, os.O_RDONLY | os.O_DIRECTORY | os.O_CLOEXEC)
    try:
        fcntl.flock(fd, (fcntl.LOCK_SH if shared else fcntl.LOCK_EX) | fcntl.LOCK_NB)
    except BlockingIOError:
        os.close(fd)
        raise DataError(
            f"cannot start {doing} {shown(path)}: it is in use by {_who(path)}, and two runs "
            "at once would mix their files; wait for the other to finish, or name another folder"
        ) from None
    return fd


@contextlib.contextmanager
def folder_lock(
    folder: str | os.PathLike[str], doing: str, *, shared: bool = False
) -> Iterator[None]:
    """Hold a lock on the existing ``folder`` for the block: exclusive to write it, ``shared``
    to read it while no one writes.

    Args:
        folder: The folder.
        doing: What this command does with it, for the message: ``"writing into"``...
        shared: Take a shared lock (readers) instead of an exclusive one (a writer).

    Raises:
        DataError: Another process holds the folder, naming the folder and the process.
    """
    fd = take(folder, doing, shared=shared)
    try:
        yield
    finally:
        os.close(fd)


@contextlib.contextmanager
def reading(folder: str | os.PathLike[str] | None, doing: str) -> Iterator[None]:
    """A shared :func:`folder_lock` on ``folder`` if it is a folder (anything else is left to
    the command's own checks, which name it)."""
    if folder is None or not Path(folder).is_dir():
        yield
        return
    with folder_lock(folder, doing, shared=True):
        yield


@contextlib.contextmanager
def writing(folder: str | os.PathLike[str], doing: str, *, hold: bool = True) -> Iterator[None]:
    """An exclusive :func:`folder_lock` on ``folder``, made first if it does not exist (and
    removed again if the block leaves it empty): the lock must exist before anything is
    checked or written, so that a second run is refused before it reads what the first is
    writing. With ``hold`` false (a training rank other than the first) nothing is done.

    Raises:
        ConfigError: ``folder`` exists and is not a folder.
        DataError: Another process holds it (:func:`folder_lock`).
    """
    from pfnet.errors import ConfigError

    path = Path(folder)
    if not hold:
        yield
        return
    if path.exists() and not path.is_dir():
        raise ConfigError(f"{path} exists and is not a folder")
    made = not path.exists() and not path.is_symlink()
    path.mkdir(parents=True, exist_ok=True)
    try:
        with folder_lock(path, doing):
            yield
    finally:
        if made:
            with contextlib.suppress(OSError):
                path.rmdir()  # only if empty: a run that wrote nothing leaves nothing
