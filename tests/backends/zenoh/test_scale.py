"""Runs with many flows, and runs in which a flow that should have ticked did not
(benchmarks/reports/scale.md)."""

from __future__ import annotations

import signal

import pytest

from retriever import BackendError, Latest, Pipeline, Rate
from retriever.backends.zenoh.coordinator import ticks_due
from retriever.backends.zenoh.protocol import Start
from tests.backends.zenoh.lifecycle_flows import SINK_HZ, SOURCE_HZ, Counter, Total

RUN_S = 1.0
#: issue 17: 50 flows on this 2-core machine panicked or lost flows (about 15 s here now)
MANY_FLOWS = 50


def _stop_before_the_start(session, node: str) -> None:
    """Have ``node``'s worker stop (SIGTERM) and exit just before the coordinator puts the run's
    start: it says ``done`` having run nothing, and exits 0."""
    proc = session.book.processes.workers[node]
    put = session.control.put

    def control(record) -> None:
        if type(record) is Start:
            proc.send_signal(signal.SIGTERM)
            proc.wait()
        put(record)

    session.control.put = control


def test_a_flow_whose_worker_stopped_before_the_start_fails_the_run_and_is_named():
    with Pipeline("stopped_early") as pipe:
        Counter() @ Rate(hz=SOURCE_HZ)
        Counter().configure(name="early") @ Rate(hz=SOURCE_HZ)
    _stop_before_the_start(pipe.open("zenoh", quiet=True), "early")
    with pytest.raises(BackendError, match=r"1 flow\(s\) never ticked in the run's 1 s, though their clocks had "
                                           r"ticks due:\n    early \(Rate\(hz=20\)\): 0 of 20 ticks; its worker "
                                           r"stopped before the run's start reached it\n    hint: .*start_margin="):
        pipe.run(duration=RUN_S, backend="zenoh")
    stats = pipe.stats()
    assert stats["early"].ticks == 0 and stats["counter"].ticks == RUN_S * SOURCE_HZ


def test_fifty_flows_start_and_every_one_ticks():
    """A camera-like source and 49 consumers, one process each: every flow runs every tick due
    (a flow that ran none would fail the run, as above)."""
    with Pipeline("fifty") as pipe:
        source = Counter() @ Rate(hz=SOURCE_HZ)
        for i in range(MANY_FLOWS - 1):
            source.then(Total().configure(name=f"total{i}") @ Rate(hz=SINK_HZ), sync=Latest())
    pipe.run(duration=RUN_S, backend="zenoh", quiet=True)
    due = {nid: ticks_due(node.clock, round(RUN_S * 1e9)) for nid, node in pipe.session.graph.nodes.items()}
    assert {nid: s.ticks for nid, s in pipe.stats().items()} == due
