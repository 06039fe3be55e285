"""Bad input: each case raises (or warns) once, with a message that names the thing, says what was
expected and what arrived, and gives a hint for common misuse."""

from __future__ import annotations

import json
import math
import re
import sys
import threading

import numpy as np
import pytest

import retriever
from retriever import (
    IR,
    ActionChunking,
    BackendError,
    Burst,
    CodecError,
    CausalityError,
    ClockError,
    Flow,
    GraphError,
    Hybrid,
    IRError,
    Latest,
    LatestDistinct,
    Pipeline,
    Queue,
    Rate,
    RetrieverError,
    RetrieverWarning,
    StepError,
    Trigger,
    Window,
    io,
)
from retriever.errors import InternalError
from retriever.ir import IR_VERSION
from tests import ir_flows


@io
class Num:
    x: int


@io
class Real:
    x: float


@io
class Text:
    s: str


@io
class Pair:
    a: int
    b: int


@io
class PairIn:
    p: int
    q: int


class NumSource(Flow[None, Num]):
    def step(self, inp):
        return Num(1)


class TextSource(Flow[None, Text]):
    def step(self, inp):
        return Text("a")


class PairSource(Flow[None, Pair]):
    def step(self, inp):
        return Pair(1, 2)


class RealSink(Flow[Real, None]):
    def step(self, inp):
        return None


class PairSink(Flow[PairIn, None]):
    def step(self, inp):
        return None


class NoStep(Flow[None, Num]):
    pass


class Counter(Flow[None, Num]):
    """Counts its steps; raises on the ``fail_at``-th step since construction/reset."""

    def __init__(self, fail_at: int = 3):
        self.fail_at = fail_at
        self.n = 0

    def step(self, inp):
        self.n += 1
        if self.n == self.fail_at:
            raise KeyError("no such joint")
        return Num(self.n)


class Monitor(Flow):
    def step(self, fb=None, tick=None):
        return {"skill": 1}


class Policy(Flow):
    def step(self, skill):
        return {"fb": 1}


class Ticker(Flow):
    def step(self):
        return {"tick": 1}


# ---------------------------------------------------------------------------------------------
# Graph errors (build_ir)
# ---------------------------------------------------------------------------------------------
def test_flow_without_step():
    with Pipeline("p") as pipe:
        NoStep() @ Rate(hz=1)
    with pytest.raises(GraphError, match=r"pipeline 'p' has 1 problem:\n"
                                         r"  - flow 'no_step' \(tests\.test_errors:NoStep\) has no step\(\) method\n"
                                         r"    hint: define step\(self, inp\)"):
        pipe.build_ir()


def test_flow_without_step_called_directly():
    with pytest.raises(NotImplementedError, match=r"NoStep has no step\(\) method\n    hint: define step"):
        NoStep()(None)


def test_unknown_output_port_in_map():
    with Pipeline("p") as pipe:
        (NumSource() @ Rate(hz=1)).then(RealSink() @ Rate(hz=1), map={"y": "x"})
    with pytest.raises(GraphError, match=r"edge num_source → real_sink \(test_errors\.py:\d+\): map names output port "
                                         r"'y', but num_source has no such output \(outputs: x\)\n"
                                         r"    hint: map goes \{output_port: input_port\}"):
        pipe.build_ir()


def test_unknown_input_port_in_map():
    with Pipeline("p") as pipe:
        (NumSource() @ Rate(hz=1)).then(RealSink() @ Rate(hz=1), map={"x": "z"})
    with pytest.raises(GraphError, match=r"map names input port 'z', but real_sink has no such input \(inputs: x\)"):
        pipe.build_ir()


def test_ambiguous_port_matching_by_type():
    with Pipeline("p") as pipe:
        (PairSource() @ Rate(hz=1)).then(PairSink() @ Rate(hz=1))
    with pytest.raises(GraphError, match=r"edge pair_source → pair_sink \(.*\): ambiguous port matching: no names in "
                                         r"common and several type-compatible pairs \(a→p, a→q, b→p, b→q\)\n"
                                         r"    hint: pass map=\{'<output>': '<input>'\} to choose"):
        pipe.build_ir()


def test_ambiguous_port_matching_from_an_untyped_producer():
    with Pipeline("p") as pipe:
        (Ticker() @ Rate(hz=1)).then(PairSink() @ Rate(hz=1))
    with pytest.raises(GraphError, match=r"ticker is untyped, so its outputs cannot be matched by name to pair_sink's "
                                         r"inputs \(p, q\); the match is ambiguous \(its step\(\) returns 'tick', "
                                         r"none of them an input's name\)\n"
                                         r"    hint: pass map=\{'<output>': '<input>'\} to say which port "
                                         r"of pair_sink"):
        pipe.build_ir()


