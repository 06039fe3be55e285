"""The user API of a flow: @io, typed and untyped styles, clocks, configure, reset, EventStream."""

from __future__ import annotations

import dataclasses
import re
from dataclasses import dataclass
from typing import Optional

import pytest

import retriever
import retriever.flow
import retriever.flow.adapter
from retriever.flow.core import settings_of
from retriever import MISSING, ClockError, Flow, GraphError, Pipeline, Rate, StepError, io
from retriever.backends import default_backend
from retriever.flow import EventStream, Hybrid, Latest, Trigger, Window
from retriever.flow.adapter import ActionChunking, LatestDistinct, Queue


@io
@dataclass
class Obs:
    image: list
    goal: str


@io
class Act:
    action: float
    score: float


@io
class Tick:
    k: int


@io
class WithFallbacks:
    value: int
    note: str = "none"
    extra: Optional[int] = None


@io
class Sparse:
    always: int
    sometimes: Optional[int] = None


class ActionChunk:
    """A plain (non-@io) type: a single port named after it."""


class Policy(Flow[Obs, Act]):
    def __init__(self, gain: float = 1.0, *, bias: float = 0.0):
        self.gain = gain
        self.bias = bias
        self.calls = 0

    def step(self, inp: Obs) -> Act:
        self.calls += 1
        return Act(action=self.gain * len(inp.image) + self.bias, score=float(self.calls))


class Clock(Flow[None, Tick]):
    def __init__(self, start: int = 0):
        self.k = start

    def step(self, inp: None) -> Tick:
        self.k += 1
        return Tick(self.k)


class ObsSource(Flow[None, Obs]):
    def step(self, inp: None) -> Obs:
        return Obs(image=[0, 1], goal="wave")


class NoArgSource(Flow[None, Tick]):
    """A source whose step takes no input parameter at all."""

    def step(self) -> Tick:
        return Tick(1)


class Adder(Flow):
    """Untyped (the paper's Listing 1): one parameter per input port, a dict of outputs."""

    def __init__(self):
        self.total = 0

    def step(self, a, b=10):
        self.total += a + b
        return {"total": self.total}


class NoSuper(Flow[Tick, Tick]):
    def __init__(self, offset):
        self.offset = offset  # no super().__init__() on purpose

    def step(self, inp: Tick) -> Tick:
        return Tick(inp.k + self.offset)


class WithSuper(Flow[Tick, Tick]):
    def __init__(self, offset):
        super().__init__()
        self.offset = offset

    def step(self, inp: Tick) -> Tick:
        return Tick(inp.k + self.offset)


class Resettable(Flow[None, Tick]):
    """The paper's pattern: state initialised in reset(), which the runtime calls."""

    def reset(self):
        self.k = 100

    def step(self, inp):
        self.k += 1
        return Tick(self.k)


class Chunker(Flow[Tick, ActionChunk]):
    def step(self, inp):
        return ActionChunk()


class Fallbacks(Flow[WithFallbacks, None]):
    def __init__(self):
        self.seen = []

    def step(self, inp: WithFallbacks) -> None:
        self.seen.append(inp)


class SparseSource(Flow[None, Sparse]):
    def __init__(self):
        self.k = 0

    def step(self, inp):
        self.k += 1
        return Sparse(always=self.k, sometimes=self.k if self.k % 2 == 0 else None)


@pytest.fixture
def restore_default_backend():
    before = default_backend()
    yield
    retriever.init(backend=before)


# ---------------------------------------------------------------------------------------------
# Imports at the paths the paper and the project page use
# ---------------------------------------------------------------------------------------------
def test_paper_import_paths():
    from retriever import Flow as F1, Latest as L1, Pipeline as P1, Rate as R1, io as io1
    from retriever.flow import Hybrid as H2, Latest as L2, Rate as R2, Trigger as T2, Window as W2
    from retriever.flow.adapter import ActionChunking as AC3, LatestDistinct as LD3
    from retriever.flow.types import EventStream as ES4

    assert F1 is Flow and P1 is Pipeline and io1 is io

    assert R2 is R1 is retriever.Rate
    assert L2 is L1 is retriever.Latest
    assert AC3 is retriever.ActionChunking
    assert LD3 is retriever.LatestDistinct
    assert ES4 is retriever.EventStream
    assert H2 is retriever.Hybrid and T2 is retriever.Trigger and W2 is retriever.Window


