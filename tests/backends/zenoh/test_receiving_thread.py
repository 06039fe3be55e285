"""Steps on the receiving thread (node/loop.py, INLINE_STEP_NS): where a tick runs, and what may not.

A data message that arrives while a node's main thread waits is handled on the Zenoh thread that
received it, and the ticks it makes ready run there too, when the node's last step was short
and the node is on no cycle. The first tests run real pipelines and ask each step where it ran;
the last ones drive a real NodeLoop by hand (as test_warmup does) to show what happens to a step
that raises there and to a message that comes while the main thread is busy: no test here
depends on timing for its verdict.
"""

from __future__ import annotations

import pytest

from retriever import Latest, Pipeline, Rate, Trigger
from retriever.backends.zenoh.node import DATA, INLINE_STEP_NS, NUDGE
from retriever.errors import StopRun
from retriever.backends.zenoh.wire import WireEncoder
from retriever.backends.zenoh.worker.build import build_loop

from .semantics_flows import Counter, Faulty, Ticker, WhereRun
from .specs import run_spec

MS = 1_000_000


def run(pipe: Pipeline, duration: float, **options):
    return pipe.run(duration=duration, backend="zenoh", quiet=True, **options)


def where(trace, node: str) -> list[bool]:
    """Per step of ``node`` in tick order: whether it ran on the main thread."""
    by_id = {e.id: e for e in trace.events}
    return [by_id[s.produced[0]].value["main"] for s in trace.steps_of(node) if s.status == "ok"]


def test_short_steps_of_a_node_on_no_cycle_run_on_the_receiving_thread():
    with Pipeline("inline_chain") as pipe:
        src = Ticker().configure(name="counter") @ Rate(hz=20)
        src.then(WhereRun().configure(name="where") @ Trigger("x"), sync=Latest())
    trace = run(pipe, 1.0)
    ran = where(trace, "where")
    assert len(ran) >= 15, trace.steps_of("where")
    assert ran[0] is True, "the first step, of unknown length, runs on the main thread"
    # later steps run on the receiving thread when the main thread is waiting, which it does for
    # almost all of the 50 ms between messages
    assert ran.count(False) >= 1, ran
    xs = [e.value["x"] for e in trace.events_of("where")]
    assert xs == list(range(len(xs))), "every input, once, in order"


def test_steps_off_the_main_thread_run_on_zenohs_receiving_thread_which_keeps_its_python_state():
    # Zenoh's own thread (indirect=False), not a Python thread zenoh-python starts and wakes for
    # each sample; and that thread's Python state is kept from one message to the next (node/
    # transport.py, _keep_thread_state): a flow's threading.local holds there as on a Python thread
    # on Zenoh (same_host_links=False; over a same-host link it is the link's thread: below)
    with Pipeline("inline_rx") as pipe:
        src = Ticker().configure(name="counter") @ Rate(hz=20)
        src.then(WhereRun().configure(name="where") @ Trigger("x"), sync=Latest())
    trace = run(pipe, 1.0, same_host_links=False)
    off = [e.value for e in trace.events_of("where") if not e.value["main"]]
    assert len(off) >= 2, [e.value for e in trace.events_of("where")]
    assert {v["thread"].split("-")[0] for v in off} == {"rx"}, off
    for tid in {v["tid"] for v in off}:
        befores = [v["before"] for v in off if v["tid"] == tid]
        assert befores == list(range(len(befores))), (tid, befores)


def test_over_a_same_host_link_steps_off_the_main_thread_run_on_the_links_receiving_thread():
    """Its LinkClient's thread (node/linked.py), as a Zenoh callback's: the message handled
    where it was received, no hand-off to the main thread."""
    with Pipeline("inline_link") as pipe:
        src = Ticker().configure(name="counter") @ Rate(hz=20)
        src.then(WhereRun().configure(name="where") @ Trigger("x"), sync=Latest())
    trace = run(pipe, 1.0)
    off = [e.value for e in trace.events_of("where") if not e.value["main"]]
    assert len(off) >= 2, [e.value for e in trace.events_of("where")]
    # one thread, a Python one (its native name is the interpreter's), not Zenoh's "rx-…"
    assert len({v["tid"] for v in off}) == 1 and {v["thread"] for v in off} == {"python"}, off
    assert [v["before"] for v in off] == list(range(len(off))), off


def test_a_node_on_a_cycle_runs_every_step_on_its_main_thread():
    with Pipeline("inline_cycle") as pipe:
        count = Counter().configure(name="count") @ Rate(hz=20)
        echo = WhereRun().configure(name="where") @ Trigger("x")
        count.then(echo, sync=Latest(), map={"value": "x"})
        echo.then(count, sync=Latest(), map={"report": "x"})
    trace = run(pipe, 1.0)
    ran = where(trace, "where")
    assert len(ran) >= 15 and all(ran), ran