def test_an_untyped_producer_whose_keys_are_known_is_matched_by_name():
    class Both(Flow):
        def step(self):
            return {"p": 1.0, "q": 2.0, "extra": 3.0}

    with Pipeline("p") as pipe:
        (Both() @ Rate(hz=1)).then(PairSink() @ Rate(hz=1))
    assert [(e["source"]["port"], e["destination"]["port"]) for e in pipe.build_ir().edges] == [("p", "p"),
                                                                                                  ("q", "q")]


def test_no_matching_port():
    with Pipeline("p") as pipe:
        (TextSource() @ Rate(hz=1)).then(RealSink() @ Rate(hz=1))
    with pytest.raises(GraphError, match=r"no output of text_source \(s\) matches an input of real_sink \(x\) "
                                         r"by name or type"):
        pipe.build_ir()


def test_edge_whose_output_type_does_not_fit_the_input_type():
    with Pipeline("p") as pipe:
        (TextSource() @ Rate(hz=1)).then(RealSink() @ Rate(hz=1), map={"s": "x"})
    with pytest.raises(GraphError, match=r"type mismatch on text_source\.s → real_sink\.x: the input expects float, "
                                         r"the edge delivers str\n    hint: fix one of the annotations"):
        pipe.build_ir()


def test_window_into_a_scalar_port_hints_that_windows_deliver_lists():
    with Pipeline("p") as pipe:
        (NumSource() @ Rate(hz=1)).then(RealSink() @ Rate(hz=1), sync=Window(buffer_size=2))
    with pytest.raises(GraphError, match=r"the input expects float, the edge delivers list of int\n"
                                         r"    hint: Window and Queue deliver lists"):
        pipe.build_ir()


def test_edge_into_a_source():
    with Pipeline("p") as pipe:
        (NumSource() @ Rate(hz=1)).then(TextSource() @ Rate(hz=1))
    with pytest.raises(GraphError, match=r"'text_source' is a source \(it has no input ports\)"):
        pipe.build_ir()


def test_trigger_on_a_port_the_flow_does_not_have():
    with Pipeline("p") as pipe:
        (NumSource() @ Rate(hz=1)).then(RealSink() @ Trigger("y"))
    with pytest.raises(GraphError, match=r"Trigger\('y'\) on 'real_sink': 'real_sink' has no input port 'y' "
                                         r"\(inputs: x\)\n    hint: trigger on one of the flow's input ports"):
        pipe.build_ir()


def test_hybrid_trigger_on_a_port_the_flow_does_not_have():
    with Pipeline("p") as pipe:
        (NumSource() @ Rate(hz=1)).then(RealSink() @ Hybrid(hz=5, trigger=["y"]))
    with pytest.raises(GraphError, match=r"Hybrid\(hz=5, trigger=\['y'\]\) on 'real_sink': 'real_sink' has no "
                                         r"input port 'y'"):
        pipe.build_ir()


def test_source_on_a_trigger_never_ticks():
    with Pipeline("p") as pipe:
        NumSource() @ Trigger()
    with pytest.raises(GraphError, match=r"'num_source' is a source clocked by Trigger\(\), so it never ticks\n"
                                         r"    hint: clock a source with Rate\(hz=\.\.\.\)"):
        pipe.build_ir()


def test_flow_with_no_clock():
    with Pipeline("p") as pipe:
        NumSource().then(RealSink() @ Rate(hz=1))
    with pytest.raises(GraphError, match=r"flow 'num_source' has no clock\n"
                                         r"    hint: bind one: NumSource\(\.\.\.\) @ Rate\(hz=\.\.\.\) or @ Trigger"):
        pipe.build_ir()


def test_duplicate_node_names():
    with Pipeline("p") as pipe:
        (NumSource().named("a") @ Rate(hz=1)).then(RealSink().named("a") @ Rate(hz=1))
    with pytest.raises(GraphError, match=r"node id 'a' is used by two flows \(NumSource and RealSink\)\n"
                                         r"    hint: give each flow its own name") as info:
        pipe.build_ir()
    # The collision must not cascade into phantom problems about an edge a → a.
    assert info.value.problems == [info.value.problems[0]], str(info.value)


def test_fan_in_with_mixed_policies():
    with Pipeline("p") as pipe:
        sink = RealSink() @ Rate(hz=1)
        (NumSource() @ Rate(hz=1)).then(sink, sync=Latest())
        (NumSource() @ Rate(hz=1)).then(sink, sync=LatestDistinct())
    with pytest.raises(GraphError, match=r"fan-in into real_sink\.x mixes sync policies: num_source\.x → real_sink\.x "
                                         r"uses Latest\(\), num_source_2\.x → real_sink\.x uses LatestDistinct\(\)\n"
                                         r"    hint: .*give every edge into the port the same sync="):
        pipe.build_ir()


