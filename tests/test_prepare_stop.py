"""Ctrl-C during ``pfnet prepare`` with a worker pool: only pfnet acts on it. It exits with
130 and its one-line message, no traceback and no hang, leaves no output folder, and the
same command then runs again. (The pool's workers used to get the SIGINT too: some printed
``KeyboardInterrupt`` tracebacks, and one killed while holding a lock of the pool's result
queue made the shutdown wait for ever.)"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest
from process_tree import children, fork_servers, wait_for

from pfnet.processes import _sigint_deferred, close_pool, start_helpers

# Ctrl-C as in a terminal, even when the test suite runs in the background (SIGINT ignored)
pytestmark = [
    pytest.mark.usefixtures("sigint_as_in_a_terminal"),
    pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc"),
]

# 5 categories × 5,000 shapes: far more than a test waits for, as every run is interrupted.
PREPARE = ["prepare", "procedural", "--points", "512", "--count", "5000", "--workers", "2"]


def _start(out: Path, *options: str) -> subprocess.Popen[str]:
    command = [sys.executable, "-m", "pfnet.cli", *options, "--out", str(out)]
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    # A session of its own: killpg reaches prepare, its workers and its fork server, as a
    # terminal's Ctrl-C would.
    return subprocess.Popen(
        command,
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        start_new_session=True,
    )


def _workers(pid: int) -> list[int]:
    return [worker for server in fork_servers(pid) for worker in children(server)]


def _working(pid: int) -> bool:
    """Whether both workers have been sampling shapes for a second."""
    if len(_workers(pid)) < 2:
        return False
    time.sleep(1.0)
    return True


MOMENTS = {
    # the fork server has been started and imports pfnet: the pool is starting
    "pool-starting": lambda pid: bool(fork_servers(pid)),
    # the fork server has forked both workers
    "workers-started": lambda pid: len(_workers(pid)) >= 2,
    "working": _working,
}


@pytest.mark.parametrize("moment", list(MOMENTS))
def test_ctrl_c_during_prepare_exits_130_and_leaves_nothing(moment: str, tmp_path: Path) -> None:
    out = tmp_path / "data"
    process = _start(out, *PREPARE)
    try:
        wait_for(lambda: process.poll() is not None or MOMENTS[moment](process.pid), timeout=60)
        assert process.poll() is None, process.communicate()[1][-3000:]
        os.killpg(process.pid, signal.SIGINT)
        _, stderr = process.communicate(timeout=60)  # a hang fails here
    finally:
        if process.poll() is None:
            os.killpg(process.pid, signal.SIGKILL)
            process.communicate()
    assert process.returncode == 130, stderr[-3000:]
    assert stderr.splitlines() == ["pfnet prepare: interrupted"], stderr[-3000:]
    assert not out.exists()
    assert list(tmp_path.iterdir()) == []  # no temporary folder either
    # the same command, smaller (20 shapes: still a pool of 2)
    again = _start(out, *PREPARE[:2], "--points", "64", "--count", "4", "--workers", "2")
    _, stderr = again.communicate(timeout=120)
    assert again.returncode == 0, stderr[-3000:]
    assert (out / "manifest.json").exists()


class _StuckPool:
    """A pool whose shutdown never ends, as when a worker died holding one of its locks."""

    def __init__(self, processes: list) -> None:
        self._pool = processes
        self.release = threading.Event()

    def terminate(self) -> None:
        self.release.wait()

    def join(self) -> None:
        pass


def test_a_pool_that_cannot_shut_down_is_killed_after_the_timeout() -> None:
    context = start_helpers([])
    workers = [context.Process(target=time.sleep, args=(3600,), daemon=True) for _ in range(2)]
    for worker in workers:
        worker.start()
    pool = _StuckPool(workers)
    try:
        close_pool(pool, timeout=0.5)  # returns, though terminate never does
        for worker in workers:
            worker.join(60)
            assert worker.exitcode == -signal.SIGKILL
    finally:
        pool.release.set()
        for worker in workers:
            if worker.is_alive():
                worker.kill()
                worker.join()


def test_a_ctrl_c_while_the_pool_starts_is_raised_once_it_has_started() -> None:
    """Not lost, only held back: a worker still reading its start-up data when prepare
    exited printed a traceback."""
    done = []
    with pytest.raises(KeyboardInterrupt):
        with _sigint_deferred():
            signal.raise_signal(signal.SIGINT)
            done.append(True)
    assert done
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler
    previous = signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        with _sigint_deferred():  # an ignored SIGINT stays ignored
            signal.raise_signal(signal.SIGINT)
        assert signal.getsignal(signal.SIGINT) is signal.SIG_IGN
    finally:
        signal.signal(signal.SIGINT, previous)


def test_an_error_while_a_pool_shuts_down_is_raised() -> None:
    def cannot_join() -> None:
        raise OSError("cannot join")

    pool = _StuckPool([])
    pool.release.set()
    pool.join = cannot_join
    with pytest.raises(OSError, match="cannot join"):
        close_pool(pool, timeout=60)
