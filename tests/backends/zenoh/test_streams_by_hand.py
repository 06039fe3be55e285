"""A consumer's input streams, driven by hand (see test_restart_afresh.py): bursts, and progress
messages far ahead of the data they come after. No test here waits on time."""

from __future__ import annotations

from retriever import Burst
from retriever.codec import packb
from retriever.backends.zenoh.node import DATA, EARLY_SEQS_MAX, PROGRESS, WAITING_MAX
from retriever.backends.zenoh.node import handover
from retriever.backends.zenoh.wire import WireEncoder

from . import test_restart_afresh as by_hand
from .test_restart_afresh import MS, STREAM, consumed, data, tick_all

loop = by_hand.loop  # its fixture: a NodeLoop of a Queue consumer of counter.value (session: conftest.py)


def burst(first: int, n: int, t_ms: int) -> tuple:
    message = WireEncoder().data((t_ms * MS, 0), first, (t_ms * MS + 1, 0), "counter", "value",
                                 Burst(range(first, first + n)))
    return (DATA, STREAM, message)


def progress(after_seq: int, t_ms: int) -> tuple:
    return (PROGRESS, "counter", WireEncoder().progress((t_ms * MS, 0), "counter", {"value": after_seq}))


def test_a_burst_is_taken_in_seq_order_and_makes_one_tick(loop):
    loop.handle(burst(0, 3, 50))
    loop.handle(burst(5, 2, 100))  # overtook the one before it: waits for seqs 3 and 4
    assert loop.streams.expect[STREAM] == 3 and sorted(loop.streams.early[STREAM]) == [5, 6]
    loop.handle(burst(3, 2, 80))
    tick_all(loop)
    assert [consumed(r) for r in loop.reports.records] == [[0, 1, 2], [3, 4], [5, 6]]
    assert loop.counts["garbage"] == 0 and loop.streams.frontiers[STREAM] == (100 * MS + 1, 0)


def test_a_burst_longer_than_a_seq_may_run_ahead_is_taken_but_one_from_the_future_is_not(loop):
    loop.handle(burst(0, 2 * EARLY_SEQS_MAX, 50))
    assert loop.streams.expect[STREAM] == 2 * EARLY_SEQS_MAX and loop.counts["garbage"] == 0
    loop.handle(burst(3 * EARLY_SEQS_MAX + 1, 2, 60))  # its first seq: EARLY_SEQS_MAX + 1 past the next
    assert loop.counts["garbage"] == 1 and not loop.streams.early[STREAM]


def test_a_progress_message_far_ahead_of_its_data_waits_for_them(loop):
    """A consumer behind a producer of bursts may learn of seqs millions ahead from a progress
    message (another key): not garbage, its frontier holds once the data before it came."""
    far = 10 * EARLY_SEQS_MAX
    loop.handle(progress(far, 500))
    assert loop.counts["garbage"] == 0 and loop.streams.frontiers[STREAM] < (500 * MS, 0)
    loop.handle(burst(0, far, 50))  # the data before it: seqs 0 .. far - 1
    assert loop.streams.frontiers[STREAM] == (50 * MS + 1, 0)
    loop.handle(data(far, 60))
    assert loop.streams.frontiers[STREAM] == (500 * MS, 0) and not loop.streams.waiting[STREAM]


def test_progress_messages_waiting_are_bounded_and_the_last_promise_still_holds(loop):
    for k in range(3 * WAITING_MAX):
        loop.handle(progress(10 + k, 100 + k))
        assert loop.streams.waiting[STREAM][-1] == (10 + k, ((100 + k) * MS, 0))  # the newest stays
    assert len(loop.streams.waiting[STREAM]) <= WAITING_MAX
    loop.handle(burst(0, 10 + 3 * WAITING_MAX, 50))
    assert loop.streams.frontiers[STREAM] == ((100 + 3 * WAITING_MAX - 1) * MS, 0) and not loop.streams.waiting[STREAM]
    assert loop.counts["garbage"] == 0


def test_held_let_outputs_with_a_burst_are_handed_over(loop):
    """A restarting flow hands its state to its new process through the codec: held LET outputs
    may hold a burst (which is no value the codec encodes)."""
    loop.outputs.held = [((5 * MS, 0), "saw", Burst(["a", "b"]), 3), ((6 * MS, 0), "saw", "c", 5)]
    state = handover.decode_state(packb(loop.handover_state()), loop)
    loop.outputs.held = []
    handover.take_over(loop, state)
    burst, single = loop.outputs.held
    assert burst[:2] == ((5 * MS, 0), "saw") and type(burst[2]) is Burst and burst[2].values == ("a", "b")
    assert burst[3] == 3 and single == ((6 * MS, 0), "saw", "c", 5)