def test_fan_in_with_differently_parametrised_policies():
    with Pipeline("p") as pipe:
        sink = RealSink() @ Rate(hz=1)
        (NumSource() @ Rate(hz=1)).then(sink, sync=Latest(staleness=0.1))
        (NumSource() @ Rate(hz=1)).then(sink, sync=Latest())
    with pytest.raises(GraphError, match=r"mixes sync policies: .* uses Latest\(staleness=0\.1\), .* uses Latest\(\)"):
        pipe.build_ir()


def test_edge_declared_twice():
    with Pipeline("p") as pipe:
        src, sink = NumSource() @ Rate(hz=1), RealSink() @ Rate(hz=1)
        src.then(sink)
        src.then(sink)
    with pytest.raises(GraphError, match=r"edge num_source\.x → real_sink\.x is declared twice"):
        pipe.build_ir()


def test_required_port_with_no_edge_warns():
    with Pipeline("p") as pipe:
        RealSink() @ Rate(hz=1)
    with pytest.warns(RetrieverWarning, match=r"pipeline 'p': input port real_sink\.x has no incoming edge and no "
                                              r"default: every tick of 'real_sink' will be skipped"):
        ir = pipe.build_ir()
    assert any("real_sink.x" in w for w in ir.warnings)


def test_warnings_point_at_the_users_code():
    with Pipeline("p") as pipe:
        RealSink() @ Rate(hz=1)
    with pytest.warns(RetrieverWarning) as built:
        pipe.build_ir()
    assert built[0].filename == __file__
    with Pipeline("q") as pipe:
        RealSink() @ Rate(hz=1)
    with pytest.warns(RetrieverWarning) as ran:
        pipe.run(duration=1)  # compiles on first run: the warning is still about this line, not pipeline.py
    assert ran[0].filename == __file__, f"{ran[0].filename}:{ran[0].lineno}"


def test_build_ir_reports_all_problems_in_one_graph_error():
    with Pipeline("many") as pipe:
        NoStep() @ Rate(hz=1)
        (NumSource() @ Rate(hz=1)).then(RealSink(), map={"y": "x"})
        (TextSource() @ Rate(hz=1)).then(RealSink() @ Trigger("q"), map={"s": "x"})
        (PairSource() @ Rate(hz=1)).then(PairSink() @ Rate(hz=1))
    with pytest.raises(GraphError) as info:
        pipe.build_ir()
    err = info.value
    assert err.pipeline == "many"
    expected = [
        r"flow 'no_step' \(tests\.test_errors:NoStep\) has no step\(\) method",
        r"map names output port 'y', but num_source has no such output",
        r"type mismatch on text_source\.s → real_sink_2\.x",
        r"ambiguous port matching",
        r"flow 'real_sink' has no clock",
        r"Trigger\('q'\) on 'real_sink_2': 'real_sink_2' has no input port 'q'",
    ]
    assert len(err.problems) == len(expected), str(err)
    text = str(err)
    assert text.startswith(f"pipeline 'many' has {len(expected)} problems:\n")
    for pattern in expected:
        assert any(re.search(pattern, str(p)) for p in err.problems), pattern
        assert re.search(r"\n  - .*" + pattern, text), pattern


def test_graph_error_is_a_retriever_error():
    assert issubclass(GraphError, RetrieverError)
    with Pipeline("p") as pipe:
        NoStep() @ Rate(hz=1)
    with pytest.raises(RetrieverError):
        pipe.run(duration=1)


# ---------------------------------------------------------------------------------------------
# Declaration errors (raised at once)
# ---------------------------------------------------------------------------------------------
@pytest.mark.parametrize("hz", [0, -1, -0.5, float("nan"), float("inf"), True, "30", None])
def test_rate_with_an_impossible_hz(hz):
    with pytest.raises(ClockError, match=re.escape(f"Rate(hz={hz!r}): hz must be a finite number > 0, got {hz!r}")
                       + r"\n    hint: for an event-driven flow use Trigger\(\"port\"\) instead of a rate"):
        Rate(hz=hz)


def test_clock_error_is_a_value_error():
    with pytest.raises(ValueError):
        Rate(hz=math.nan)


@pytest.mark.parametrize("offset", [-0.1, float("nan"), float("inf")])
def test_rate_with_an_impossible_offset(offset):
    with pytest.raises(ClockError, match=re.escape(f"Rate(offset={offset!r}): offset must be a finite number of "
                                                   "seconds >= 0")):
        Rate(hz=10, offset=offset)


def test_hybrid_with_an_impossible_hz():
    with pytest.raises(ClockError, match=r"Hybrid\(hz=0\): hz must be a finite number > 0"):
        Hybrid(hz=0, trigger=["x"])


@pytest.mark.parametrize("port", ["", 3, None])
def test_trigger_with_a_bad_port_name(port):
    with pytest.raises(ClockError, match=r"Trigger: trigger ports must be non-empty port names \(str\), got "
                                         + re.escape(repr(port))):
        Trigger(port)


