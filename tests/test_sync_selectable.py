"""``SyncPolicy.selectable``: what a restarted consumer's new process takes over of an input
buffer (zenoh/node/handover.py). Only what a later tick can still select goes, so a buffer that
bursts filled while the flow restarted stays small; and the new process must select from it
exactly what one process would have selected from the whole buffer.

The property drives each policy twice through the same random history (bursts of events at one
tag, several producers, ticks, skipped ticks, events that arrive after a tick at or past their
tag ran, as in real time): once on one buffer, once handing the buffer over (``selectable``)
before random ticks. Every tick's ``(value, ids, dropped)`` must agree. Examples then pin how
much each policy keeps of a buffer of bursts.
"""

from __future__ import annotations

import random

from hypothesis import given
from hypothesis import strategies as st

from retriever import Exact, Latest, LatestDistinct, Queue, Window
from retriever.plan import UNFED
from retriever.sync import PortBuffer

from .test_sync import MS, SETTINGS, RefEvent, Scenario, buffer_entry

#: each policy a restarted consumer may have on an input, its durations in ms
POLICIES = {
    "Latest()": lambda: Latest(),
    "Latest(staleness=3 ms)": lambda: Latest(staleness=0.003),
    "LatestDistinct()": lambda: LatestDistinct(),
    "Window(3)": lambda: Window(buffer_size=3),
    "Window(duration=4 ms)": lambda: Window(duration=0.004),
    "Window(2, duration=4 ms)": lambda: Window(buffer_size=2, duration=0.004),
    "Window()": lambda: Window(),
    "Queue()": lambda: Queue(),
    "Queue(2)": lambda: Queue(maxsize=2),
    "Exact()": lambda: Exact(),
    "Exact(tolerance=2 ms)": lambda: Exact(tolerance=0.002),
}


@st.composite
def restart_scenarios(draw) -> tuple[Scenario, set[int]]:
    """A history of bursts (1 to 6 events of one producer at one tag) from 1 to 3 producers, the
    consumer's ticks, which of them skip, and before which ticks its buffer is handed over. An
    event enters the buffer before the first tick that can see it, or, one time in four, later
    (late); each producer's in seq order."""
    rnd = random.Random(draw(st.integers(0, 2**32)))  # an int seed shrinks fast; a Random does not
    horizon = 30
    ticks = sorted({(rnd.randint(0, horizon + 5) * MS, rnd.randint(0, 3)) for _ in range(rnd.randint(1, 25))})
    events, inserts = [], [[] for _ in ticks]
    for producer in rnd.choice([("a",), ("b", "a"), ("c", "a", "b")]):
        mine = []
        for tag in sorted({(rnd.randint(0, horizon) * MS, rnd.randint(0, 2)) for _ in range(rnd.randint(0, 12))}):
            size = rnd.choice([1, 1, 2, 3, 6])
            mine += [RefEvent(tag, producer, len(mine) + i, rnd.randint(-5, 5)) for i in range(size)]
        moments = []
        for e in mine:
            first_seen = next((i for i, tau in enumerate(ticks) if tau >= e.tag), len(ticks) - 1)
            late = rnd.random() < 0.25
            moments.append(rnd.randint(first_seen, len(ticks) - 1) if late else rnd.randint(0, first_seen))
        for e, moment in zip(mine, sorted(moments)):  # a stream is taken in seq order
            inserts[moment].append(e)
        events += mine
    skipped = [rnd.random() < 0.3 for _ in ticks]
    handovers = {i for i in range(len(ticks)) if rnd.random() < 0.3}
    return Scenario(MS, events, ticks, skipped, inserts, trim_batch=rnd.choice([1, 2, 64])), handovers


def drive(policy, sc: Scenario, handovers: set[int]) -> list[tuple]:
    """Each tick's ``(value, ids, dropped)``, the buffer handed over before the ticks in ``handovers``."""
    buf, after, got = PortBuffer(trim_batch=sc.trim_batch), (-1, 0), []
    for i, tau in enumerate(sc.ticks):
        if i in handovers:
            buf = policy.selectable(buf, after)
        for e in sc.inserts[i]:
            buf.insert(buffer_entry(e.tag, e.node, e.seq, e.value))
        value, ids, dropped, commit = policy.select(buf, tau)
        got.append((value, ids, dropped))
        if not sc.skipped[i]:
            policy.commit_to(buf, commit)
        after = tau
    return got


@SETTINGS
@given(scenario=restart_scenarios(), name=st.sampled_from(sorted(POLICIES)))
def test_a_buffer_handed_over_selects_what_the_whole_buffer_selects(scenario, name):
    sc, handovers = scenario
    policy = POLICIES[name]()
    assert drive(policy, sc, handovers) == drive(policy, sc, set())


# ---------------------------------------------------------------------------------------------
# How much each policy keeps of a buffer of bursts
# ---------------------------------------------------------------------------------------------
def _bursts(count: int, size: int) -> PortBuffer:
    """A real-time buffer after the tick at 1 ms: ``count`` bursts of ``size`` events, at 1, 2, …
    ms (the first one consumed by a Queue), as a restarting consumer's fills up."""
    buf = PortBuffer(trim_batch=1)
    for k in range(count):
        for i in range(size):
            buf.insert((((k + 1) * MS, 0), "src", "out", k * size + i, k * size + i))
    buf.visible = buf.cursor = size
    return buf


AFTER = (1 * MS, 0)


def _kept(buf: PortBuffer) -> list[int]:
    return [e[3] for e in buf.entries]


def test_latest_keeps_the_last_event_of_each_burst():
    for policy in (Latest(), LatestDistinct()):
        kept = policy.selectable(_bursts(5, 1000), AFTER)
        assert _kept(kept) == [999, 1999, 2999, 3999, 4999] and kept.visible == 1


def test_a_window_keeps_the_last_n_of_each_burst_and_what_its_duration_still_reaches():
    kept = Window(buffer_size=3).selectable(_bursts(3, 1000), AFTER)
    assert _kept(kept) == [997, 998, 999, 1997, 1998, 1999, 2997, 2998, 2999] and kept.visible == 3
    assert len(Window(duration=0.001).selectable(_bursts(3, 1000), (2 * MS, 0)).entries) == 3000
    assert len(Window(duration=0.001).selectable(_bursts(3, 1000), (3 * MS, 0)).entries) == 2000
    assert len(Window().selectable(_bursts(3, 1000), AFTER).entries) == 3000


def test_exact_keeps_the_first_event_of_each_burst():
    kept = Exact().selectable(_bursts(3, 1000), AFTER)
    assert _kept(kept) == [0, 1000, 2000] and kept.visible == 1


def test_a_queue_keeps_every_event():
    """Those it has not consumed, those it would drop past ``maxsize`` (they count as dropped), and
    those it consumed: a late event sorts behind them or not (PortBuffer.insert). (A real-time
    buffer forgets those at once: trim_batch=1.)"""
    kept = Queue(maxsize=10).selectable(_bursts(3, 1000), AFTER)
    assert _kept(kept) == list(range(3000)) and kept.cursor == kept.visible == 1000


def test_an_input_nothing_feeds_keeps_nothing():
    assert UNFED.selectable(_bursts(1, 10), AFTER).entries == []
