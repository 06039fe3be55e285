"""The in-process loop (``InprocSession._advance``): a graph's schedule does not depend on what
else runs. A graph run as it is (its rate group often alone on the schedule: nothing else due,
nothing else scheduled) and beside a flow on another schedule (so the group is never alone)
records the same events and step records for the graph's own nodes, in the same order, with the
same stats and errors, whatever happens between the group's ticks: a delayed event scheduled at
the group's next tick (the two share that tick) or between two of them, a Trigger flow's tick at
the next microstep, a failed step, the end of a run, a log hand-over. (A loop that ran a lone
group's ticks back to back, and missed a delayed event due with its next tick, failed here.)"""

from __future__ import annotations

import threading
import warnings
from unittest import mock

import pytest
from hypothesis import given
from hypothesis import strategies as st

from retriever import Flow, Hybrid, Latest, LatestDistinct, Pipeline, Rate, RetrieverWarning, StepError, Trigger, Window
from retriever.backends.inproc import InprocSession

from .test_inproc_ticks import Count, Join, Plain, Untyped, UntypedSource
from .test_inproc_ticks import outcome as ticks_outcome
from . import test_schedule_independence as schedule_independence
from .test_schedule_independence import DURATION, SETTINGS, EdgeSpec, GraphSpec, NodeSpec, budget, graphs


def without(result, extra: str):
    """``test_inproc_ticks.outcome``'s records, stats and error, without node ``extra``'s."""
    (events, steps), stats, error = result
    return ([e for e in events if e[1] != extra], [s for s in steps if s[0] != extra],
            {node: s for node, s in stats.items() if node != extra}, error)


def outcome(build, runs, beside: bool, **options):
    """The graph's own records (wall-clock fields aside), stats and error; ``beside``: with an
    unrelated flow on another schedule, whose records are left out."""
    return without(ticks_outcome(lambda: build(beside), runs, **options), "beside")


def assert_alone_as_beside(build, runs=(0.5,), **options):
    alone, beside = outcome(build, runs, False, **options), outcome(build, runs, True, **options)
    assert alone[3] == beside[3]
    assert alone[2] == beside[2]
    assert len(alone[1]) == len(beside[1]) and len(alone[0]) == len(beside[0])
    assert alone[1] == beside[1]
    assert alone[0] == beside[0]
    return alone


def graph(*, delay: float = 0.0, trigger: bool = False, fail: int = 0, on_error: str = "stop", untyped: bool = False):
    def build(beside: bool):
        with Pipeline("alone") as pipe:
            if untyped:
                src = UntypedSource().named("src") @ Rate(100)
                stage = src.then(Untyped().named("s1") @ Rate(100), map={"x": "x"}, sync=Latest())
                stage.then(Untyped().named("s2") @ Rate(100), map={"out": "x"}, sync=Latest())
            else:
                src = Count(fail=fail).named("src").configure(on_error=on_error) @ Rate(100)
                src.then(Join().named("s1") @ Rate(100), map={"x": "a"}, sync=Latest())
            if delay:
                src.then(Plain().named("late") @ Trigger(), map={"x": "int"}, sync=Latest(), delay=delay)
            if trigger:
                src.then(Plain().named("next") @ Trigger(), map={"x": "int"}, sync=Latest())
            if beside:  # ticks at k/7 s: with the group's only at whole seconds
                Count().named("beside") @ Rate(7)
        return pipe
    return build


def test_a_chain_alone_records_what_it_records_beside_another_flow():
    events, steps, _, _ = assert_alone_as_beside(graph(), runs=(0.3, 0.25))
    assert len(steps) == 2 * 55  # a record per tick of each (s1's first, Latest having nothing yet, a skipped one)


def test_an_untyped_chain_alone_records_the_same():
    assert_alone_as_beside(graph(untyped=True))


@pytest.mark.parametrize("delay", [0.01, 0.004])  # at the group's next tick, or between two of them
def test_a_delayed_event_scheduled_from_a_lone_group_records_the_same(delay):
    _, steps, _, _ = assert_alone_as_beside(graph(delay=delay))
    assert sum(1 for s in steps if s[0] == "late") == 50 - (delay == 0.01)  # the last one lands at 0.5 s


def test_a_trigger_at_the_next_microstep_records_the_same():
    _, steps, _, _ = assert_alone_as_beside(graph(trigger=True))
    assert sum(1 for s in steps if s[0] == "next") == 50


@pytest.mark.parametrize("on_error", ["skip_tick", "stop"])
def test_a_failed_step_in_a_lone_group_records_the_same(on_error):
    _, _, _, error = assert_alone_as_beside(graph(fail=7, trigger=True, on_error=on_error), runs=(0.3, 0.2))
    assert (error is None) == (on_error == "skip_tick")