def test_a_node_whose_last_step_took_long_runs_the_next_on_its_main_thread():
    with Pipeline("inline_slow") as pipe:
        src = Ticker().configure(name="counter") @ Rate(hz=20)
        slow = WhereRun(sleep=2 * INLINE_STEP_NS / 1e9).configure(name="where") @ Trigger("x")
        src.then(slow, sync=Latest())
    trace = run(pipe, 1.0)
    ran = where(trace, "where")
    assert len(ran) >= 15 and all(ran), ran


# ---------------------------------------------------------------------------------------------
# A NodeLoop driven by hand: the test thread plays the receiving thread
# ---------------------------------------------------------------------------------------------
def faulty_loop(session):
    with Pipeline("inline_by_hand") as pipe:
        src = Ticker().configure(name="counter") @ Rate(hz=20)
        src.then(Faulty(fail_at=[1], message="inline-boom").configure(name="faulty") @ Trigger("x"),
                 sync=Latest())
    loop = build_loop(run_spec(pipe.compile().to_ir().doc, "inline-test"), "faulty", session)
    assert loop.inline, "faulty is on no cycle"
    loop.declare()
    loop.run_clock.t0, loop.run_clock.end, loop.run_clock.started = 0, 1 << 62, True  # as run() sets them
    loop.last_wall = 0  # as after a short step
    return loop


def data(k: int) -> tuple:
    message = WireEncoder().data((k * 50 * MS, 0), k, (k * 50 * MS + 1, 0), "counter", "value", k)
    return (DATA, ("counter", "value"), message)


def test_a_message_that_comes_while_the_main_thread_waits_is_stepped_on_arrival(session):
    loop = faulty_loop(session)
    try:
        loop.turn.release()  # the main thread waits in _wait
        loop.receive(data(0))
        assert [r[3] for r in loop.reports.records] == ["ok"], "the tick ran on the receiving thread"
        assert loop.sent == {"report": 0}, "and published"
        assert loop.inbox.get_nowait()[0] == NUDGE, "the main thread is told to look again"
        assert loop.turn.acquire(blocking=False), "the receiving thread gave the loop back"
    finally:
        loop.undeclare()


def test_a_grouped_loop_hears_its_data_only_to_queue_it_off_zenohs_thread(session):
    # a group's loops never lend their turn to a receiving thread (GroupLoop waits for them): their
    # data subscribers only queue, on zenoh-python's thread, never taking the GIL on Zenoh's own
    loop = faulty_loop(session)
    try:
        assert loop.transport.inputs[2] == loop.receive, "a lone loop may step on Zenoh's thread"
    finally:
        loop.undeclare()
    with Pipeline("inline_grouped") as pipe:
        src = Ticker().configure(name="counter") @ Rate(hz=20)
        src.then(Faulty(fail_at=[]).configure(name="faulty") @ Trigger("x"), sync=Latest())
    grouped = build_loop(run_spec(pipe.compile().to_ir().doc, "inline-test"), "faulty", session)
    grouped.grouped = True  # as GroupLoop sets it, before the loop declares anything
    grouped.declare()
    try:
        assert grouped.inline and grouped.transport.inputs[2] is None
    finally:
        grouped.undeclare()


def test_a_message_that_comes_while_the_main_thread_works_is_queued_for_it(session):
    loop = faulty_loop(session)
    try:
        # the main thread holds the loop (it is not waiting)
        loop.receive(data(0))
        assert not loop.reports.records and not loop.schedule.pending and not loop.sent
        assert loop.inbox.get_nowait() == data(0)
    finally:
        loop.undeclare()


def test_a_step_that_raises_on_the_receiving_thread_stops_the_run_from_the_main_thread(session):
    loop = faulty_loop(session)
    try:
        loop.turn.release()
        loop.receive(data(0))
        loop.receive(data(1))  # Faulty raises at x=1; on_error="stop"
        assert isinstance(loop.failure, StopRun) and "inline-boom at x=1" in str(loop.failure)
        assert [r[3] for r in loop.reports.records] == ["ok", "error"], "the failed tick is recorded"
        loop.receive(data(2))  # after a failure, messages only queue: nothing more runs
        assert len(loop.reports.records) == 2
        # the main thread, back from its wait, raises it (the worker then reports the failure)
        assert loop.turn.acquire(blocking=False), "the receiving thread gave the loop back"
        with pytest.raises(StopRun, match="inline-boom at x=1") as info:
            loop.wait(10 * MS)
        assert isinstance(info.value.__cause__, ValueError)
    finally:
        loop.undeclare()
