"""A step's sys.exit(0) in virtual time ends the run where it does in-process: at the step's tag,
whatever the wall clock read when the coordinator heard of it, and whatever the other nodes ran
ahead in their lockstep window; the coordinator grants no window past it."""

from __future__ import annotations

import pytest

from retriever import Latest, Pipeline, Rate, Trigger
from retriever.backends.zenoh.coordinator import RunControl
from retriever.backends.zenoh.coordinator.waiting import LOCKSTEP_WINDOW_NS
from retriever.backends.zenoh.protocol import Grant

from .semantics_flows import Echo, EndsAt, Ticker

EXIT_NS = 700_000_000  # the ender's 8th tick, at 10 Hz


def ending_pipeline() -> Pipeline:
    with Pipeline("ends") as pipe:
        ender = EndsAt(at=8).configure(name="ender") @ Rate(hz=10)
        ticker = Ticker().configure(name="ticker") @ Rate(hz=15)  # (no tick at the exit's t=0.7 s)
        echo = Echo().configure(name="echo") @ Trigger("x")
        ticker.then(echo, sync=Latest(), map={"value": "x"})
    return pipe


def steps(trace) -> list:
    return sorted((s.node, s.tag, s.status, tuple(sorted(s.consumed.items()))) for s in trace.steps)


@pytest.fixture(scope="module")
def ended():
    """The pipeline run in-process, then on zenoh in virtual time with every grant it put seen
    (RunControl.put, the coordinator's one way to the workers)."""
    pipe = ending_pipeline()
    reference = pipe.run(duration=30.0, backend="inproc")
    pipe.reset()
    grants = []
    put = RunControl.put

    def seen_put(control, record):
        if isinstance(record, Grant):
            grants.append(record.until)
        put(control, record)

    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(RunControl, "put", seen_put)
        trace = pipe.run(duration=30.0, backend="zenoh", virtual_time=True, quiet=True)
    return pipe, reference, trace, grants


def test_a_step_ending_the_run_in_virtual_time_ends_it_at_its_tag_as_in_process(ended):
    pipe, reference, trace, _ = ended
    assert pipe.session.ended_by == "ender"
    last = max(s.tag for s in reference.steps)
    assert last[0] < 1_000_000_000, "the reference ends at the exit, not at the duration"
    assert steps(trace) == steps(reference)
    assert sorted(e.id for e in trace.events) == sorted(e.id for e in reference.events)
    assert trace.first_difference(reference) is None
    assert pipe.now == EXIT_NS / 1e9


def test_no_window_is_granted_past_the_window_of_the_exit(ended):
    """The windows up to the one holding the exit's tag (the first one comes with the start),
    each granted once but when a node was slow to say it reached it; none after."""
    *_, grants = ended
    windows = list(range(2 * LOCKSTEP_WINDOW_NS, EXIT_NS + LOCKSTEP_WINDOW_NS + 1, LOCKSTEP_WINDOW_NS))
    assert sorted(set(grants)) == windows