def test_log_hand_overs_and_stop_checks_between_ticks_record_the_same():
    with mock.patch.object(InprocSession, "LOG_BATCH", 5):
        assert_alone_as_beside(graph(trigger=True, delay=0.01), keep="records")


@SETTINGS
@given(spec=graphs(), salt=st.integers(0, 1000))
def test_random_graphs_record_the_same_beside_another_flow(spec, salt):
    """The random multi-rate graphs of the schedule-independence properties, as they are and with
    one more source on a schedule of its own that nothing consumes. That source spends none of
    the work budget, which the graph's own steps share: a graph that spends it all stops at the
    same step of its own beside it (the run's error, compared as the rest) as alone."""
    assert_random_graph_alone_as_beside(spec, salt)


def assert_random_graph_alone_as_beside(spec: GraphSpec, salt: int) -> None:
    beside = GraphSpec([*spec.nodes, NodeSpec("Beside", Rate(9), 0.0, {"salt": salt})], spec.edges)
    extra = f"n{len(spec.nodes)}"

    def run(graph):
        with budget(), warnings.catch_warnings():
            warnings.simplefilter("ignore", RetrieverWarning)
            return without(ticks_outcome(graph.build, (DURATION,)), extra)

    assert run(spec) == run(beside)


def test_a_random_graph_over_its_work_budget_stops_at_the_same_step_beside_another_flow():
    """A graph of Rally rallies fed by windows that spends its whole work budget (lowered here,
    so that it does in a short run): its run stops with the same error at the same step of its
    own beside the flow as alone. (With the flow beside it spending the budget too, it stopped a
    few steps earlier beside it, and the property failed on every such graph.)"""
    src = NodeSpec("Src", Rate(7), 0.0, {"salt": 0, "sparse": 0, "burst": 0})
    mix = NodeSpec("Mix", Trigger(), 0.0, {"salt": 0, "sparse": 0})
    rally = NodeSpec("Rally", Hybrid(200, trigger=["b"]), 0.0, {"salt": 0, "sparse": 0, "limit": 6})
    window = Window(buffer_size=3, duration=0.1)
    spec = GraphSpec([src, src, src, mix, mix, mix, mix, rally],
                     [EdgeSpec(0, "out", 6, "a", Latest()), EdgeSpec(0, "out", 7, "a", window),
                      EdgeSpec(6, "out", 7, "a", window), EdgeSpec(7, "fb", 7, "b", LatestDistinct())])
    with mock.patch.object(schedule_independence, "WORK_BUDGET", 3000):
        assert_random_graph_alone_as_beside(spec, salt=0)


def test_a_step_that_runs_its_own_pipeline_is_refused():
    """pipe.run() from a step of that pipeline's run (the run's thread, inside it): a clear error,
    not a second loop over the first one's schedule (the two tick paths disagreed on it)."""
    holder = {}

    class Recurses(Flow):
        def step(self):
            holder["pipe"].run(duration=0.01)

    with Pipeline("nested") as pipe:
        Recurses().named("r") @ Rate(100)
    holder["pipe"] = pipe
    with pytest.raises(StepError, match="called while this pipeline runs"):
        pipe.run(duration=0.05)


def test_a_background_run_stops_at_the_next_instant_after_stop():
    """RunHandle.stop() from another thread: the run stops before its next tick, not at the next
    batch of 4096 (with slow steps, many seconds later)."""
    reached, release = threading.Event(), threading.Event()

    class Waits(Flow):
        def __init__(self):
            self.n = 0

        def step(self):
            self.n += 1
            if self.n == 10:
                reached.set()
                release.wait(60)

    with Pipeline("stopped") as pipe:
        Waits().named("w") @ Rate(100)
    handle = pipe.run(duration=100, blocking=False)
    assert reached.wait(60)
    handle.stop()
    release.set()
    with pytest.raises(KeyboardInterrupt):
        handle.wait()
    assert pipe.stats()["w"].steps == 10
    assert pipe.now == 0.09, "at the last tick that ran"


def test_a_run_that_raised_is_at_the_instant_it_got_to():
    """After a step's error ``pipe.now`` is the time of the tick that raised (it stayed where
    the run began), and the next run goes on from there for its duration."""

    class FailsOnce(Flow):
        def __init__(self):
            self.n = 0

        def step(self):
            self.n += 1
            if self.n == 5:
                raise ValueError("once")
            return {"n": self.n}

    with Pipeline("raised") as pipe:
        FailsOnce().named("f") @ Rate(10)
    with pytest.raises(StepError, match="once"):
        pipe.run(duration=2.0)
    assert pipe.now == 0.4
    pipe.run(duration=1.0)
    assert pipe.now == 1.4
    assert [s.tag[0] for s in pipe.trace.steps_of("f")][-1] == 1_300_000_000
