"""A worker's reports to the coordinator, sent from a thread of their own.

A node loop batches its step records and the data messages it published (reports.py) and
hands each batch to its :class:`Reporter`. The reporter writes the big messages to files of
the run's spill directory (the coordinator maps them: one copy, none on its side) and puts the
report on ``status/report/<node>``. Both take time that has nothing to do with the node's
ticks: writing a camera frame of megabytes to fresh shared memory can take longer than a 20 Hz
period, and a node that did it between ticks would fall further behind with each frame
(benchmarks/reports/latency.md). On their own thread they overlap the loop (file writes and puts
release the GIL).

A report may be handed over with a time before which it does not go (``not_before``): the loop
hands its report over right after a tick that published, and the reporter's work (spilling the
frames, the put) and the coordinator's (mapping them, recording) then ran beside that tick's
messages on their way, and made them late: on a 2-core host, frames of 256 KiB-4 MiB that met a
report on their way took 1.4-3 times as long to arrive (benchmarks/reports/latency.md,
2026-12-05 lat13). So the loop defers its report into the idle time before its next wake. A
report goes at once, whatever its time, when another is handed over behind it (the loop is
ahead of the reporter), a send waits for room, or the reporter closes.

Reports go out in the order they were handed over. At most MAX_PENDING reports, holding at most
MAX_PENDING_BYTES of messages, wait; a loop further ahead waits for the reporter, as it would for
a congested link. The bound is in bytes because big messages are what falls behind: memory a
machine never touched before is handed out slower than a stream of 16 MiB frames at 20 Hz
(320 MB/s) may need, so the reporter can fall behind for a while, and a bound of a few frames
would stall the loop within seconds (the last frames of a run would get tags past its end).
256 MiB (16 such frames) lets such a stretch pass; how long a stretch depends on the machine
(benchmarks/reports/latency.md).
:meth:`Reporter.close` returns once every report is out, so a worker's last status message comes
after its last report.

How a report leaves is the reporter's ``put``: a reliable put on the node's report key
(:func:`session_put`) unless its maker passes another (a test, a congested or broken link).
"""

from __future__ import annotations

import contextlib
import os
import queue
import threading
import time
from collections.abc import Callable

import zenoh

from ....errors import ReportError
from ..origin import sign
from ..protocol import Report
from ..wire import RELIABLE

#: reports handed over and not yet sent, at most; and the bytes of messages they hold, at most
#: (a single report bigger than that still goes, once nothing else waits)
MAX_PENDING = 64
MAX_PENDING_BYTES = 256 << 20
#: and the seqs their events used, at most (a burst is many seqs in a few bytes): this bounds the
#: seqs a process may have published unknown to the coordinator (RESTART_SEQ_GAP in frontiers.py)
MAX_PENDING_SEQS = 1 << 19

#: ``put(payload, attachment)``: sends one encoded report, signed (``attachment``) or not (None)
Put = Callable[[bytes, bytes | None], None]


def session_put(session: zenoh.Session, key: str) -> Put:
    """How reports leave unless told otherwise: a reliable put on ``key`` of ``session`` (a
    congested link holds it, rather than drop a report)."""

    def put(payload: bytes, attachment: bytes | None) -> None:
        session.put(key, payload, congestion_control=RELIABLE, attachment=attachment)

    return put


