"""When a node loop's step records and published events go to the coordinator (node/reports.py,
FLUSH_AFTER_NS, RECORDS_FLUSH_AFTER_NS): events within 100 ms, records alone within a second (an idle flow's
ten reports a second were a quarter of its CPU, issue 21).

A real NodeLoop, rebuilt from the IR as a worker does, on a real (unconnected) Zenoh session, its
clock read from a variable: no test here waits on the wall clock.
"""

from __future__ import annotations

import threading

import pytest

from retriever import Pipeline, Rate, Trigger
from retriever.backends.zenoh.node import FLUSH_AFTER_NS, RECORDS_FLUSH_AFTER_NS
from retriever.backends.zenoh.worker.build import build_loop

from .payload_flows import Camera, Viewer, frame
from .specs import run_spec

MS = 1_000_000


@pytest.fixture
def cam(session):
    with Pipeline("batching") as pipe:
        camera = Camera(size=4096).named("cam") @ Rate(20)
        camera.then(Viewer().named("viewer") @ Trigger("image"))
    loop = build_loop(run_spec(pipe.compile().to_ir().doc, "batching-test"), "cam", session)
    loop.declare()
    clock = {"now": 0}
    loop.run_clock.now = lambda: clock["now"]
    try:
        yield loop, clock
    finally:
        loop.undeclare()


def record(loop, t: int) -> None:
    loop.reports.record((t, 0), {}, [], "ok", None, t, 0)


def publish(loop, t: int, seq: int) -> None:
    loop.outputs.publish([((t, 1), "image", frame(seq, 4096).reshape(-1, 1024), seq)])


def test_step_records_alone_wait_up_to_a_second(cam):
    loop, clock = cam
    assert RECORDS_FLUSH_AFTER_NS > FLUSH_AFTER_NS
    clock["now"] = 7 * MS
    record(loop, 7 * MS)
    assert loop.reports.flush_due == 7 * MS + RECORDS_FLUSH_AFTER_NS
    clock["now"] = 57 * MS
    record(loop, 57 * MS)
    assert loop.reports.flush_due == 7 * MS + RECORDS_FLUSH_AFTER_NS, "the oldest record sets it"


def test_a_published_event_brings_the_report_forward_to_100_ms(cam):
    loop, clock = cam
    record(loop, 0)
    clock["now"] = 300 * MS
    publish(loop, 300 * MS, 0)  # records waiting since 0: now with an event, they go within 100 ms of it
    assert loop.reports.flush_due == 300 * MS + FLUSH_AFTER_NS
    clock["now"] = 350 * MS
    publish(loop, 350 * MS, 1)
    record(loop, 350 * MS)
    assert loop.reports.flush_due == 300 * MS + FLUSH_AFTER_NS, "the oldest event sets it"


def test_an_event_first_then_its_record_goes_within_100_ms(cam):
    loop, clock = cam
    clock["now"] = 20 * MS
    publish(loop, 20 * MS, 0)
    record(loop, 20 * MS)
    assert loop.reports.flush_due == 20 * MS + FLUSH_AFTER_NS


def test_a_report_of_step_records_alone_is_not_deferred(cam):
    """The loop defers a report into its idle time (reporter.py) for the events it carries; one of
    records alone goes at once: nothing big goes with it, and its thread wakes once, not twice."""
    loop, clock = cam
    went = threading.Event()
    loop.reports.reporter.put = lambda payload, attachment: went.set()
    record(loop, 0)
    loop.reports.flush(defer_ns=3600 * 10**9)
    assert went.wait(timeout=30), "a report of records alone waited"