@pytest.mark.parametrize("module", [retriever.flow, retriever.flow.adapter])
def test_sub_namespaces_reexport_the_same_objects(module):
    assert module.__all__ == sorted(module.__all__)
    for name in module.__all__:
        assert getattr(module, name) is getattr(retriever, name), name


# ---------------------------------------------------------------------------------------------
# @io
# ---------------------------------------------------------------------------------------------
def test_io_makes_a_dataclass_whose_fields_are_ports():
    assert dataclasses.is_dataclass(Act)
    assert [f.name for f in dataclasses.fields(Act)] == ["action", "score"]
    assert Act(1.0, 2.0) == Act(action=1.0, score=2.0)


def test_io_on_top_of_dataclass_keeps_it():
    assert [f.name for f in dataclasses.fields(Obs)] == ["image", "goal"]


def test_io_with_dataclass_options():
    @io(frozen=True)
    class Frozen:
        x: int

    with pytest.raises(dataclasses.FrozenInstanceError):
        Frozen(1).x = 2


def test_io_types_declare_the_ports_in_the_ir():
    with Pipeline("p") as pipe:
        (ObsSource() @ Rate(hz=1)).then(Policy() @ Rate(hz=1))
    ir = pipe.build_ir()
    assert ir.node("policy")["inputs"] == {"image": "list", "goal": "str"}
    assert ir.node("policy")["outputs"] == {"action": "float", "score": "float"}


def test_plain_type_is_a_single_port_named_in_snake_case():
    with Pipeline("p") as pipe:
        (Clock() @ Rate(hz=1)).then(Chunker() @ Rate(hz=1))
    assert pipe.build_ir().node("chunker")["outputs"] == {"action_chunk": "tests.flow.test_flow.ActionChunk"}


# ---------------------------------------------------------------------------------------------
# Calling a flow directly, with no runtime
# ---------------------------------------------------------------------------------------------
def test_typed_flow_direct_call():
    policy = Policy(gain=2.0)
    out = policy(Obs(image=[1, 2, 3], goal="open the drawer"))
    assert out == Act(action=6.0, score=1.0)
    assert policy(Obs(image=[], goal="")).score == 2.0


def test_untyped_flow_direct_call():
    adder = Adder()
    assert adder(1, 2) == {"total": 3}
    assert adder(a=1) == {"total": 14}


def test_source_direct_call():
    assert Clock(start=5)(None) == Tick(6)
    assert NoArgSource()() == Tick(1)


def test_subclass_without_super_init():
    flow = NoSuper(3) @ Rate(hz=1)
    assert flow(Tick(1)) == Tick(4)
    flow.configure(name="plus3")
    assert repr(flow) == "<NoSuper 'plus3' @ Rate(hz=1)>"


def test_subclass_with_super_init():
    assert WithSuper(2)(Tick(1)) == Tick(3)


@pytest.mark.parametrize("cls", [NoSuper, WithSuper])
def test_subclasses_run_in_a_pipeline(cls):
    with Pipeline("p") as pipe:
        (Clock() @ Rate(hz=10)).then(cls(100) @ Trigger("k"))
    trace = pipe.run(duration=0.3)
    assert trace.values_of(pipe.build_ir().nodes[1]["id"], "k") == [101, 102, 103]


# ---------------------------------------------------------------------------------------------
# Sources, clocks, configuration
# ---------------------------------------------------------------------------------------------
def test_sources_are_called_with_none_or_nothing():
    with Pipeline("p") as pipe:
        Clock() @ Rate(hz=10)
        NoArgSource() @ Rate(hz=10)
    trace = pipe.run(duration=0.2)
    assert trace.values_of("clock", "k") == [1, 2]
    assert trace.values_of("no_arg_source", "k") == [1, 1]


def test_matmul_binds_the_clock_and_returns_the_flow():
    flow = Clock()
    rate = Rate(hz=30)
    assert (flow @ rate) is flow
    assert repr(flow) == "<Clock @ Rate(hz=30)>"
    assert (flow @ Rate(hz=30)) is flow  # the same clock again changes nothing


