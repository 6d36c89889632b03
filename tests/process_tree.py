"""Shared by the tests of Ctrl-C: a process's children and fork server, read from /proc
(Linux), and waiting for a condition."""

from __future__ import annotations

import time
from pathlib import Path


def children(pid: int) -> list[int]:
    """The pids of process ``pid``'s children (none once it has gone)."""
    path = Path(f"/proc/{pid}/task/{pid}/children")
    try:
        return [int(child) for child in path.read_text().split()]
    except OSError:
        return []


def fork_servers(pid: int) -> list[int]:
    """The pids of the multiprocessing fork servers that process ``pid`` has started."""
    found = []
    for child in children(pid):
        try:
            if b"forkserver" in Path(f"/proc/{child}/cmdline").read_bytes():
                found.append(child)
        except OSError:  # gone meanwhile
            continue
    return found


def wait_for(condition, timeout: float = 120.0) -> None:
    """Poll ``condition`` until it holds; AssertionError after ``timeout`` seconds."""
    deadline = time.monotonic() + timeout
    while not condition():
        if time.monotonic() > deadline:
            raise AssertionError("timed out")
        time.sleep(0.02)
