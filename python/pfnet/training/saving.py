"""When and how a training run writes its checkpoints without stalling the training.

``last.pt`` (the full state, for ``--resume``) is written every ``save_every`` (a time such
as ``10min``, or a number of epochs), at the end, and when the run is stopped; ``best.pt``
(what inference needs) whenever validation improves. The state is copied to the CPU in the
training thread (a consistent snapshot) and serialised on a background thread, so the next
steps overlap the write; every file is replaced atomically, so a reader or an interrupted
run only ever sees the previous complete file or the new one.
"""

from __future__ import annotations

import threading
import time
from pathlib import Path
from typing import Any

import torch

from pfnet.errors import DataError


def cpu_snapshot(obj: Any) -> Any:
    """A deep copy of ``obj`` with every tensor copied to the CPU (nothing shared with it).

    The training thread takes the snapshot; the writer thread may then serialise it while
    the live parameters and optimiser states keep changing.
    """
    if isinstance(obj, torch.Tensor):
        return obj.detach().to("cpu", copy=True)
    if isinstance(obj, dict):
        return {key: cpu_snapshot(value) for key, value in obj.items()}
    if isinstance(obj, list | tuple):
        return type(obj)(cpu_snapshot(value) for value in obj)
    return obj


class CheckpointWriter:
    """Writes checkpoints on one background thread, newest state per file.

    :meth:`submit` queues a snapshot and returns at once; a snapshot of a file that is
    still waiting is replaced by the newer one (only the newest state of a file matters).
    :meth:`flush` waits until everything submitted is on disk. A failed write is raised
    by the next :meth:`submit` or :meth:`flush` in the training thread. The thread is not a
    daemon: a file being written when the interpreter exits is completed first.

    Use as a context manager; leaving it flushes and stops the thread.
    """

    def __init__(self) -> None:
        from pfnet.inference.checkpoint import save_checkpoint

        self._save = save_checkpoint
        self._pending: dict[Path, dict[str, Any]] = {}
        self._busy = False
        self._closed = False
        self._error: BaseException | None = None
        self._condition = threading.Condition()
        self._thread = threading.Thread(target=self._work, name="pfnet-checkpoints")
        self._thread.start()
        self.seconds_writing = 0.0

    def __enter__(self) -> CheckpointWriter:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close(raise_errors=exc[0] is None)

    def submit(self, path: Path, state: dict[str, Any]) -> None:
        """Queue ``state`` (a :func:`cpu_snapshot`) to be written to ``path``."""
        with self._condition:
            self._raise_error()
            self._pending[Path(path)] = state
            self._condition.notify_all()

    def flush(self) -> None:
        """Wait until every submitted checkpoint is written."""
        with self._condition:
            while (self._pending or self._busy) and self._error is None:
                self._condition.wait()
            self._raise_error()

    def close(self, raise_errors: bool = True) -> None:
        """Write what is queued, then stop the thread."""
        with self._condition:
            self._closed = True
            self._condition.notify_all()
        self._thread.join()
        if raise_errors:
            with self._condition:
                self._raise_error()

    def _raise_error(self) -> None:
        error, self._error = self._error, None
        if error is not None:
            raise error

    def _work(self) -> None:
        while True:
            with self._condition:
                while not self._pending and not self._closed:
                    self._condition.wait()
                if not self._pending:
                    return
                path = next(iter(self._pending))
                state = self._pending.pop(path)
                self._busy = True
            started = time.perf_counter()
            try:
                self._save(path, state)
            except OSError as err:
                error: BaseException | None = DataError(
                    f"cannot write checkpoint {path}: {err.strerror or err}"
                )
            except BaseException as err:  # re-raised in the training thread
                error = err
            else:
                error = None
            with self._condition:
                self.seconds_writing += time.perf_counter() - started
                self._busy = False
                if error is not None:
                    self._error = error
                    self._pending.clear()
                self._condition.notify_all()
