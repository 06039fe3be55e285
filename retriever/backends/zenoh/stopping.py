"""A stop that SIGTERM and SIGINT (or any signals given) ask for, safe to ask from a signal
handler: the long-lived processes (``retriever worker``, ``retriever router``, a run's router
process) wait on it between their checks.

Not a ``threading.Event``: its ``set()`` takes the Event's lock, and a handler runs in the main
thread between two bytecodes, where that same thread may hold the lock already, inside the
Event's own ``wait()`` (re-taking it as a timed wait ends): the handler then waits for itself
forever. A run's router process was found so, its daemon SIGKILLed, the process left running with
its stack in ``Event.set`` under ``_PyErr_CheckSignals``. Here the handler only stores the signal
and writes a byte to a pipe (both safe wherever it lands); :meth:`Stop.wait` selects on the pipe,
so it returns as soon as a signal came.
"""

from __future__ import annotations

import os
import select
import signal


class Stop:
    """Asked for by one of ``signums`` (the handlers are installed at once)."""

    def __init__(self, *signums: int):
        self._read, self._write = os.pipe()
        os.set_blocking(self._write, False)
        self.signal: int | None = None  # the first that asked
        for signum in signums:
            signal.signal(signum, self._asked)

    def _asked(self, signum, frame) -> None:
        if self.signal is None:
            self.signal = signum
        try:
            os.write(self._write, b"\0")
        except BlockingIOError:  # (the pipe is full of earlier asks: one is enough)
            pass

    def is_set(self) -> bool:
        """Whether a stop was asked for."""
        return self.signal is not None

    def wait(self, timeout: float) -> bool:
        """Wait up to ``timeout`` seconds for a stop; whether one was asked for."""
        if self.signal is None:
            select.select([self._read], [], [], timeout)
        return self.signal is not None