class Reporter:
    """Sends one node's reports, in order, from its own thread (started on the first report),
    each through ``put`` (default: :func:`session_put` on ``key`` of ``session``)."""

    def __init__(self, session: zenoh.Session, key: str, node: str, *, spill_dir: str | None, spill_bytes: int,
                 put: Put | None = None, max_pending: int = MAX_PENDING, max_pending_bytes: int = MAX_PENDING_BYTES,
                 max_pending_seqs: int = MAX_PENDING_SEQS):
        self.key_expr, self.node = key, node
        self.put = put if put is not None else session_put(session, key)
        self.spill_dir, self.spill_bytes = spill_dir, spill_bytes
        #: this process's key, which signs each report (origin.py; set by the worker)
        self.key: bytes | None = None
        self.max_pending, self.max_pending_bytes = max_pending, max_pending_bytes
        self.max_pending_seqs = max_pending_seqs
        self.queue: queue.SimpleQueue = queue.SimpleQueue()
        self.room = threading.Condition()  # guards the counts below, and tells a deferred report what changed
        self.crowded = False  # a send waits for room (a deferred report then goes at once)
        self.closing = False  # close() was called: a deferred report goes at once
        self.pending = 0  # reports handed over, not yet sent
        self.pending_bytes = 0  # bytes of the messages in them
        self.pending_seqs = 0  # seqs of the events they were published with
        self.thread: threading.Thread | None = None
        self.error: BaseException | None = None
        self.spilled = 0  # files written to spill_dir
        self.sent = 0  # reports put (the last status says how many: the coordinator waits for them all)
        self.waits = 0  # sends that had to wait for room
        self.waited_ns = 0  # and for how long in all (the loop's time, not its ticks')

    def send(self, records: list, events: list[tuple[int, bytes]], seqs: int = 0, not_before: int | None = None) -> None:
        """Hand over step records and ``(wall ns, data message)`` pairs (of events that used
        ``seqs`` seqs); waits only while the reports still unsent leave no room for these
        (MAX_PENDING, MAX_PENDING_BYTES, MAX_PENDING_SEQS). ``not_before``: a
        ``time.monotonic_ns()`` before which this report does not go, unless another is handed
        over behind it, a send waits for room, or the reporter closes (the module's docstring says
        why)."""
        self._raise()
        if self.thread is None:
            self.thread = threading.Thread(target=self._run, name=f"retriever-report-{self.node}", daemon=True)
            self.thread.start()
        size = sum(len(message) for _, message in events)
        with self.room:
            if not self.has_room(size, seqs):
                start = time.monotonic_ns()
                self.crowded = True
                self.room.notify_all()
                self.room.wait_for(lambda: self.has_room(size, seqs) or self.error is not None)
                self.crowded = False
                self.waits += 1
                self.waited_ns += time.monotonic_ns() - start
            self._raise()
            self.pending += 1
            self.pending_bytes += size
            self.pending_seqs += seqs
            self.room.notify_all()  # (one more pending: a deferred report before it goes now)
        self.queue.put((records, events, size, seqs, not_before))

    def has_room(self, size: int, seqs: int = 0) -> bool:
        """Whether a report holding ``size`` bytes of messages (``seqs`` seqs) would go without waiting."""
        return self.pending == 0 or (self.pending < self.max_pending
                                     and self.pending_bytes + size <= self.max_pending_bytes
                                     and self.pending_seqs + seqs <= self.max_pending_seqs)

    def close(self) -> None:
        """Return once every report handed over is out (then no more may be sent)."""
        if self.thread is not None:
            with self.room:
                self.closing = True
                self.room.notify_all()
            self.queue.put(None)
            self.thread.join()
            self.thread = None
            self.closing = False
        self._raise()

    def _raise(self) -> None:
        if self.error is not None:
            raise ReportError(f"worker '{self.node}' could not report to the coordinator: "
                              f"{type(self.error).__name__}: {self.error}") from self.error

    def _run(self) -> None:
        while (item := self.queue.get()) is not None:
            records, events, size, seqs, not_before = item
            try:
                if not_before is not None:
                    self._defer(not_before)
                if self.error is None:
                    self._deliver(records, events)
            except BaseException as exc:  # told to the loop at its next report
                self.error = exc
            finally:
                with self.room:
                    self.pending -= 1
                    self.pending_bytes -= size
                    self.pending_seqs -= seqs
                    self.room.notify_all()

    def _defer(self, not_before: int) -> None:
        """Wait until ``not_before`` (monotonic ns), unless another report was handed over behind
        this one, a send waits for room, or the reporter closes."""
        with self.room:
            while not (self.pending > 1 or self.crowded or self.closing):
                left = not_before - time.monotonic_ns()
                if left <= 0:
                    return
                self.room.wait(left / 1e9)

    def _deliver(self, records: list, events: list[tuple[int, bytes]]) -> None:
        """One report: its big messages spilled, encoded, signed, put."""
        if self.spill_dir is not None:
            events = [(wall, self._spill(message)) if len(message) >= self.spill_bytes else (wall, message)
                      for wall, message in events]
        payload = Report(node=self.node, records=tuple(records), events=tuple(events)).encode()
        self.put(payload, sign(self.key, self.key_expr, payload) if self.key is not None else None)
        self.sent += 1

    def _spill(self, message: bytes) -> bytes | str:
        """Write a published message to a file of the spill directory, whose name goes in the
        report (the coordinator maps the file and removes it); the message itself if that fails."""
        self.spilled += 1
        name = f"{self.node}.{os.getpid()}.{self.spilled}.msg"
        try:
            fd = os.open(os.path.join(self.spill_dir, name), os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
        except OSError:  # the directory is gone or full: the report carries it
            return message
        try:
            view = memoryview(message)
            while view:
                view = view[os.write(fd, view):]
        except OSError:
            with contextlib.suppress(OSError):
                os.unlink(os.path.join(self.spill_dir, name))
            return message
        finally:
            os.close(fd)
        return name