def test_connect_with_a_class_instead_of_an_instance_hints_to_instantiate():
    with pytest.raises(TypeError, match=r"connect\(\): the source must be a Flow instance, got the class NumSource\n"
                                        r"    hint: instantiate it: \w+\(\) @ Rate\(hz=\.\.\.\)"):
        Pipeline("p").connect(NumSource, RealSink() @ Rate(hz=1))


def test_connect_with_a_policy_class_instead_of_an_instance_hints_to_instantiate():
    with pytest.raises(TypeError, match=r"connect\(\): sync must be a sync policy such as Latest\(\), got "
                                        r"<class 'retriever\.sync\.Latest'>\n"
                                        r"    hint: instantiate it: sync=Latest\(\)"):
        Pipeline("p").connect(NumSource() @ Rate(hz=1), RealSink() @ Rate(hz=1), sync=Latest)


def test_then_with_a_policy_class_hints_too():
    with Pipeline("p"), pytest.raises(TypeError, match=r"hint: instantiate it: sync=Latest\(\)"):
        (NumSource() @ Rate(hz=1)).then(RealSink() @ Rate(hz=1), sync=Latest)


def test_then_outside_a_pipeline_block():
    with pytest.raises(RuntimeError, match=r"NumSource\.then\(\.\.\.\) was called outside a `with Pipeline\(\.\.\.\)` "
                                           r"block\n    hint: wrap the wiring"):
        NumSource().then(RealSink())


@pytest.mark.parametrize("kwargs, message", [
    ({"map": ["x"]}, r"connect\(\): map must be a dict \{output_port: input_port\} of str, got \['x'\]"),
    ({"delay": -1}, r"connect\(\): edge NumSource → RealSink: delay must be a finite number of seconds >= 0, got -1"),
    ({"qsize": 0}, r"connect\(\): qsize must be an integer >= 1, got 0"),
])
def test_connect_with_bad_edge_options(kwargs, message):
    with pytest.raises((TypeError, ValueError), match=message):
        Pipeline("p").connect(NumSource() @ Rate(hz=1), RealSink() @ Rate(hz=1), **kwargs)


def test_unknown_backend_names_the_available_ones():
    with pytest.raises(BackendError, match=r"unknown backend 'ros2'; available: dora, inproc, zenoh"):
        retriever.init(backend="ros2")
    assert retriever.available_backends() == ["dora", "inproc", "zenoh"]


def test_run_on_an_unknown_backend():
    with Pipeline("p") as pipe:
        NumSource() @ Rate(hz=1)
    with pytest.raises(BackendError, match=r"unknown backend 'zenoh-x'; available: dora, inproc"):
        pipe.run(duration=1, backend="zenoh-x")


@pytest.mark.parametrize("name, value, allowed", [
    ("on_error", "ignore", "'stop', 'skip_tick', 'restart'"),
    ("on_overrun", "queue", "'skip', 'error'"),
    ("on_deadline_miss", "late", "'publish_late', 'drop', 'error'"),
])
def test_failure_policy_values_are_checked(name, value, allowed):
    with pytest.raises(ValueError, match=re.escape(f"Counter: {name}={value!r} is not one of {allowed}")):
        Counter().configure(**{name: value})


@pytest.mark.parametrize("on_error", ["stop", "skip_tick", "restart"])
def test_failure_policy_values_are_accepted_and_recorded_in_the_ir(on_error):
    with Pipeline("p") as pipe:
        Counter().configure(on_error=on_error) @ Rate(hz=1)
    assert pipe.build_ir().node("counter")["config"]["on_error"] == on_error


@pytest.mark.parametrize("latency", [-0.1, float("nan"), "fast"])
def test_bad_latency(latency):
    with pytest.raises(ValueError, match=re.escape(f"Counter.configure(latency={latency!r}): latency must be a "
                                                   "finite number of seconds >= 0")):
        Counter().configure(latency=latency)


@pytest.mark.parametrize("name", ["has space", "a/b", "", "1st", "n" * 129])
def test_bad_node_name(name):
    shown = repr(name) if len(name) < 40 else f"{repr(name)[:40]}… ({len(name)} characters)"
    with pytest.raises(ValueError, match=re.escape(f"Counter: node name {shown} must be an identifier-like str")):
        Counter().named(name)


# ---------------------------------------------------------------------------------------------
# Numbers beyond what integer-nanosecond time holds (issue 17 §3): no hang, no bare OverflowError
# ---------------------------------------------------------------------------------------------
TOO_LONG = "must be at most 9.223e+09 s (about 292 years: times are int64 nanoseconds)"


@pytest.mark.parametrize("make, owner", [(lambda hz: Rate(hz), "Rate"), (lambda hz: Hybrid(hz, trigger="a"), "Hybrid")],
                         ids=["Rate", "Hybrid"])
