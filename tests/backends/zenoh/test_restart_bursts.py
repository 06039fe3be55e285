"""A consumer of big bursts restarted (on_error="restart"; node/handover.py). While its new
process starts, the old one keeps receiving: bursts of 60,000 events at 4 Hz piled up hundreds
of thousands of events in its input buffer, all of which it handed over, each written and read
back one by one, for longer than the run waited (issue 42). Now it hands over only what the
input's policy can still select (SyncPolicy.selectable), a burst as a whole, and says so when
that is still more than a new process takes over in time (a Queue far behind).

First piece by piece: real NodeLoops driven by hand with the wire's bursts (as
test_restart_afresh.py does), the hand-over through the state file, and what the new loop
consumes, which must be what one loop that never restarted consumes. No test there waits on
time. Then real runs, with real processes: one whose log replays, one whose Queue is too far
behind.
"""

from __future__ import annotations

import pytest

from retriever import BackendError, Burst, Latest, Pipeline, Queue, Rate, Trigger, Window, read_log
from retriever.backends.zenoh.node import DATA, handover
from retriever.backends.zenoh.node.handover import HANDOVER_EVENTS_MAX
from retriever.backends.zenoh.wire import WireEncoder
from retriever.backends.zenoh.worker.build import build_loop
from retriever.codec import packb
from retriever.errors import StopRun
from retriever.flow.burst import MAX_BURST
from retriever.replay import replay
from retriever.trace import StepStatus

from .burst_flows import Bursts, FailAt
from .specs import run_spec
from .test_restart_afresh import consumed, tick_all

MS = 1_000_000
SIZE = 60_000  # events a burst: as issue 42 found them
PERIOD_MS = 250  # 4 Hz
STREAM = ("bursts", "value")


def consumer_loop(session, sync, fail_at: int):
    """The loop of ``consumer`` (untyped, Trigger on x: one tick a burst), fed ``bursts`` with
    ``sync``, as run() leaves it; it raises on its tick that gets ``fail_at`` (-1: never)."""
    with Pipeline("restart_bursts_by_hand") as pipe:
        src = Bursts(SIZE).configure(name="bursts") @ Rate(hz=1000 / PERIOD_MS)
        src.then(FailAt(fail_at).configure(name="consumer", on_error="restart") @ Trigger("x"), sync=sync,
                 map={"value": "x"})
    loop = build_loop(run_spec(pipe.compile().to_ir().doc, "restart-bursts-test"), "consumer", session)
    loop.run_clock.t0, loop.run_clock.end, loop.run_clock.started = 0, 1 << 62, True  # as run() sets them
    return loop


def burst(k: int) -> tuple:
    """The k-th burst's message, as the consumer's subscriber queues it: SIZE events at k periods."""
    tag = (k * PERIOD_MS * MS, 0)
    message = WireEncoder().data(tag, k * SIZE, (tag[0] + 1, 0), *STREAM, Burst(range(k * SIZE, (k + 1) * SIZE)))
    return (DATA, STREAM, message)


def restarted(session, sync, tmp_path, bursts: int) -> tuple:
    """A consumer whose step raises on the first burst, then takes ``bursts - 1`` more while its
    new process starts, hands over to that one through the state file; the new loop runs the
    ticks due. Returns (the old loop, the new one, the state as read)."""
    old = consumer_loop(session, sync, fail_at=SIZE - 1)
    old.handle(burst(0))
    tick_all(old)
    assert old.restarting and old.counts["garbage"] == 0
    for k in range(1, bursts):
        old.handle(burst(k))
    path = tmp_path / "consumer.handover"
    path.write_bytes(packb(old.handover_state()))
    new = consumer_loop(session, sync, fail_at=SIZE - 1)
    state = handover.read_state(path, new)
    handover.take_over(new, state)
    tick_all(new)
    return old, new, state


@pytest.mark.parametrize("sync, kept", [
    (Latest(), lambda k: [(k + 1) * SIZE - 1]),  # the newest event of each burst
    (Window(buffer_size=3), lambda k: list(range((k + 1) * SIZE - 3, (k + 1) * SIZE))),
], ids=["Latest", "Window(3)"])
def test_a_restart_hands_over_only_what_the_policy_can_still_select(session, tmp_path, sync, kept):
    """Ten bursts of 60,000 events, the first one's tick run (and failed): the state holds what
    a later tick may still select of each burst (of the first too: a tick of another clock or
    input could come before the second burst's tag); the new loop consumes what one loop would
    have, which is that too (a tick a burst)."""
    bursts = 10
    old, new, state = restarted(session, sync, tmp_path, bursts)
    ((port, entries, *_),) = state.buffers
    held = [e[3] for e in entries]
    assert len(held) <= bursts * 3, (
        f"the hand-over holds {len(held):,} events of {port}, where its next ticks may select {bursts * 3} at most")
    assert held == [seq for k in range(bursts) for seq in kept(k)]
    ticks = [consumed(r) for r in old.reports.records + new.reports.records]
    assert ticks == [kept(k) for k in range(bursts)]
    assert [r[3] for r in old.reports.records] == [StepStatus.ERROR]
    assert {r[3] for r in new.reports.records} == {StepStatus.OK}
    assert new.counts["garbage"] == 0


def test_a_queue_hands_over_every_event_it_has_not_consumed(session, tmp_path):
    """Each burst its tick's, whole; written and read back a burst at a time."""
    bursts = 4
    old, new, state = restarted(session, Queue(), tmp_path, bursts)
    ((_, entries, *_),) = state.buffers
    assert [e[3] for e in entries] == list(range(SIZE, bursts * SIZE))
    ticks = [consumed(r) for r in old.reports.records + new.reports.records]
    assert ticks == [list(range(k * SIZE, (k + 1) * SIZE)) for k in range(bursts)]


