"""A real-time consumer that rarely ticks holds, on each input, what its policy may still select,
not every event since its last tick (sync.fill, bounded by Streams.horizon): a real NodeLoop
driven by hand, as in test_restart_afresh.py. No test here waits on time."""

from __future__ import annotations

import pytest

from retriever import Latest, Pipeline, Rate, Trigger
from retriever.backends.zenoh.node import DATA, PROGRESS
from retriever.backends.zenoh.wire import WireEncoder
from retriever.backends.zenoh.worker.build import build_loop

from .semantics_flows import PairProbe, Ticker
from .specs import run_spec
from .test_restart_afresh import tick_all

MS = 1_000_000


@pytest.fixture
def loop(session):
    """``belief`` (Trigger on b, rare's) takes the newest of counter's 1 kHz values on a."""
    with Pipeline("bounded_by_hand") as pipe:
        fast = Ticker().configure(name="counter") @ Rate(hz=1000)
        rare = Ticker().configure(name="rare") @ Rate(hz=0.01)
        belief = PairProbe().configure(name="belief") @ Trigger("b")
        fast.then(belief, map={"value": "a"}, sync=Latest())
        rare.then(belief, map={"value": "b"}, sync=Latest())
    loop = build_loop(run_spec(pipe.compile().to_ir().doc, "bounded-test"), "belief", session)
    loop.declare()
    loop.run_clock.t0, loop.run_clock.end, loop.run_clock.started = 0, 1 << 62, True  # as run() sets them
    yield loop
    loop.undeclare()


def fast(seq: int) -> tuple:
    """counter's event at ``seq`` ms (its frontier just past it)."""
    return (DATA, ("counter", "value"), WireEncoder().data((seq * MS, 1), seq, (seq * MS, 2), "counter", "value", seq))


def test_a_consumer_between_rare_triggers_holds_a_few_of_a_1_khz_stream(loop):
    buf = next(buf for port, buf, *_ in loop.steps.inputs if port == "a")
    # rare promises nothing before 30 s: no tick of belief comes before it
    loop.handle((PROGRESS, "rare", WireEncoder().progress((30_000 * MS, 0), "rare", {"value": -1})))
    most = 0
    for seq in range(20_000):  # 20 s of counter's events, belief not ticking
        loop.handle(fast(seq))
        most = max(most, len(buf.entries))
    assert most <= 4  # without the bound: 20 000
    # rare's event at 30 s: belief ticks there, and takes the newest of counter's as ever
    loop.handle((DATA, ("rare", "value"), WireEncoder().data((30_000 * MS, 1), 0, (30_000 * MS, 2), "rare", "value", 7)))
    tick_all(loop)
    (record,) = loop.reports.records
    assert record[0] == (30_000 * MS, 1)
    assert {port: [eid[2] for eid in ids] for port, ids in record[1].items()} == {"a": [19_999], "b": [0]}
