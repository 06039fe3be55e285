"""``sync.fill``/``sync.bound``: a buffer forgets, as events come, what its consumer's policy can
no longer select, so a flow that rarely ticks holds what it may still take, not every event since
its last tick (benchmarks/reports/replay.md, "One hour of Retriever-0").

The property drives each policy twice through the same random history as test_sync_selectable's
(bursts, several producers, ticks, skipped ticks, late events): once on a plain buffer, once
bounding the buffer at random moments between ticks, by a random tag between the last tick and
the one before the next. Every tick's ``(value, ids, dropped)`` must agree.
"""

from __future__ import annotations

import random

from hypothesis import given
from hypothesis import strategies as st

from retriever import ActionChunking, Latest
from retriever.sync import PortBuffer, before, bound, fill


from .test_sync import MS, SETTINGS, Scenario, buffer_entry
from .test_sync_selectable import POLICIES, restart_scenarios

CHUNKING = {
    "ActionChunking(1000 Hz)": lambda: ActionChunking(control_hz=1000),
    "ActionChunking(500 Hz, 2 steps, missing)": lambda: ActionChunking(control_hz=500, chunk_steps=2,
                                                                        on_exhausted="missing"),
    "ActionChunking(1000 Hz, horizon 2 ms)": lambda: ActionChunking(control_hz=1000, horizon_ms=2.0),
}
EVERY = {**POLICIES, **CHUNKING}


def _value(name: str, e) -> object:
    """The event's value; for ActionChunking a chunk of three rows, starting a little before, at
    or after its tag, or (no ``t0``) at it."""
    if name not in CHUNKING:
        return e.value
    rows = [e.value, e.value + 1, e.value + 2]
    shift = e.value % 4
    return rows if shift == 3 else {"actions": rows, "t0": e.tag[0] + (shift - 1) * MS}


def drive(name: str, sc: Scenario, seed: int | None) -> list[tuple]:
    """Each tick's ``(value, ids, dropped)``; with a ``seed``, the buffer bounded at random moments."""
    policy = EVERY[name]()
    rnd = random.Random(seed)
    buf, last, got = PortBuffer(trim_batch=sc.trim_batch, policy=policy), (-1, 0), []
    for i, tau in enumerate(sc.ticks):
        for e in sc.inserts[i]:
            buf.insert(buffer_entry(e.tag, e.node, e.seq, _value(name, e)))
            if seed is not None and rnd.random() < 0.5:
                # every tick to come is past the last one, and at or after the next one
                after = rnd.choice([last, max(last, before(tau))])
                bound(buf, after)
        value, ids, dropped, commit = policy.select(buf, tau)
        got.append((value, ids, dropped))
        if not sc.skipped[i]:
            policy.commit_to(buf, commit)
        last = tau
    return got


@SETTINGS
@given(scenario=restart_scenarios(), name=st.sampled_from(sorted(EVERY)), seed=st.integers(0, 2**32))
def test_bounding_a_buffer_at_any_moment_changes_no_selection(scenario, name, seed):
    sc, _ = scenario
    assert drive(name, sc, seed) == drive(name, sc, None)


def test_a_latest_buffer_stays_small_between_rare_ticks():
    """A 1 kHz stream into a consumer that has not ticked yet: Latest keeps a handful."""
    buf = PortBuffer(policy=Latest())
    for k in range(100_000):
        fill(buf, ((k * MS, 1), "src", "out", k, k), before((k * MS, 0)))
        assert len(buf.entries) <= 2 * buf.trim_batch  # (32: 16 entries a tick would let pile up, twice)
    assert buf.entries[-1][3] == 99_999


def test_a_bound_keeps_what_the_consumer_already_saw_in_place():
    """The first ``visible`` entries stay (a generated tick counts them); only what follows goes."""
    buf = PortBuffer(policy=Latest())
    for k in range(10):
        buf.insert(((k * MS, 1), "src", "out", k, k))
    bound(buf, (20 * MS, 0), visible=3)
    assert [e[3] for e in buf.entries] == [0, 1, 2, 9]
