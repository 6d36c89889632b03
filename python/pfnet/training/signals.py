"""Safe stopping: Ctrl-C / SIGTERM end a run with a saved state, never with a traceback.

A terminal's Ctrl-C sends SIGINT to the whole process group. Only the training process acts on
it (it finishes the batch, saves ``last.pt`` and exits with 130): its data-loader workers,
their fork server and multiprocessing's resource tracker hold SIGINT and SIGTERM blocked from
their first instruction (:mod:`pfnet.processes`). The training process never changes its own
handlers for them: a signal sent at any moment, while the helpers start included, reaches it.
"""

from __future__ import annotations

import contextlib
import signal
import threading
from collections.abc import Callable, Iterator
from typing import Any

from pfnet.processes import STOP_SIGNALS

STOP_NOTICE = "stopping at the next safe point and saving (Ctrl-C again to abort)"
"""What a caller says when a signal asks a run to stop (:class:`StopRequest`'s ``on_stop``)."""


class StopRequest:
    """SIGINT/SIGTERM handler: the first signal asks the run to stop at the next safe point.

    A second SIGINT raises ``KeyboardInterrupt`` (abort without waiting); checkpoint files
    are replaced atomically, so even then the previous ``last.pt`` stays intact.
    """

    def __init__(self, on_stop: Callable[[], None] | None = None) -> None:
        """``on_stop`` is called when the first signal asks the run to stop (``pfnet train``
        says so, in :data:`STOP_NOTICE`'s words)."""
        self.requested = False
        self._on_stop = on_stop
        self._previous: dict[int, Any] = {}

    def _handle(self, signum: int, _frame: object) -> None:
        if self.requested and signum == signal.SIGINT:
            raise KeyboardInterrupt
        self.requested = True
        if self._on_stop is not None:
            self._on_stop()

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
