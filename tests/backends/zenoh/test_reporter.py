"""The reporter (node/reporter.py): a worker's reports leave from their own thread, in order, big
messages through the spill directory; at most MAX_PENDING reports and MAX_PENDING_BYTES of messages
wait; a failure is told, not lost.

Real Zenoh session and subscriber (a congested or broken link: a put the test gives the reporter);
each test waits on events its own messages set, never on time alone (the timeouts only bound a
broken run).
"""

from __future__ import annotations

import threading
import time

import pytest

from retriever.backends.zenoh.node import FLUSH_MAX_SEQS
from retriever.backends.zenoh.protocol import RESTART_SEQ_GAP
from retriever.backends.zenoh.node.reporter import (MAX_PENDING, MAX_PENDING_BYTES, MAX_PENDING_SEQS, Reporter,
                                                    session_put)
from retriever.backends.zenoh.protocol import Report
from retriever.backends.zenoh.wire import KeySpace
from retriever.errors import ReportError
from retriever.flow.burst import MAX_BURST

KEYS = KeySpace("reporter-test")
KEY = KEYS.report("cam")
SENTINEL = f"{KEYS.prefix}/zz/end"
RECORD = ((5, 0), {"x": (("src", "value", 1),)}, (("cam", "image", 0),), "ok", None, 100, 7)


class Received(list):
    """The reports put on KEY, decoded, in arrival order; ``settle()`` returns once everything
    put before it has arrived (the session delivers its own puts in order)."""

    def __init__(self, session):
        super().__init__()
        self.session, self.done = session, threading.Event()
        self.sub = session.declare_subscriber(f"{KEYS.prefix}/**", self._on_sample)

    def _on_sample(self, sample) -> None:
        if str(sample.key_expr) == SENTINEL:
            self.done.set()
        else:
            self.append(Report.decode(sample.payload.to_bytes(), node="cam"))

    def settle(self) -> "Received":
        self.session.put(SENTINEL, b"")
        assert self.done.wait(timeout=30), "the session's own sentinel never came back"
        return self


@pytest.fixture
def reports(session):
    got = Received(session)
    yield got
    got.sub.undeclare()


def test_reports_go_out_in_order_and_close_returns_once_they_are_out(session, reports, tmp_path):
    reporter = Reporter(session, KEY, "cam", spill_dir=str(tmp_path), spill_bytes=1000)
    big = b"B" * 1000
    for k in range(6):
        reporter.send([RECORD], [(k, b"small"), (k, big)])
    reporter.close()
    assert reporter.thread is None
    reports.settle()
    assert [[wall for wall, _ in r.events] for r in reports] == [[k, k] for k in range(6)]
    for k, report in enumerate(reports):
        assert report.node == "cam" and report.records == (RECORD,)
        small, spilled = report.events[0][1], report.events[1][1]
        assert small == b"small", "messages under spill_bytes travel inside the report"
        assert isinstance(spilled, str) and (tmp_path / spilled).read_bytes() == big, "big ones as files"
    assert len({r.events[1][1] for r in reports}) == 6, "one file per message"


def test_without_a_spill_directory_big_messages_travel_in_the_report(session, reports):
    reporter = Reporter(session, KEY, "cam", spill_dir=None, spill_bytes=10)
    reporter.send([], [(1, b"x" * 100)])
    reporter.close()
    assert [r.events for r in reports.settle()] == [((1, b"x" * 100),)]


class CongestedLink:
    """A put on KEY that blocks until ``free()``: a reporter given it piles its reports up unsent."""

    def __init__(self, session):
        self.free_now = threading.Event()
        self.session_put = session_put(session, KEY)

    def put(self, payload, attachment):
        assert self.free_now.wait(timeout=30), "the test never freed the link"
        self.session_put(payload, attachment)

    def free(self) -> None:
        self.free_now.set()


def test_at_most_max_pending_reports_wait_then_the_loop_waits_too(session, reports):
    link = CongestedLink(session)
    reporter = Reporter(session, KEY, "cam", spill_dir=None, spill_bytes=1 << 20, put=link.put)
    for k in range(MAX_PENDING):
        assert reporter.has_room(1)
        reporter.send([], [(k, b"m")])  # none of these waits
    assert not reporter.has_room(1), f"a {MAX_PENDING + 1}th send would wait"
    link.free()
    reporter.close()
    assert reporter.waits == 0 and reporter.waited_ns == 0
    assert [r.events[0][0] for r in reports.settle()] == list(range(MAX_PENDING)), "nothing lost or reordered"


def test_the_seqs_of_waiting_reports_are_bounded_below_the_restart_gap(session, reports):
    """A burst is many seqs in a few bytes: the seqs a process may have published unknown to the
    coordinator (the loop's unflushed ones, the reporter's waiting ones) stay below the gap a
    restarted flow's streams leave (RESTART_SEQ_GAP), or its new seqs could be the old ones."""
    assert FLUSH_MAX_SEQS + MAX_BURST + max(MAX_PENDING_SEQS, FLUSH_MAX_SEQS + MAX_BURST) < RESTART_SEQ_GAP
    link = CongestedLink(session)
    reporter = Reporter(session, KEY, "cam", spill_dir=None, spill_bytes=1 << 20, put=link.put, max_pending_seqs=1000)
    reporter.send([], [(0, b"a")], seqs=600)
    assert not reporter.has_room(1, seqs=500), "600 + 500 seqs would pass 1000"
    assert reporter.has_room(1, seqs=400)
    link.free()
    reporter.close()
    assert reporter.has_room(1, seqs=5000), "with nothing waiting, even a report over the bound goes"
    assert [r.events[0][0] for r in reports.settle()] == [0]