@pytest.mark.parametrize("hz", [1e300, 2e9, 10**9 + 1], ids=repr)
def test_a_rate_faster_than_one_tick_per_nanosecond_is_refused(make, owner, hz):
    """Rate(hz=1e300) had a period of 0 ns and hung inproc; hz above 1e9 ran two ticks at one tag."""
    with pytest.raises(ClockError, match=re.escape(
            f"{owner}(hz={hz!r}): hz must be at most 1e+09 (a tick period of at least 1 ns: ticks are integer "
            f"nanoseconds), got {hz!r}\n    hint: time counts integer nanoseconds: use hz <= 1e9")):
        make(hz)


def test_a_rate_slower_than_one_tick_per_292_years_is_refused():
    with pytest.raises(ClockError, match=re.escape("Rate(hz=1e-300): hz must be at least 1.084e-10 (a tick period "
                                                   "of at most about 292 years), got 1e-300")):
        Rate(hz=1e-300)


def test_the_fastest_rate_ticks_every_nanosecond():
    with Pipeline("p") as pipe:
        NumSource() @ Rate(hz=1e9)
    steps = pipe.run(duration=5e-9).steps
    assert [s.tag for s in steps] == [(t, 0) for t in range(5)]


@pytest.mark.parametrize("build, message", [
    (lambda: Rate(hz=1, offset=1e300), f"Rate(offset=1e+300): offset {TOO_LONG}, got 1e+300"),
    (lambda: Counter().configure(latency=1e300), f"Counter.configure(latency=1e+300): latency {TOO_LONG}, got 1e+300"
                                                 "\n    hint: latency is the flow's logical execution time"),
    (lambda: Pipeline("p").connect(NumSource() @ Rate(hz=1), RealSink() @ Rate(hz=1), delay=1e300),
     f"connect(): edge NumSource → RealSink: delay {TOO_LONG}, got 1e+300\n    hint: delay is the seconds"),
    (lambda: Pipeline("p").connect(NumSource() @ Rate(hz=1), RealSink() @ Rate(hz=1), deadline=float("inf")),
     "connect(): edge NumSource → RealSink: deadline must be a finite number of seconds >= 0, got inf"),
    (lambda: Pipeline("p", deadline=1e300), f"Pipeline(deadline=1e+300): deadline {TOO_LONG}, got 1e+300"),
    (lambda: Latest(staleness=1e300), f"Latest(staleness=1e+300): staleness {TOO_LONG}"),
    (lambda: Window(duration=1e20), f"Window(duration=1e+20): duration {TOO_LONG}"),
    (lambda: ActionChunking(horizon_ms=1e300), "ActionChunking(horizon_ms=1e+300): horizon_ms must be at most "
                                               "9.223e+12 (about 292 years"),
    (lambda: ActionChunking(control_hz=1e300), "ActionChunking(control_hz=1e+300): control_hz must be at most 1e+09"),
], ids=["offset", "latency", "delay", "deadline", "pipeline deadline", "staleness", "window", "horizon", "control_hz"])
def test_huge_seconds_are_refused_where_they_are_given(build, message):
    """Each of these raised a bare OverflowError (some only at build_ir() or run()) before."""
    with pytest.raises(ValueError, match=re.escape(message)):
        build()


@pytest.mark.parametrize("value", [0, -1, 1.5, True, "10", 2**63], ids=repr)
def test_bad_max_microsteps(value):
    with pytest.raises(ValueError, match=re.escape(f"Pipeline(max_microsteps={value!r}): max_microsteps must be an "
                                                   f"integer from 1 to 2**63 - 1 (how many microsteps")):
        Pipeline("p", max_microsteps=value)


def test_a_run_that_would_end_past_292_years_is_refused():
    with Pipeline("p") as pipe:
        NumSource() @ Rate(hz=1e-9)
    with pytest.raises(ValueError, match=re.escape(f"pipe.run(duration=1e+300): duration {TOO_LONG}, got 1e+300\n"
                                                   "    hint: run for a number of seconds")):
        pipe.run(duration=1e300)
    pipe.run(duration=9e9)
    with pytest.raises(ValueError, match=re.escape("pipe.step(dt=300000000.0): the run is at 9e+09 s, and dt would take "
                                                   "it past 9.223e+09 s")):
        pipe.step(dt=3e8)


# ---------------------------------------------------------------------------------------------
# Run-time errors
# ---------------------------------------------------------------------------------------------
def _zeno_pipeline(max_microsteps: int = 20) -> Pipeline:
    with Pipeline("zeno", max_microsteps=max_microsteps) as pipe:
        monitor = Monitor() @ Trigger("fb", "tick")
        policy = Policy() @ Trigger("skill")
        (Ticker() @ Rate(hz=1)).then(monitor, map={"tick": "tick"})
        monitor.then(policy, map={"skill": "skill"})
        policy.then(monitor, map={"fb": "fb"})
    return pipe