def test_a_queue_too_far_behind_is_not_handed_over_and_says_why(session):
    """More events its next ticks may still take than a new process takes over in time: the
    state is not written; the run stops with what to do (worker/ending.py says it ``failed``)."""
    old = consumer_loop(session, Queue(), fail_at=SIZE - 1)
    old.handle(burst(0))
    tick_all(old)
    behind = HANDOVER_EVENTS_MAX // SIZE + 1
    for k in range(1, behind + 1):
        old.handle(burst(k))
    with pytest.raises(StopRun, match=(
            rf"^flow 'consumer' cannot restart after its step failed at t=0\.000000000s m=0: its new process would "
            rf"take over {behind * SIZE:,} events of consumer.x \(Queue\(\)\) that its next ticks may still "
            rf"select, more than it can in time \(HANDOVER_EVENTS_MAX = {HANDOVER_EVENTS_MAX:,}\)\n"
            r"    hint: on consumer.x, Latest\(\) or Window\(n\) hand over only the events they may still select; "
            r"or on_error='skip_tick' goes on in the same process$")) as info:
        old.handover_state()
    assert info.value.tag == (0, 0)


def test_more_pending_ticks_than_a_new_process_takes_are_not_handed_over(session):
    """As many trigger ticks pending as the reader of the state takes at most (protocol/handover.py)
    and one more: the state is not written, the run stops saying why."""
    old = consumer_loop(session, Latest(), fail_at=SIZE - 1)
    old.handle(burst(0))
    tick_all(old)
    old.schedule.pending = [(t, 0) for t in range(1, HANDOVER_EVENTS_MAX + 2)]
    with pytest.raises(StopRun, match=(
            rf"^flow 'consumer' cannot restart after its step failed: it has {HANDOVER_EVENTS_MAX + 1:,} trigger "
            rf"ticks pending, more than a new process takes over \(HANDOVER_EVENTS_MAX = {HANDOVER_EVENTS_MAX:,}\)\n"
            r"    hint: on_error='skip_tick' goes on in the same process$")):
        old.handover_state()


# ---------------------------------------------------------------------------------------------
# Real runs
# ---------------------------------------------------------------------------------------------
def test_consumers_of_big_bursts_restart_and_the_log_replays(tmp_path):
    """Bursts of 20,000 events at 4 Hz into two untyped consumers, a Latest's and a Queue's,
    each raising once: each restarts in a new process, which runs a tick for every burst that
    came meanwhile with what one process would have given it; the log replays bit for bit."""
    size = 20_000
    with Pipeline("restart_bursts") as pipe:
        src = Bursts(size).configure(name="bursts") @ Rate(hz=4)
        for name, sync in (("newest", Latest()), ("every", Queue())):
            consumer = FailAt(2 * size - 1).configure(name=name, on_error="restart") @ Trigger("x")
            src.then(consumer, sync=sync, map={"value": "x"})
    path = tmp_path / "run.mcap"
    try:
        trace = pipe.run(duration=3.0, backend="zenoh", quiet=True, log=path)
    except BackendError as e:
        pytest.fail(f"the run did not end: {str(e)[:600]}")
    ticks = 12  # 3 s at 4 Hz: a tick a burst
    assert pipe.counts()["restarts"] == 2 and pipe.counts().get("garbage", 0) == 0
    for name, taken in (("newest", lambda k: [(k + 1) * size - 1]),
                        ("every", lambda k: list(range(k * size, (k + 1) * size)))):
        recs = trace.steps_of(name)
        assert [[eid[2] for eid in r.consumed["x"]] for r in recs] == [taken(k) for k in range(ticks)], name
        assert [r.status for r in recs] == [StepStatus.OK, StepStatus.ERROR] + [StepStatus.OK] * (ticks - 2), name
    report = replay(read_log(path))
    assert report.identical, report.divergences[:3]


def test_a_run_whose_queue_is_too_far_behind_to_restart_stops_saying_so():
    """Twenty bursts of 65,536 events within a second, through an edge with a 2 s delay: they wait
    in the consumer's buffer for their (delayed) tags, the first of which makes the tick that
    fails. The rest, unconsumed, are more than a new process takes over in time: the run stops,
    the error naming the flow, its input, the count and what to do."""
    with Pipeline("restart_too_far_behind") as pipe:
        src = Bursts(MAX_BURST, count=20).configure(name="bursts") @ Rate(hz=20)
        consumer = FailAt(MAX_BURST - 1).configure(name="consumer", on_error="restart") @ Trigger("x")
        pipe.connect(src, consumer, sync=Queue(), map={"value": "x"}, delay=2.0)
    with pytest.raises(BackendError, match=(
            r"^zenoh run stopped: flow 'consumer' cannot restart after its step failed at t=2\.\d+s m=0: its new "
            r"process would take over [\d,]+ events of consumer.x \(Queue\(\)\) that its next ticks may still "
            rf"select, more than it can in time \(HANDOVER_EVENTS_MAX = {HANDOVER_EVENTS_MAX:,}\)\n    hint: on "
            r"consumer.x, Latest\(\) or Window\(n\) hand over only the events they may still select; or "
            r"on_error='skip_tick' goes on in the same process$")):
        pipe.run(duration=2.5, backend="zenoh", quiet=True, keep="counters")