def test_the_bytes_held_by_waiting_reports_are_bounded_too(session, reports):
    assert MAX_PENDING_BYTES >= 16 * (16 << 20), "room for 16 frames of 16 MiB (see the reporter's docstring)"
    link = CongestedLink(session)
    reporter = Reporter(session, KEY, "cam", spill_dir=None, spill_bytes=1 << 20, put=link.put, max_pending_bytes=250)
    reporter.send([], [(0, b"a" * 100)])
    reporter.send([], [(1, b"b" * 100)])
    assert not reporter.has_room(100), "a third message of 100 bytes would pass 250"
    assert reporter.has_room(50)
    link.free()
    reporter.close()
    assert reporter.has_room(1000), "with nothing waiting, even a report over the bound goes"
    assert [r.events[0][0] for r in reports.settle()] == [0, 1]


class WatchedRoom(threading.Condition):
    """The reporter's condition, telling the test when a send starts waiting for room."""

    def __init__(self) -> None:
        super().__init__()
        self.waiting = threading.Event()

    def wait(self, timeout=None):
        self.waiting.set()
        return super().wait(timeout)


def test_a_report_that_waits_for_room_goes_once_the_link_frees(session, reports):
    link = CongestedLink(session)
    reporter = Reporter(session, KEY, "cam", spill_dir=None, spill_bytes=1 << 20, put=link.put, max_pending=1)
    reporter.room = room = WatchedRoom()
    reporter.send([], [(0, b"m")])
    sent = threading.Event()

    def second() -> None:
        reporter.send([], [(1, b"m")])
        sent.set()

    loop = threading.Thread(target=second)
    loop.start()
    assert room.waiting.wait(timeout=30), "the second send did not wait for room"
    assert not sent.is_set(), "the second send waits while the first report is unsent"
    link.free()
    assert sent.wait(timeout=30), "the waiting send never went"
    loop.join()
    reporter.close()
    assert [r.events[0][0] for r in reports.settle()] == [0, 1]
    assert reporter.waits == 1 and reporter.waited_ns > 0, "the wait is counted (the node loop reports it)"


def test_a_failed_report_is_raised_naming_the_node(session):
    def broken(payload, attachment):
        raise RuntimeError("link down")

    reporter = Reporter(session, KEY, "cam", spill_dir=None, spill_bytes=1 << 20, put=broken)
    reporter.send([], [(1, b"m")])
    with pytest.raises(ReportError, match="worker 'cam' could not report to the coordinator: RuntimeError: link down"):
        reporter.close()
    with pytest.raises(ReportError):
        reporter.send([], [(2, b"m")])


class TimedLink:
    """A put on KEY that notes when (time.monotonic_ns) each report went, and tells the test."""

    def __init__(self, session):
        self.session_put = session_put(session, KEY)
        self.times: list[int] = []
        self.went = threading.Semaphore(0)

    def put(self, payload, attachment):
        self.times.append(time.monotonic_ns())
        self.session_put(payload, attachment)
        self.went.release()

    def wait(self) -> None:
        assert self.went.acquire(timeout=30), "a report never went"


def test_a_deferred_report_goes_at_its_time_or_at_once_when_another_comes_behind_it_or_it_closes(session, reports):
    """The loop defers its report into its idle time (reporter.py): the report waits until
    ``not_before``; one handed over behind it, or the reporter's close, sends it at once."""
    link = TimedLink(session)
    reporter = Reporter(session, KEY, "cam", spill_dir=None, spill_bytes=1 << 20, put=link.put)
    not_before = time.monotonic_ns() + 200_000_000
    reporter.send([], [(0, b"a")], not_before=not_before)
    link.wait()
    assert link.times[0] >= not_before, "a deferred report waits for its time"

    start = time.monotonic_ns()
    reporter.send([], [(1, b"b")], not_before=start + 3600 * 10**9)
    reporter.send([], [(2, b"c")])
    link.wait()
    link.wait()
    reporter.send([], [(3, b"d")], not_before=time.monotonic_ns() + 3600 * 10**9)
    reporter.close()
    assert len(link.times) == 4 and link.times[-1] - start < 30 * 10**9, "none waited its hour"
    assert [r.events[0][0] for r in reports.settle()] == [0, 1, 2, 3], "in order"


def test_a_send_that_waits_for_room_held_by_a_deferred_report_sends_that_report_at_once(session, reports):
    link = TimedLink(session)
    reporter = Reporter(session, KEY, "cam", spill_dir=None, spill_bytes=1 << 20, put=link.put, max_pending=1)
    start = time.monotonic_ns()
    reporter.send([], [(0, b"a")], not_before=start + 3600 * 10**9)
    reporter.send([], [(1, b"b")])  # no room while the first waits: it goes now, then this one
    reporter.close()
    assert reporter.waits == 1 and link.times[-1] - start < 30 * 10**9, "neither waited the hour"
    assert [r.events[0][0] for r in reports.settle()] == [0, 1]