def test_instantaneous_cycle_warns_at_build_time_naming_the_cycle():
    with pytest.warns(RetrieverWarning, match=r"instantaneous cycle monitor → policy → monitor: every link is a "
                                              r"zero-latency, undelayed edge into a trigger port"):
        ir = _zeno_pipeline().build_ir()
    assert ir.topology["instantaneous_cycles"] == [["monitor", "policy"]]


def test_zeno_loop_at_run_time_names_the_cycle_and_the_tag():
    pipe = _zeno_pipeline(max_microsteps=20)
    with pytest.warns(RetrieverWarning), pytest.raises(CausalityError) as info:
        pipe.run(duration=1)
    err = info.value
    assert re.search(r"Zeno loop: the instant at t=0\.000000000s m=\d+ ran past max_microsteps=20 around the cycle "
                     r"(monitor → policy → monitor|policy → monitor → policy)\n"
                     r"    hint: break the cycle in time: give a flow on it latency=", str(err)), str(err)
    assert set(err.cycle) == {"monitor", "policy"}
    assert err.tag[0] == 0


def test_zeno_loop_is_broken_by_latency():
    pipe = _zeno_pipeline()
    pipe.flows[1].configure(latency=0.01)
    trace = pipe.run(duration=0.1)
    assert len(trace.steps_of("policy")) == 10


def test_step_that_raises_stops_the_run_naming_node_and_tick():
    with Pipeline("p") as pipe:
        Counter(fail_at=3) @ Rate(hz=10)
    with pytest.raises(StepError, match=r"counter\.step\(\) raised KeyError: 'no such joint' "
                                        r"\(tick at t=0\.200000000s m=0\)\n"
                                        r"    hint: set on_error='skip_tick' or 'restart' on 'counter'") as info:
        pipe.run(duration=1)
    err = info.value
    assert isinstance(err.__cause__, KeyError)
    assert err.__cause__.args == ("no such joint",)
    assert (err.node, err.tag) == ("counter", (200_000_000, 0))
    record = pipe.trace.steps_of("counter")[-1]
    assert record.status == "error"
    assert record.detail == {"error": "KeyError: 'no such joint'", "on_error": "stop"}


class Exits(Flow[None, Num]):
    """Calls sys.exit(3) on every ``every``-th step."""

    def __init__(self, every: int = 2):
        self.every, self.n = every, 0

    def step(self, inp):
        self.n += 1
        if self.n % self.every == 0:
            sys.exit(3)
        return Num(self.n)


def test_sys_exit_in_a_step_is_that_steps_error():
    """sys.exit(3) in a step ended the inproc run, and the program, silently with status 3."""
    with Pipeline("p") as pipe:
        Exits() @ Rate(hz=10)
    with pytest.raises(StepError, match=r"exits\.step\(\) raised SystemExit: 3 \(tick at t=0\.100000000s m=0\)\n"
                                        r"    hint: set on_error='skip_tick'") as info:
        pipe.run(duration=1)
    assert isinstance(info.value.__cause__, SystemExit)
    assert pipe.trace.steps[-1].detail == {"error": "SystemExit: 3", "on_error": "stop"}


def test_sys_exit_in_a_step_follows_on_error():
    with Pipeline("p") as pipe:
        Exits().configure(on_error="skip_tick") @ Rate(hz=10)
    trace = pipe.run(duration=1)
    assert [s.status for s in trace.steps] == ["ok", "error"] * 5
    assert pipe.stats()["exits"].errors == 5


def test_keyboard_interrupt_in_a_step_still_stops_the_program():
    class Interrupted(Flow[None, Num]):
        def step(self, inp):
            raise KeyboardInterrupt

    with Pipeline("p") as pipe:
        Interrupted().configure(on_error="skip_tick") @ Rate(hz=10)
    with pytest.raises(KeyboardInterrupt):
        pipe.run(duration=1)


class Unrecordable(Flow):
    """Returns, on its ``bad_at``-th step, a value the codec cannot encode on port ``y``."""

    def __init__(self, bad: str = "lock", bad_at: int = 2):
        self.bad, self.bad_at, self.n = bad, bad_at, 0

    def step(self):
        self.n += 1
        if self.n != self.bad_at:
            return {"x": self.n, "y": [self.n]}
        if self.bad == "itself":  # a list that holds itself
            itself: list = [np.zeros(2)]
            itself.append(itself)
            return {"x": self.n, "y": itself}
        value = {"lock": threading.Lock(), "set": {"a": {1, 2}}, "burst": Burst([7, threading.Lock()])}[self.bad]
        return {"x": self.n, "y": value}


@pytest.mark.parametrize("on_error", ["stop", "skip_tick"])
@pytest.mark.parametrize("bad, what", [("lock", "cannot encode a value of type _thread.lock"),
                                       ("set", "cannot encode a value of type builtins.set at value['a']")])
