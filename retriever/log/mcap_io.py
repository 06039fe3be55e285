"""``WriteQueue``: the log's one I/O thread. Compression and file writes run there, in call order
(zstd and file writes release the GIL), so they overlap the run instead of pausing it.

Two things flow back to the callers: the first write that failed, raised at their next call; and
back-pressure: past ``max_queued`` bytes handed over and not yet written, whoever hands over more
waits for the disk (a run faster than its disk would otherwise grow its memory without bound).
"""

from __future__ import annotations

import threading
import time
from concurrent.futures import ThreadPoolExecutor
from typing import Any, Callable


def _nothing() -> None:
    """A job for the I/O thread whose end tells that every job queued before it is done."""


class WriteQueue:
    """Jobs run one at a time on the I/O thread, in the order they were submitted."""

    def __init__(self, max_queued: int):
        self._io = ThreadPoolExecutor(max_workers=1, thread_name_prefix="retriever-log-io")
        self._max_queued = max_queued
        self._queued = 0  # bytes handed to the I/O thread and not yet written
        self._written = threading.Condition()
        #: how often submitting waited for the disk (``max_queued``), and for how long in all
        self.waits, self.waited_ns = 0, 0
        self._failure: BaseException | None = None

    @property
    def queued_bytes(self) -> int:
        """Bytes handed to the I/O thread and not yet written (past ``max_queued``, submits wait)."""
        return self._queued

    def submit(self, job: Callable[..., Any], *args: Any, size: int = 0) -> None:
        """Queue ``job(*args)``, which writes ``size`` bytes (counted as queued until it is done),
        once the queue is short enough. Raises the first write that failed, if one did."""
        if size:
            self._reserve(size)
        self.check()
        self._io.submit(self._run, job, args, size)

    def wait(self) -> None:
        """Block until every queued job is done; raise the first write that failed."""
        self._io.submit(_nothing).result()
        self.check()

    def check(self) -> None:
        """Raise the first write that failed, if one did."""
        if self._failure is not None:
            raise self._failure

    def close(self) -> None:
        """Let the queued jobs end (after a failure: let the thread end); no job runs after."""
        self._io.shutdown(wait=True)

    def _run(self, job: Callable[..., Any], args: tuple, size: int) -> None:
        try:
            if self._failure is None:
                job(*args)
        except BaseException as e:  # reported to the caller at its next call
            with self._written:  # a caller waiting for the disk stops waiting
                self._failure = e
                self._written.notify_all()
        finally:
            if size:
                self._written_out(size)

    def _reserve(self, size: int) -> None:
        """Count ``size`` bytes as queued, once the queue is short enough (``max_queued``)."""
        with self._written:
            if self._queued > self._max_queued and self._failure is None:
                began = time.monotonic_ns()
                self.waits += 1
                self._written.wait_for(lambda: self._queued <= self._max_queued or self._failure is not None)
                self.waited_ns += time.monotonic_ns() - began
            self._queued += size

    def _written_out(self, size: int) -> None:
        with self._written:
            self._queued -= size
            self._written.notify_all()
