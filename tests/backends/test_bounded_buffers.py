"""A flow that rarely ticks holds, on each input, what its policy may still select, not every event
since its last tick (benchmarks/reports/replay.md, "One hour of Retriever-0": belief, ticking twice
in an hour, held every observation of the world's until its next tick). Input buffers are bounded
as events come (sync.fill), by the consumer's policy, on the generated ticks' path and the
reference one alike; what each tick selects is the same as without the bound."""

from __future__ import annotations

from dataclasses import dataclass

import pytest

from retriever import Flow, Latest, Pipeline, Queue, Rate, Trigger, Window, io
from retriever.backends.inproc import InprocSession

from .test_inproc_inputs_at import Count, Counter

S = 1_000_000_000


@io
@dataclass
class Seen:
    n: int


@io
@dataclass
class Batch:
    n: list


class Rare(Flow[Seen, Count]):
    """Ticks once per 100 s of virtual time; says what it saw."""

    def step(self, inp: Seen) -> Count:
        return Count(inp.n)


class Batcher(Flow[Batch, Count]):
    def step(self, inp: Batch) -> Count:
        return Count(len(inp.n))


def rare_pipeline(sync) -> Pipeline:
    with Pipeline("rare") as pipe:
        fast = Counter().named("fast") @ Rate(1000)
        flow = (Batcher() if sync.delivers_list else Rare()).named("rare") @ Rate(0.01, offset=50.0)
        fast.then(flow, map={"n": "n"}, sync=sync)
    return pipe


@pytest.mark.parametrize("generate", [True, False], ids=["generated ticks", "reference ticks"])
def test_a_flow_ticking_once_per_100_s_holds_a_few_of_a_1000_hz_stream(generate):
    session = InprocSession(rare_pipeline(Latest()).compile(), generate_ticks=generate)
    most = 0
    for k in range(1, 251):  # 250 s of virtual time, looking every second
        session.advance(k * S)
        most = max(most, session.held("rare")["n"])
    assert most <= 32  # twice what its ticks let pile up (16); without the bound: 100 000 (every event of the 100 s before a tick)
    seen = [record.tag[0] // S for record in session.trace.steps_of("rare")]
    assert seen == [50, 150]
    values = {event.id: event.value for event in session.trace.events}
    for record in session.trace.steps_of("rare"):  # the newest event before each tick, as ever
        (event_id,), = record.consumed.values()
        assert values[event_id] == record.tag[0] * 1000 // S


def test_a_window_holds_its_size_and_a_queue_everything_it_has_not_consumed():
    window = InprocSession(rare_pipeline(Window(buffer_size=5)).compile())
    queue = InprocSession(rare_pipeline(Queue()).compile())
    for k in range(1, 121):
        window.advance(k * S)
        queue.advance(k * S)
        assert window.held("rare")["n"] <= 32
    assert queue.held("rare")["n"] == 70 * 1000  # consumed at 50 s; since then every one stays


@pytest.mark.parametrize("hz", [62.5, 50, 20, 1])
def test_generated_ticks_select_as_the_reference_ones_while_their_buffers_are_bounded(hz):
    """A generated tick keeps its count of the entries it saw in a variable of its own: a bound
    between two of its ticks (its producer's 16 events after a tick that saw 16, trimming none)
    must leave them where they are, or the next tick takes an entry not yet visible, or none."""
    def run(generate: bool):
        with Pipeline("between") as pipe:
            fast = Counter().named("fast") @ Rate(1000)
            fast.then(Rare().named("mid") @ Rate(hz), map={"n": "n"}, sync=Latest())
        session = InprocSession(pipe.compile(), generate_ticks=generate)
        session.advance(2 * S)  # one run: the generated ticks hand nothing over until it ends
        return session.trace.digest(), session.generated_ticks()

    (generated, nodes), (reference, _) = run(True), run(False)
    assert "mid" in nodes and generated == reference