def test_a_second_clock_is_refused_with_a_hint_at_hybrid():
    """A second ``@`` silently replaced the clock before."""
    flow = Clock() @ Rate(hz=30)
    with pytest.raises(ClockError, match=re.escape(
            "<Clock @ Rate(hz=30)> @ Trigger('k'): the flow already has the clock Rate(hz=30), and a flow has one "
            "clock\n    hint: to tick on a rate and on events, bind one Hybrid(hz=..., trigger=[...])")):
        flow @ Trigger("k")
    assert settings_of(flow).clock == Rate(hz=30)


def test_binding_a_flow_of_another_pipeline_is_refused():
    """``s @ Rate(5)`` in a second ``with Pipeline`` gave that pipeline a 0-node IR, silently."""
    with Pipeline("first") as first:
        flow = Clock()
    with Pipeline("second") as second:
        with pytest.raises(GraphError, match=re.escape(
                "pipeline 'second' has 1 problem:\n  - <Clock> belongs to pipeline 'first', where it was created "
                "or first wired, so it cannot join pipeline 'second'\n    hint: a flow belongs to one pipeline: make "
                "a new instance for 'second', e.g. Clock(...) @ Rate(hz=...)")):
            flow @ Rate(hz=5)
        with pytest.raises(GraphError, match="belongs to pipeline 'first'"):
            second.connect(flow, Clock() @ Trigger())
    assert settings_of(flow).clock is None
    assert len(second.flows) == 1  # the fresh Clock() only
    assert first.flows == [flow]


def test_a_flow_made_outside_a_pipeline_joins_the_one_it_is_bound_in():
    flow = Clock()
    with Pipeline("p") as pipe:
        flow @ Rate(hz=5)
    assert pipe.flows == [flow]
    assert pipe.build_ir().topology["node_count"] == 1


def test_matmul_with_something_that_is_not_a_clock():
    with pytest.raises(TypeError):
        Clock() @ 30


def test_clocks_are_values():
    assert Rate(hz=30) == Rate(30.0) != Rate(hz=30, offset=0.01)
    assert Trigger("a", "a", "b") == Trigger("a", "b")
    assert Hybrid(hz=10, trigger="a") == Hybrid(10, trigger=["a"])
    assert Rate(hz=0.1).tick_time(1) == 10_000_000_000
    assert Rate(hz=30).tick_time(3) == 100_000_000


def test_configure_and_named_return_the_flow_and_land_in_the_ir():
    with Pipeline("p") as pipe:
        policy = Policy(2.0, bias=1.0)
        assert policy.configure(latency=0.3, on_error="restart", on_overrun="error",
                                on_deadline_miss="drop") is policy
        assert policy.named("vla") is policy
        (ObsSource() @ Rate(hz=1)).then(policy @ Rate(hz=2))
    node = pipe.build_ir().node("vla")
    assert node["params"] == {"gain": 2.0, "bias": 1.0}
    assert node["config"] == {"clock": {"Rate": {"hz": 2, "offset": 0.0}}, "latency": 0.3, "on_error": "restart",
                              "on_overrun": "error", "on_deadline_miss": "drop",
                              "max_restarts": 5, "restart_window": 10.0}  # the restart budget's defaults


def test_spin_lands_in_the_ir_only_when_set_and_comes_back_from_it():
    with Pipeline("p") as pipe:
        ObsSource().configure(name="plain") @ Rate(hz=1)
        ObsSource().configure(name="ctrl", spin=100e-6) @ Rate(hz=200)
    ir = pipe.build_ir()
    assert "spin" not in ir.node("plain")["config"]
    assert ir.node("ctrl")["config"]["spin"] == 100e-6
    rebuilt = Pipeline.from_ir(ir)
    assert {settings_of(f).name: (settings_of(f).spin, settings_of(f).spin_ns) for f in rebuilt.flows} == {
        "plain": (0.0, 0), "ctrl": (100e-6, 100_000)}


@pytest.mark.parametrize("spin, says", [
    (-1e-6, "spin must be a finite number of seconds >= 0, got -1e-06"),
    (float("nan"), "spin must be a finite number of seconds >= 0, got nan"),
    ("100us", "spin must be a finite number of seconds >= 0, got '100us'"),
    (0.002, r"spin must be at most 0\.001 s \(a busy-wait before each tick\), got 0\.002"),
    (1e300, r"spin must be at most 0\.001 s \(a busy-wait before each tick\), got 1e\+300"),
])
def test_a_spin_out_of_range_is_refused_naming_it(spin, says):
    with pytest.raises(ValueError, match=r"ObsSource\.configure\(spin=.*\): " + says + r"\n    hint: spin is how long"):
        ObsSource().configure(spin=spin)