def test_a_step_returning_an_unencodable_value_stops_the_run_at_that_step(bad, what, on_error):
    """inproc ran such a run to the end and then failed in trace.digest(); it stops at the step, as
    zenoh (which cannot send the value) does, whatever on_error says: the flow has a bug."""
    with Pipeline("p") as pipe:
        Unrecordable(bad).named("u").configure(on_error=on_error) @ Rate(hz=10)
    with pytest.raises(CodecError, match=re.escape(
            f"u.y: the step at t=0.100000000s m=0 returned a value the run cannot record: {what}\n"
            "    hint: use numbers, str, bytes, lists, dicts, numpy arrays or @io dataclasses")):
        pipe.run(duration=1)
    last = pipe.trace.steps[-1]
    assert (last.tag, last.status, last.produced) == ((100_000_000, 0), "error", (("u", "x", 1),))
    assert last.detail["error"].startswith("CodecError: u.y: the step at t=0.100000000s m=0")
    assert pipe.stats()["u"].errors == 1
    pipe.trace.digest()  # what was recorded can be digested


def test_a_step_returning_a_value_that_holds_itself_stops_the_run_at_that_step():
    """A list appended to itself cannot be encoded (nor made read-only): the run stops at the
    step with the codec's error, not a RecursionError from deep in the runtime."""
    with Pipeline("p") as pipe:
        Unrecordable("itself").named("u") @ Rate(hz=10)
    with pytest.raises(CodecError, match=re.escape(
            "u.y: the step at t=0.100000000s m=0 returned a value the run cannot record: cannot encode a list "
            "nested too deeply (it may contain itself: a list or dict holding itself, a dataclass referring back "
            "to it)\n    hint: emit values that are trees, not graphs")):
        pipe.run(duration=1)
    last = pipe.trace.steps[-1]
    assert (last.tag, last.status, last.produced) == ((100_000_000, 0), "error", (("u", "x", 1),))


def test_a_burst_holding_an_unencodable_value_stops_the_run_with_none_of_its_events():
    with Pipeline("p") as pipe:
        Unrecordable("burst").named("u") @ Rate(hz=10)
    with pytest.raises(CodecError, match="u.y: the step at t=0.100000000s m=0 returned a Burst whose value 1 is one "
                                         "the run cannot record: cannot encode a value of type _thread.lock"):
        pipe.run(duration=1)
    last = pipe.trace.steps[-1]
    # none of the burst's events, as on zenoh, where it is one message that cannot be sent
    assert (last.status, last.produced) == ("error", (("u", "x", 1),))


def test_step_that_raises_with_skip_tick_keeps_running():
    with Pipeline("p") as pipe:
        Counter(fail_at=3).configure(on_error="skip_tick") @ Rate(hz=10)
    trace = pipe.run(duration=1)
    statuses = [s.status for s in trace.steps_of("counter")]
    assert statuses == ["ok", "ok", "error"] + ["ok"] * 7
    assert trace.values_of("counter", "x") == [1, 2, 4, 5, 6, 7, 8, 9, 10]
    assert pipe.stats()["counter"].errors == 1


def test_step_that_raises_with_restart_resets_the_flow():
    with Pipeline("p") as pipe:
        Counter(fail_at=3).configure(on_error="restart") @ Rate(hz=10)
    trace = pipe.run(duration=1)
    # the state restarts after each failure, so it fails every third tick
    assert [s.status for s in trace.steps_of("counter")] == ["ok", "ok", "error"] * 3 + ["ok"]
    assert trace.values_of("counter", "x") == [1, 2, 1, 2, 1, 2, 1]
    assert trace.steps_of("counter")[2].detail["on_error"] == "restart"


def test_step_returning_the_wrong_type_is_a_step_error():
    class Wrong(Flow[None, Num]):
        def step(self, inp):
            return "not a Num"

    with Pipeline("p") as pipe:
        Wrong() @ Rate(hz=1)
    with pytest.raises(StepError, match=r"wrong\.step\(\) raised OutputError: step\(\) returned str, expected "
                                        r"tests\.test_errors\.Num"):
        pipe.run(duration=1)


def test_a_typed_step_returning_a_dict_with_an_undeclared_port_is_a_step_error():
    class Partial(Flow[None, Num]):
        def __init__(self, ports: list):
            self.ports = ports

        def step(self, inp):
            return dict.fromkeys(self.ports, 1)

    with Pipeline("fine") as pipe:  # a dict of declared ports is fine
        Partial(["x"]) @ Rate(hz=1)
    assert pipe.run(duration=1).values_of("partial", "x") == [1]
    with Pipeline("p") as pipe:
        Partial(["x", "bogus"]) @ Rate(hz=1)
    with pytest.raises(StepError, match=r"partial\.step\(\) raised OutputError: step\(\) returned a dict with "
                                        r"port\(s\) 'bogus', which tests\.test_errors\.Num does not declare "
                                        r"\(its ports: x\)"):
        pipe.run(duration=1)


# ---------------------------------------------------------------------------------------------
# IR documents
# ---------------------------------------------------------------------------------------------
def _ir_doc() -> dict:
    return json.loads(ir_flows.build().build_ir().to_json())


