"""The end of a real-time run at a triggered consumer (node/waiting.py, done_waiting): how long it
waits for a producer whose frontier is short of the end. A real NodeLoop driven by hand (the test
thread plays the transport's receiving thread and the coordinator); no test here waits on time.

A stall of the machine (dora's daemon, or the consumer's own process, stopped past the end and
the edge's deadline) used to make the consumer give the edge up at end + deadline, and drop
without a word the events its producer had made before the end: a camera's 10 events in the
trace, its policy's 0 steps.
"""

from __future__ import annotations

import pytest

from retriever import Latest, Pipeline, Rate, Trigger
from retriever.backends.zenoh.node import CONTROL, DATA, NEVER
from retriever.backends.zenoh.node.schedule import DONE
from retriever.backends.zenoh.node.waiting import FINISHED_ASK_NS, LAST_WORD_MAX_NS
from retriever.backends.zenoh.protocol import Finished
from retriever.backends.zenoh.wire import WireEncoder
from retriever.backends.zenoh.worker.build import build_loop

from .semantics_flows import Ticker, WhereRun
from .specs import run_spec

MS = 1_000_000
STREAM = ("counter", "value")
END = 1000 * MS


@pytest.fixture
def loop(session):
    """The loop of ``where`` (Trigger on x, the Latest of counter's values; its edge's deadline the
    default 0.1 s) in a run of 1 s, as run() leaves it."""
    with Pipeline("end_by_hand") as pipe:
        src = Ticker().configure(name="counter") @ Rate(hz=10)
        src.then(WhereRun().configure(name="where") @ Trigger("x"), sync=Latest(), map={"value": "x"})
    loop = build_loop(run_spec(pipe.compile().to_ir().doc, "end-test"), "where", session)
    loop.declare()
    loop.run_clock.t0, loop.run_clock.end, loop.run_clock.started = 0, END, True  # as run() sets them
    yield loop
    loop.undeclare()


def data(seq: int, last: bool = False) -> tuple:
    """counter's event ``seq``, made at its tick seq * 100 ms (the last one promises no more)."""
    tag = (seq * 100 * MS, 0)
    frontier = NEVER if last else ((seq + 1) * 100 * MS, 0)
    return (DATA, STREAM, WireEncoder().data(tag, seq, frontier, "counter", "value", seq))


def done(*nodes: str) -> tuple:
    """The coordinator's answer to the loop's question: these nodes are done."""
    return (CONTROL, None, Finished(nodes=nodes, complete=(), restarting=(), handed_over=()))


def ticks(loop) -> int:
    """Run every tick that is ready; how many ran in all."""
    while loop.try_tick(1 << 61) == "ticked":
        pass
    return len(loop.reports.records)


def past_deadline(loop) -> int:
    return END + loop.streams.edges[0].deadline_ns + 1


def test_a_done_producers_events_that_come_past_the_deadline_are_waited_for_and_ticked_on(loop):
    """The consumer stalled (or the transport did) through the run: seq 0 came, and then, past
    the end and the edge's deadline, nothing. The coordinator says the producer is done: its
    last messages are on their way, and each of its events still triggers its tick."""
    loop.handle(data(0))
    assert ticks(loop) == 1
    now = past_deadline(loop)
    assert loop.waiting.done_waiting(now) != DONE, "it asks the coordinator first"
    loop.handle(done("counter"))
    assert loop.waiting.done_waiting(now) != DONE, "the producer's last word has not come"
    for seq in range(1, 10):
        loop.handle(data(seq, last=seq == 9))
    assert ticks(loop) == 10
    assert loop.waiting.done_waiting(now) == DONE
    assert "unfinished_inputs" not in loop.counts and loop.counts["garbage"] == 0


def test_a_producer_not_done_is_given_up_past_the_deadline_once_the_coordinator_says_so(loop):
    """A producer whose step outlasts the end is waited for no longer than the edge's deadline."""
    loop.handle(data(0))
    now = past_deadline(loop)
    assert loop.waiting.done_waiting(now) != DONE
    loop.handle(done("where"))
    assert loop.waiting.done_waiting(now) == DONE
    assert "unfinished_inputs" not in loop.counts


def test_without_the_coordinators_answer_the_edge_is_given_up_after_the_question_timed_out(loop):
    now = past_deadline(loop)
    assert loop.waiting.done_waiting(now) != DONE
    assert loop.waiting.done_waiting(now + FINISHED_ASK_NS) == DONE


def test_a_done_producers_last_word_that_never_comes_is_given_up_and_counted(loop):
    loop.handle(data(0))
    now = past_deadline(loop)
    loop.waiting.done_waiting(now)
    loop.handle(done("counter"))
    assert loop.waiting.done_waiting(now + LAST_WORD_MAX_NS - 2) != DONE
    assert loop.waiting.done_waiting(now + LAST_WORD_MAX_NS) == DONE
    assert loop.waiting.done_waiting(now + LAST_WORD_MAX_NS) == DONE
    assert loop.counts["unfinished_inputs"] == 1, "once per stream"


def test_before_the_deadline_nothing_is_asked_of_the_coordinator(loop):
    loop.handle(data(0))
    assert loop.waiting.done_waiting(END + 1) != DONE
    assert loop.waiting.finished_asked is None