def test_flows_created_inside_a_with_block_join_the_innermost_pipeline():
    with Pipeline("outer") as outer:
        a = Clock() @ Rate(hz=1)
        with Pipeline("inner") as inner:
            b = Clock() @ Rate(hz=1)
        c = Clock() @ Rate(hz=1)
    assert outer.flows == [a, c]
    assert inner.flows == [b]


# ---------------------------------------------------------------------------------------------
# reset
# ---------------------------------------------------------------------------------------------
def test_default_reset_reruns_init_with_the_original_arguments():
    policy = Policy(3.0, bias=0.5).named("p") @ Rate(hz=2)
    policy(Obs([1], "x"))
    policy.gain = 99.0
    policy.scratch = "junk"
    policy.reset()
    assert (policy.gain, policy.bias, policy.calls) == (3.0, 0.5, 0)
    assert not hasattr(policy, "scratch")
    assert repr(policy) == "<Policy 'p' @ Rate(hz=2)>"  # runtime settings survive a reset


def test_default_reset_of_a_flow_without_init_clears_its_attributes():
    flow = NoArgSource()
    flow.cache = [1]
    flow.reset()
    assert not hasattr(flow, "cache")


def test_custom_reset_runs_at_the_start_of_a_run():
    with Pipeline("p") as pipe:
        Resettable() @ Rate(hz=10)
    assert pipe.run(duration=0.2).values_of("resettable", "k") == [101, 102]


def test_pipe_reset_returns_to_t0_with_every_flow_reset():
    with Pipeline("p") as pipe:
        (Clock(start=10) @ Rate(hz=10)).then(Adder() @ Trigger("a"), map={"k": "a"})
    first = pipe.run(duration=0.5)
    digest = first.digest()
    assert pipe.now == 0.5
    pipe.reset()
    assert pipe.now == 0.0
    assert len(pipe.trace) == 0
    again = pipe.run(duration=0.5)
    assert again.digest() == digest
    assert again.values_of("adder", "total") == [21, 43, 66, 90, 115]


# ---------------------------------------------------------------------------------------------
# Inputs: defaults, Optional, skipped ticks; sparse outputs
# ---------------------------------------------------------------------------------------------
def test_missing_inputs_take_defaults_or_none_or_skip_the_tick():
    with Pipeline("p") as pipe:
        sink = Fallbacks() @ Rate(hz=10)
        (Clock() @ Rate(hz=10, offset=0.15)).then(sink, map={"k": "value"})
    trace = pipe.run(duration=0.3)
    # ticks at 0, 0.1: nothing upstream yet (value is required) → skipped; at 0.2 the 0.15 tick's event
    assert [s.status for s in trace.steps_of("fallbacks")] == ["skipped", "skipped", "ok"]
    assert trace.steps_of("fallbacks")[0].detail == {"missing": ["value"]}
    assert sink.seen == [WithFallbacks(value=1, note="none", extra=None)]


def test_none_in_an_output_field_is_no_event():
    with Pipeline("p") as pipe:
        SparseSource() @ Rate(hz=10)
    trace = pipe.run(duration=0.4)
    assert trace.values_of("sparse_source", "always") == [1, 2, 3, 4]
    assert trace.values_of("sparse_source", "sometimes") == [2, 4]


def test_untyped_step_returning_something_else_than_a_dict():
    class Bad(Flow):
        def step(self):
            return 3

    with Pipeline("p") as pipe:
        Bad() @ Rate(hz=1)
    with pytest.raises(StepError, match=r"an untyped flow's step\(\) must return a dict of output ports or None, "
                                        r"got int"):
        pipe.run(duration=1)


def test_step_with_star_args_cannot_declare_ports():
    class Star(Flow):
        def step(self, *frames):
            return None

    with Pipeline("p") as pipe:
        Star() @ Rate(hz=1)
    with pytest.raises(GraphError, match=r"step\(…, \*frames\) cannot declare ports; "
                                         r"name one parameter per input port"):
        pipe.build_ir()