def test_malformed_ir_text():
    with pytest.raises(IRError, match=r"invalid IR \(<string>\):\n  - not valid JSON: Expecting value at line 1, "
                                      r"column 1"):
        IR.from_json("nodes: []")


def test_wrong_version_ir():
    doc = _ir_doc()
    doc["version"] = "2.0.0"
    reads = re.escape(IR_VERSION)
    with pytest.raises(IRError, match=rf"version '2\.0\.0' is not supported by this Retriever \(it reads {reads}\); "
                                      r"rebuild the IR with this version: retriever ir FILE --out PATH"):
        IR.from_json(json.dumps(doc))


def test_unknown_policy_in_an_ir():
    doc = _ir_doc()
    doc["edges"][0]["adapter"] = {"newest": {}}
    with pytest.raises(IRError, match=r"edges\[0\]\.adapter: unknown sync policy 'newest'; known: action_chunking, "
                                      r"exact, latest, latest_distinct, queue, window"):
        IR.from_json(json.dumps(doc))


@pytest.mark.parametrize("policy, message", [
    (lambda: Window(buffer_size=0), r"Window\(buffer_size=0\): buffer_size must be an integer >= 1"),
    (lambda: Queue(maxsize=-1), r"Queue\(maxsize=-1\): maxsize must be an integer >= 1"),
    (lambda: Latest(staleness=-1), r"Latest\(staleness=-1\): staleness must be a finite number of seconds >= 0"),
])
def test_bad_policy_parameters(policy, message):
    with pytest.raises(ValueError, match=message):
        policy()


def test_internal_error_says_it_is_a_bug_in_retriever():
    assert str(InternalError("heap out of order")) == (
        "heap out of order (this is a bug in Retriever, not in your program; please report it)")



def _exception_classes_defined_outside_errors() -> list[str]:
    """Every class in ``retriever/`` outside errors.py that derives from an exception, read from
    the source (importing every module would need every optional extra)."""
    import ast
    import builtins
    from pathlib import Path

    import retriever.errors

    package = Path(retriever.__file__).parent
    exceptions = {name for name, obj in vars(retriever.errors).items()
                  if isinstance(obj, type) and issubclass(obj, BaseException)}
    exceptions |= {name for name, obj in vars(builtins).items() if isinstance(obj, type) and issubclass(obj, BaseException)}
    found = []
    for path in sorted(package.rglob("*.py")):
        if path == package / "errors.py":
            continue
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if isinstance(node, ast.ClassDef):
                bases = {b.id if isinstance(b, ast.Name) else b.attr for b in node.bases
                         if isinstance(b, (ast.Name, ast.Attribute))}
                if bases & exceptions or any(b.endswith(("Error", "Exception", "Warning")) for b in bases):
                    found.append(f"{path.relative_to(package)}: {node.name}")
    return found


def test_every_exception_of_the_package_is_defined_in_errors_py():
    assert _exception_classes_defined_outside_errors() == [], "define them in retriever/errors.py, in its tree"


def test_errors_py_draws_every_exception_it_defines():
    import retriever.errors

    classes = [name for name, obj in vars(retriever.errors).items()
               if isinstance(obj, type) and issubclass(obj, (BaseException, Warning))
               and obj.__module__ == "retriever.errors"]
    tree = retriever.errors.__doc__.split("Every exception class")[0]
    drawn = set(re.findall(r"^ {4}[│ ]*(?:[├└]── )?([A-Z][A-Za-z]+)", tree, re.MULTILINE))
    assert sorted(set(classes) - drawn) == []


def test_a_wrapped_errors_context_is_on_its_first_line_and_its_own_hint_stays_last():
    from retriever.errors import SetupError

    cause = RuntimeError("device='cuda', but torch finds no CUDA device\n    hint: device='cpu'")
    setup = str(SetupError("policy", cause)).split("\n")
    assert setup == ["policy.setup() raised RuntimeError: device='cuda', but torch finds no CUDA device, before its "
                     "first tick: the run did not start", "    hint: device='cpu'"]
    mismatch = ValueError("its observation does not fit the checkpoint\n    'state' has the shape (4,)\n"
                          "    hint: features={'source': 'feature key'}")
    step = str(StepError("policy", (200_000_000, 0), mismatch)).split("\n")
    assert step == ["policy.step() raised ValueError: its observation does not fit the checkpoint "
                    "(tick at t=0.200000000s m=0)", "    'state' has the shape (4,)",
                    "    hint: features={'source': 'feature key'}"]
    plain = str(StepError("policy", (0, 0), KeyError("x"))).split("\n")
    assert plain[0] == "policy.step() raised KeyError: 'x' (tick at t=0.000000000s m=0)"
    assert plain[1].startswith("    hint: set on_error='skip_tick' or 'restart' on 'policy'") and len(plain) == 2
