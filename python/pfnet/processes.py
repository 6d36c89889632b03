"""Worker processes that leave Ctrl-C to the process that started them.

A terminal's Ctrl-C sends SIGINT to the whole process group: the pfnet process, its worker
processes (``train``'s data-loader workers, ``prepare``'s pool), the fork server that starts
them and multiprocessing's resource tracker. Only the pfnet process may act on it; a helper
that died of it breaks the next batch fetch (the old ``BrokenPipeError`` of a fork server
killed while it imported torch), and a pool worker killed half-way through a message leaves
the pool's pipes and locks unusable, so that shutting the pool down waits for ever. The
helpers are therefore spawned with SIGINT and SIGTERM *blocked* in their signal mask: a mask
set by ``posix_spawn`` survives exec and fork, so the fork server and every worker it forks
hold both signals from their first instruction (multiprocessing's own spawn clears the mask,
so :func:`start_helpers` swaps in :func:`spawn_shielded` while it starts them). The pfnet
process never changes its own handlers for this: a signal sent at any moment, while the
helpers start included, reaches it (ignoring them there for the spawn lost a Ctrl-C sent in
those milliseconds).
"""

from __future__ import annotations

import contextlib
import multiprocessing
import multiprocessing.context
import multiprocessing.pool
import os
import signal
import threading
from collections.abc import Iterable, Iterator, Sequence

STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM)
# How long closing a pool may take before its workers are killed (a safety net: shielded
# workers are never killed half-way through a message by a Ctrl-C).
POOL_CLOSE_SECONDS = 10.0


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


def start_helpers(preload: Sequence[str]) -> multiprocessing.context.BaseContext:
    """The multiprocessing context for worker processes, its helpers started shielded.

    Workers come from a fork server that has imported ``preload`` but runs nothing: a plain
    ``fork`` of a process that runs CUDA or several threads copies their state without the
    threads, and the fork server's forks are cheap. The fork server and the resource
    tracker are spawned here by :func:`spawn_shielded` (see the module docstring); the
    preload list counts only for the first fork server of a process.
    """
    from multiprocessing import forkserver, util

    context = multiprocessing.get_context("forkserver")
    context.set_forkserver_preload(list(preload))
    spawn = util.spawnv_passfds
    util.spawnv_passfds = spawn_shielded
    try:
        forkserver.ensure_running()
    finally:
        util.spawnv_passfds = spawn
    return context


def ignore_stop_signals(*_args: object) -> None:
    """``worker_init_fn``: a data-loader worker leaves stopping to the training process.

    Already so when the fork server was started by :func:`start_helpers`; this covers a fork
    server that someone else started first.
    """
    for signum in STOP_SIGNALS:
        signal.signal(signum, signal.SIG_IGN)


def _pool_worker_init() -> None:
    """Pool initializer: Ctrl-C is the parent's; SIGTERM stops the worker.

    ``Pool.terminate`` stops its workers with SIGTERM, so only SIGINT stays ignored (a
    SIGINT pending since the fork is discarded with it)."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_DFL)
    signal.pthread_sigmask(signal.SIG_UNBLOCK, STOP_SIGNALS)


@contextlib.contextmanager
def worker_pool(workers: int, preload: Sequence[str]) -> Iterator[multiprocessing.pool.Pool]:
    """A process pool whose workers ignore Ctrl-C, terminated when the block ends.

    Only the calling process sees a Ctrl-C (as ``KeyboardInterrupt``); the workers go on
    until the pool is terminated, so none dies holding one of the pool's locks or half-way
    through a message. A Ctrl-C while the pool starts takes effect once it has started: a
    worker still reading its start-up data when this process exits would fail loudly.
    Terminating is bounded all the same (:func:`close_pool`).
    """
    pool = None
    try:
        with _sigint_deferred():
            pool = start_helpers(preload).Pool(workers, initializer=_pool_worker_init)
        yield pool
    finally:
        if pool is not None:
            close_pool(pool)


@contextlib.contextmanager
def _sigint_deferred() -> Iterator[None]:
    """SIGINT held back while the block runs and raised again after it (main thread only;
    an ignored SIGINT stays ignored)."""
    previous = signal.getsignal(signal.SIGINT)
    main = threading.current_thread() is threading.main_thread()
    if previous in (signal.SIG_IGN, None) or not main:
        yield
        return
    caught: list[int] = []
    signal.signal(signal.SIGINT, lambda signum, _frame: caught.append(signum))
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)
        if caught:
            signal.raise_signal(signal.SIGINT)


def close_pool(pool: multiprocessing.pool.Pool, timeout: float = POOL_CLOSE_SECONDS) -> None:
    """Terminate ``pool`` and wait for it; after ``timeout`` seconds, kill its workers and go.

    A worker that died while holding one of the pool's locks or half-way through a message
    makes ``Pool.terminate`` wait for ever; the wait is left to a daemon thread. An error of
    the shutdown itself is raised here.
    """
    errors: list[BaseException] = []

    def terminate() -> None:
        try:
            pool.terminate()
            pool.join()
        except BaseException as err:  # raised in the caller's thread below
            errors.append(err)

    closer = threading.Thread(target=terminate, name="pfnet-pool-close", daemon=True)
    closer.start()
    closer.join(timeout)
    if closer.is_alive():
        for process in list(getattr(pool, "_pool", ())):
            with contextlib.suppress(OSError, ValueError):
                process.kill()
        closer.join(timeout)
    if errors:
        raise errors[0]


def usable_cpus() -> int:
    """The CPU cores this process may run on (its affinity mask; all of them where unknown)."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not available on macOS
        return os.cpu_count() or 1


def threads_per_process(processes: int, cpus: int | None = None) -> int:
    """Torch threads for each of ``processes`` busy processes sharing ``cpus`` cores.

    Each torch process starts one OpenMP thread per core, and processes that each have that
    many do not share the cores gracefully: their threads spin-wait on each other. On a 2-core
    machine an epoch of a small-preset run that took 10 s alone took 67-124 s beside a second
    such run and a test suite, where three runs of one thread each took 27 s an epoch.

    Args:
        processes: How many processes run at once.
        cpus: Cores to share (default: :func:`usable_cpus`).
    """
    cpus = usable_cpus() if cpus is None else cpus
    return max(1, cpus // max(1, processes))


def idle_cpus(cpus: int | None = None, load: float | None = None) -> int:
    """The cores not busy with other work: ``cpus`` minus the one-minute load average
    (rounded), at least one.

    What ``pfnet train`` gives torch by default. Under load, torch's own default (a thread
    per core) oversubscribes the cores: a small-preset step on this 2-core machine beside two
    other runs took 1.39 s with 2 threads and 0.81 s with 1 (docs/training.md).

    Args:
        cpus: Cores this process may use (default: :func:`usable_cpus`).
        load: Runnable processes on the machine (default: ``os.getloadavg()[0]``; none where
            unknown).
    """
    cpus = usable_cpus() if cpus is None else cpus
    if load is None:
        try:
            load = os.getloadavg()[0]
        except (AttributeError, OSError):  # not available on Windows
            load = 0.0
    return max(1, cpus - int(load + 0.5))