# ---------------------------------------------------------------------------------------------
# EventStream: a policy outside any pipeline
# ---------------------------------------------------------------------------------------------
def _frames() -> EventStream:
    frames = EventStream("frames")
    for i in range(5):
        frames.append(i * 0.1, f"f{i}")
    return frames


def test_event_stream_sample_latest():
    frames = _frames()
    assert len(frames) == 5
    assert EventStream().sample(Latest(), now=1.0) is MISSING
    assert frames.sample(Latest(), now=-1) is MISSING
    assert frames.sample(Latest(), now=0.2) == "f2"  # tag ≤ now
    assert frames.sample(Latest(), now=0.25) == "f2"
    assert frames.sample(Latest(staleness=0.01), now=0.25) is MISSING


def test_event_stream_sample_window():
    frames = _frames()
    assert frames.sample(Window(buffer_size=3), now=-1) == []
    assert frames.sample(Window(duration=0.15), now=0.4) == ["f3", "f4"]
    assert frames.sample(Window(buffer_size=3), now=1.0) == ["f2", "f3", "f4"]


def test_event_stream_fresh_policy_objects_do_not_share_state():
    # The seed's pattern, `stream.sample(Latest(), now=t)`, makes a new policy per call: each is a new
    # consumer, whatever times earlier calls asked for (and however CPython reuses object ids).
    frames = _frames()
    assert frames.sample(Latest(), now=0.45) == "f4"
    assert frames.sample(Latest(), now=0.05) == "f0"
    assert frames.sample(Window(buffer_size=2), now=1.0) == ["f3", "f4"]
    assert frames.sample(Window(buffer_size=2), now=0.15) == ["f0", "f1"]


def test_event_stream_sample_queue_consumes_per_policy_object():
    frames = _frames()
    queue = Queue()
    assert frames.sample(queue, now=0.15) == ["f0", "f1"]
    assert frames.sample(queue, now=0.35) == ["f2", "f3"]
    assert frames.sample(queue, now=0.35) == []
    assert frames.sample(Queue(), now=0.15) == ["f0", "f1"]  # another consumer starts fresh
    frames.append(0.5, "f5")
    assert frames.sample(queue, now=1.0) == ["f4", "f5"]


def test_event_stream_sample_latest_distinct():
    frames = _frames()
    distinct = LatestDistinct()
    assert frames.sample(distinct, now=0.1) == "f1"
    assert frames.sample(distinct, now=0.15) is MISSING
    assert frames.sample(distinct, now=0.2) == "f2"


def test_event_stream_sample_action_chunking():
    chunks = EventStream("chunks")
    chunks.append(0.1, [[0.0], [1.0], [2.0]])
    policy = ActionChunking(control_hz=100, chunk_steps=3)
    assert chunks.sample(policy, now=0.05) is MISSING
    assert chunks.sample(policy, now=0.115) == [1.0]
    assert chunks.sample(policy, now=0.5) == [2.0]  # past the end: hold the last row


def test_event_stream_refuses_out_of_order_appends():
    frames = _frames()
    with pytest.raises(ValueError, match=r"EventStream 'frames': tag \(100000000, 0\) is earlier than the last one "
                                         r"\(400000000, 0\); append in time order"):
        frames.append(0.1, "late")


# ---------------------------------------------------------------------------------------------
# The default backend
# ---------------------------------------------------------------------------------------------
def test_init_sets_the_backend_run_uses(restore_default_backend):
    retriever.init(backend="inproc")
    assert default_backend() == "inproc"
    with Pipeline("p") as pipe:
        Clock() @ Rate(hz=10)
    assert pipe.counts() == {} and pipe.stats() == {}  # nothing has run yet
    trace = pipe.run(duration=1.0)
    assert trace.values_of("clock", "k") == list(range(1, 11))
    assert pipe.stats()["clock"].ticks == 10
    # in virtual time nothing is late, incomplete or overrun: no real-time counters
    assert pipe.counts() == {} and pipe.stats()["clock"].counts == {}


def test_a_failed_init_keeps_the_previous_backend(restore_default_backend):
    retriever.init(backend="inproc")
    with pytest.raises(retriever.BackendError):
        retriever.init(backend="ros2")
    assert default_backend() == "inproc"
