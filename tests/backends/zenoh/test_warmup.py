"""The node loop's warm-up (node/timing.py, WARM_AHEAD_NS): when it plans one, and that it runs.

A real NodeLoop, rebuilt from the IR as a worker does, on a real (unconnected) Zenoh session.
The plan is a function of logical values (now, the next wake, what was sent and received), so
no test here waits on the clock. That warming up leaves traces unchanged is the conformance
suite's business: it runs with warm-ups on.
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass, field

import numpy as np
import pytest

from retriever import Flow, Pipeline, Rate, Trigger, io
from retriever.backends.zenoh.node import WARM_AFTER_IDLE_NS, WARM_AHEAD_NS
from retriever.backends.zenoh.wire import KeySpace, WireEncoder
from retriever.backends.zenoh.worker.build import build_loop

from .payload_flows import Camera, Seen, Viewer, frame
from .specs import run_spec

MS = 1_000_000


@pytest.fixture(scope="module")
def spec():
    with Pipeline("warmup") as pipe:
        cam = Camera(size=4096).named("cam") @ Rate(20)
        cam.then(Viewer().named("viewer") @ Trigger("image"))
    return run_spec(pipe.compile().to_ir().doc, "warmup-test")


def message(k: int) -> bytes:
    return WireEncoder().data((k * 50 * MS, 0), k, (k * 50 * MS + 1, 0), "cam", "image",
                              frame(k, 4096).reshape(-1, 1024))


def watch(session, keys: KeySpace):
    """Every sample on the run's keys, in order, as (key, payload); and an event set once the
    sentinel that ``end(session, keys)`` puts comes back (local delivery keeps the session's order)."""
    seen, done = [], threading.Event()

    def on_sample(sample) -> None:
        seen.append((str(sample.key_expr), sample.payload.to_bytes()))
        if str(sample.key_expr).endswith("/zz/end"):
            done.set()

    return session.declare_subscriber(f"{keys.prefix}/**", on_sample), seen, done


def end(session, keys: KeySpace, done: threading.Event) -> None:
    session.put(f"{keys.prefix}/zz/end", b"")
    assert done.wait(timeout=30), "the session's own sentinel never came back"


def test_a_producer_warms_up_before_its_next_tick_once_it_has_sent(session, spec):
    loop = build_loop(spec, "cam", session)
    tick = 50 * MS
    loop.schedule.next_rate = (tick, 0)
    assert loop.warmup.target(0, tick) == (None, None), "nothing sent yet: nothing to warm"

    loop.outputs.warm_publish = ((0, 0), 0, (1, 0), "cam", "image", frame(0, 4096).reshape(-1, 1024))
    assert loop.warmup.target(0, tick) == (tick, None)
    loop.warmup.warmed_for = tick
    assert loop.warmup.target(0, tick) == (None, None), "once per tick"
    assert loop.warmup.target(tick - WARM_AFTER_IDLE_NS + 1, tick) == (None, None), \
        "a sleep shorter than WARM_AFTER_IDLE_NS leaves the caches warm"


def test_a_producer_warm_up_puts_only_on_its_warm_key(session, spec):
    """It encodes its last event and reads the HLC, and puts one empty message on warm/cam:
    nothing on data/** or progress/**, so no consumer and no watcher of the data sees it."""
    keys = KeySpace(spec.namespace)
    watcher, seen, done = watch(session, keys)
    loop = build_loop(spec, "cam", session)
    loop.declare()
    try:
        loop.outputs.warm_publish = ((0, 0), 0, (1, 0), "cam", "image", frame(0, 4096).reshape(-1, 1024))
        loop.warmup.warm(None)
        assert loop.outputs.warm_publish is not None, "the warm-up failed"
        end(session, keys, done)
        assert seen == [(keys.warm("cam"), b""), (f"{keys.prefix}/zz/end", b"")]
        assert loop.sent == {} and not loop.reports.published, "a warm-up sends no event"
    finally:
        loop.undeclare()
        watcher.undeclare()


def test_a_consumer_foresees_a_periodic_stream_and_rehearses_its_last_message(session, spec):
    loop = build_loop(spec, "viewer", session)
    far = 10_000 * MS  # a Trigger node with nothing pending waits long
    stream = ("cam", "image")
    loop.warmup.arrived(stream, message(1), 50 * MS)
    assert loop.warmup.target(51 * MS, far) == (None, None), "one arrival: no period yet"

    loop.warmup.arrived(stream, message(2), 100 * MS)
    target, data = loop.warmup.target(101 * MS, far)
    assert target == 150 * MS and data == message(2)
    before = (dict(loop.streams.expect), dict(loop.streams.frontiers), dict(loop.notes.counts))
    loop.warmup.warm(data)  # rehearses its arrival on scratch inputs; delivers nothing
    assert not loop.schedule.pending
    assert all(not e.buf.entries for e in loop.streams.edges), "a warm-up must not deliver"
    assert (dict(loop.streams.expect), dict(loop.streams.frontiers), dict(loop.notes.counts)) == before
    rehearsal = loop.warmup.rehearsal
    assert rehearsal.streams.frontiers[stream] == (100 * MS + 1, 0), "the rehearsal took it in order"
    assert not rehearsal.schedule.pending and all(not buf.entries for _, buf, _, _ in rehearsal.inputs), \
        "and forgot it"

    # the foreseen arrival must lie ahead and before the wake it would delay
    assert loop.warmup.target(151 * MS, far) == (None, None)
    assert loop.warmup.target(101 * MS, 120 * MS) == (None, None)
    assert loop.warmup.target(150 * MS - WARM_AHEAD_NS, far) == (None, None)


def test_a_producers_warm_up_makes_its_consumer_rehearse_on_the_thread_that_receives_it(session, spec):
    """The producer's warm-up message (on warm/cam, 1 ms before its tick) reaches its consumer,
    which rehearses the arrival of cam's last message on the thread that got it (its data
    messages' receiving thread: here, the put's, local delivery), while its main thread waits;
    none of the loop's state changes. With its main thread busy (``turn`` held), nothing runs."""
    keys = KeySpace(spec.namespace)
    loop = build_loop(spec, "viewer", session)
    assert loop.inline, "a node on no cycle, without setup(): it may step on the receiving thread"
    loop.declare()
    stream = ("cam", "image")
    try:
        loop.warmup.arrived(stream, message(2), 100 * MS)
        before = (dict(loop.streams.expect), dict(loop.streams.frontiers), dict(loop.notes.counts))
        rehearsed = loop.warmup.rehearsal.streams.frontiers
        session.put(keys.warm("cam"), b"")  # the main thread busy: it holds `turn`; the run not started
        assert rehearsed[stream] == (0, 0), "rehearsed while the main thread held the loop"
        assert loop.warmup.heralds == {}, "heralded before the run's T0, by a time not since T0"
        loop.run_clock.start(time.time_ns() - 200 * MS, 10_000 * MS)
        loop.turn.release()  # the main thread waits
        try:
            session.put(keys.warm("other"), b"")  # no stream of this node's
            assert rehearsed[stream] == (0, 0)
            session.put(keys.warm("cam"), b"not read")
            assert rehearsed[stream] == (100 * MS + 1, 0), "the consumer did not rehearse cam's last message"
        finally:
            loop.turn.acquire()
        assert not loop.schedule.pending and all(not e.buf.entries for e in loop.streams.edges)
        assert (dict(loop.streams.expect), dict(loop.streams.frontiers), dict(loop.notes.counts)) == before
        assert set(loop.warmup.heralds) == {"cam"}, "each of its producers' warm-up messages is noted"
        assert 200 * MS <= loop.warmup.heralds["cam"] < 10_000 * MS, "noted in ns since T0"
    finally:
        loop.undeclare()


def test_a_stream_whose_producer_warms_its_consumer_up_is_not_rehearsed_by_the_main_thread_too(session, spec):
    """Once a stream's last message came after a warm-up message of its producer, the main
    thread foresees no arrival of it (the receiving thread rehearses it then); a message that
    came with none since the one before is foreseen again."""
    loop = build_loop(spec, "viewer", session)
    far, stream = 10_000 * MS, ("cam", "image")
    loop.warmup.arrived(stream, message(1), 50 * MS)
    loop.warmup.herald("cam", 99 * MS)
    loop.warmup.arrived(stream, message(2), 100 * MS)
    assert loop.warmup.target(101 * MS, far) == (None, None), "heralded: left to the receiving thread"
    loop.warmup.herald("other", 149 * MS)  # another producer's: not cam's
    loop.warmup.arrived(stream, message(3), 150 * MS)
    assert loop.warmup.target(151 * MS, far) == (200 * MS, message(3)), "no warm-up message since: foreseen"
    loop.warmup.herald("cam", 199 * MS)
    loop.warmup.arrived(stream, message(4), 200 * MS)
    assert loop.warmup.target(201 * MS, far) == (None, None)


def test_the_nearest_stream_is_warmed_for(session, spec):
    loop = build_loop(spec, "viewer", session)
    slow, fast = ("cam", "image"), ("other", "out")
    for k, t in enumerate((0, 100 * MS, 200 * MS)):
        loop.warmup.arrived(slow, message(k), t)
    loop.warmup.arrived(fast, b"fast-1", 190 * MS)
    loop.warmup.arrived(fast, b"fast-2", 210 * MS)
    assert loop.warmup.target(211 * MS, 10_000 * MS) == (230 * MS, b"fast-2")


def test_a_warm_up_that_fails_is_skipped_not_raised(session, spec):
    """A flow may change a value after emitting it; warming up on it must not stop the run."""
    loop = build_loop(spec, "cam", session)
    loop.outputs.warm_publish = ((0, 0), 0, (1, 0), "cam", "image", [object()])  # not encodable
    loop.warmup.warm(b"not a data message")
    assert loop.outputs.warm_publish is None


@pytest.mark.parametrize("sent", [True, False])
def test_a_source_in_its_quiet_loop_warms_up_before_its_tick_once_it_has_sent(session, spec, sent):
    """node/source.py's PlainSource.run_quiet, driven by hand for one tick 10 ms ahead: a source that has sent
    warms up on warm/cam before it steps (and publishes its frame), as the general loop would;
    one that has not sent goes straight to the step."""
    keys = KeySpace(spec.namespace)
    watcher, seen, done = watch(session, keys)
    loop = build_loop(spec, "cam", session)
    loop.declare()
    try:
        if sent:
            loop.outputs.warm_publish = ((0, 0), 0, (1, 0), "cam", "image", frame(0, 4096).reshape(-1, 1024))
        loop.run_clock.t0 = time.time_ns()
        loop.run_clock.end = 10 * MS + 1  # one tick, at 10 ms: a wait longer than WARM_AFTER_IDLE_NS
        loop.schedule.next_rate = (10 * MS, 0)
        loop.source.run_quiet()
        end(session, keys, done)
        assert [record[3] for record in loop.reports.records] == ["ok"], loop.reports.records  # its status
        published = [key for key, _ in seen if key.startswith((keys.warm("cam"), keys.data("cam", "image")))]
        expected = [keys.warm("cam"), keys.data("cam", "image")] if sent else [keys.data("cam", "image")]
        assert published == expected, seen
        assert loop.warmup.warmed_for == (10 * MS if sent else None)
    finally:
        loop.undeclare()
        watcher.undeclare()


FACTORY_CALLS: list[int] = []


def _counted() -> int:
    """A default factory with a side effect: what a user's may have."""
    FACTORY_CALLS.append(1)
    return 0


@io
@dataclass
class Count:
    n: int


@io
@dataclass
class Looked:
    image: np.ndarray
    k: int
    n: int = field(default_factory=_counted)


class Ticks(Flow[None, Count]):
    def step(self, inp: None) -> Count:
        return Count(n=1)


class Looker(Flow[Looked, Seen]):
    def step(self, inp: Looked) -> Seen:
        return Seen(k=inp.k, checksum=inp.n)


def test_a_rehearsal_runs_no_code_of_the_flow(session):
    """The rehearsal selects the consumer's inputs on scratch buffers, where every port but the
    rehearsed stream's is MISSING: an optional port's default factory (user code) must not run
    for it (the warm-up changes only how fast a tick starts)."""
    with Pipeline("rehearsal") as pipe:
        cam = Camera(size=4096).named("cam") @ Rate(20)
        ticks = Ticks().named("ticks") @ Rate(20)
        looker = Looker().named("looker") @ Trigger("image")
        pipe.connect(cam, looker)
        pipe.connect(ticks, looker)
    loop = build_loop(run_spec(pipe.compile().to_ir().doc, "rehearsal-test"), "looker", session)
    FACTORY_CALLS.clear()
    loop.warmup.warm(message(2))
    assert loop.warmup.rehearsal.streams.frontiers[("cam", "image")] == (100 * MS + 1, 0), "it rehearsed"
    assert FACTORY_CALLS == [], "the rehearsal called the flow's default factory"
