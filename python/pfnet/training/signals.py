"""Safe stopping: Ctrl-C / SIGTERM end a run with a saved state, never with a traceback.

A terminal's Ctrl-C sends SIGINT to the whole process group: the training process, its
data-loader workers, the fork server that starts them and multiprocessing's resource
tracker. Only the training process may act on it (it finishes the batch, saves ``last.pt``
and exits with 130); a helper that died of it would break the next batch fetch (the old
``BrokenPipeError`` of a fork server killed while it imported torch). The helpers are
therefore spawned with SIGINT and SIGTERM *blocked* in their signal mask: a mask set by
``posix_spawn`` survives exec and fork, so the fork server and every worker it forks hold
both signals from their first instruction (multiprocessing's own spawn clears the mask, so
:func:`start_helpers` swaps in :func:`spawn_shielded` while it starts them). The training
process never changes its own handlers for this: a signal sent at any moment, while the
helpers start included, reaches it (ignoring them there for the spawn lost a Ctrl-C sent in
those milliseconds).
"""

from __future__ import annotations

import contextlib
import multiprocessing
import multiprocessing.context
import os
import signal
import sys
import threading
from collections.abc import Iterable, Iterator, Sequence
from typing import Any

STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM)


def spawn_shielded(path: str, args: Sequence[str], passfds: Iterable[int]) -> int:
    """``multiprocessing.util.spawnv_passfds`` with SIGINT and SIGTERM blocked in the child.

    Starts ``path`` with ``args``, passing the descriptors ``passfds`` (and 0-2; Python
    opens every other descriptor non-inheritable), and returns its pid.
    """
    fds = sorted({int(fd) for fd in passfds})
    inheritable = [os.get_inheritable(fd) for fd in fds]
    for fd in fds:
        os.set_inheritable(fd, True)
    try:
        return os.posix_spawn(path, list(args), os.environ, setsigmask=STOP_SIGNALS)
    finally:
        for fd, flag in zip(fds, inheritable, strict=True):
            os.set_inheritable(fd, flag)


def start_helpers() -> multiprocessing.context.BaseContext:
    """The multiprocessing context for data-loader workers, its helpers started shielded.

    Workers come from a fork server that has imported pfnet but run nothing: a plain
    ``fork`` of a process that runs CUDA or several threads copies their state without the
    threads, and the fork server's forks are cheap. The fork server and the resource
    tracker are spawned here by :func:`spawn_shielded` (see the module docstring).
    """
    from multiprocessing import forkserver, util

    context = multiprocessing.get_context("forkserver")
    context.set_forkserver_preload(["pfnet.training.loop"])
    spawn = util.spawnv_passfds
    util.spawnv_passfds = spawn_shielded
    try:
        forkserver.ensure_running()
    finally:
        util.spawnv_passfds = spawn
    return context


def ignore_stop_signals(_worker_id: int) -> None:
    """``worker_init_fn``: a worker leaves stopping to the training process.

    Already so when the fork server was started by :func:`start_helpers`; this covers a fork
    server that someone else started first.
    """
    for signum in STOP_SIGNALS:
        signal.signal(signum, signal.SIG_IGN)


class StopRequest:
    """SIGINT/SIGTERM handler: the first signal asks the run to stop at the next safe point.

    A second SIGINT raises ``KeyboardInterrupt`` (abort without waiting); checkpoint files
    are replaced atomically, so even then the previous ``last.pt`` stays intact.
    """

    def __init__(self) -> None:
        self.requested = False
        self._previous: dict[int, Any] = {}

    def _handle(self, signum: int, _frame: object) -> None:
        if self.requested and signum == signal.SIGINT:
            raise KeyboardInterrupt
        self.requested = True
        print(
            "\npfnet train: stopping at the next safe point and saving (Ctrl-C again to abort)",
            file=sys.stderr,
        )

    @contextlib.contextmanager
    def installed(self) -> Iterator[StopRequest]:
        """Install the handler for the duration of the block (main thread only).

        A signal ignored when the block begins stays ignored, as a program started in the
        background (``cmd &`` in a script, ``nohup``) is expected to: the shell set SIGINT to
        be ignored so that a Ctrl-C meant for the foreground does not stop it."""
        if threading.current_thread() is not threading.main_thread():
            yield self
            return
        for signum in STOP_SIGNALS:
            if signal.getsignal(signum) is not signal.SIG_IGN:
                self._previous[signum] = signal.signal(signum, self._handle)
        try:
            yield self
        finally:
            for signum, handler in self._previous.items():
                signal.signal(signum, handler)
