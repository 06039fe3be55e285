"""The compiled per-node ticks of the inproc backend (backends/inproc_ticks.py) against the
reference tick, ``retriever.tick.run_tick``: the same graph, run once with every node it can compile
compiled and once with none, must record the same events and step records in the same order
(wall-clock fields aside), the same stats, and fail the same way.

This is what keeps the two paths in sync: a change to ``run_tick`` (or to ``Latest``, the output
readers, the invokers) that the generated code does not follow fails here.
"""

from __future__ import annotations

import functools
import inspect
import struct
import threading
import time
import warnings
from dataclasses import dataclass
from typing import Any, Optional

import pytest
from hypothesis import given

from retriever import Flow, Hybrid, Latest, Pipeline, Rate, RetrieverWarning, StepError, Trigger, io
from retriever.backends.inproc import InprocSession

from .test_schedule_independence import DURATION, SETTINGS, budget, graphs


def records(trace) -> tuple[list, list]:
    """Every record in recording order, without the wall-clock fields."""
    return [e[:5] for e in trace.raw_events], [s[:6] for s in trace.raw_steps]


def ran(build, runs, **options):
    """``build()``'s pipeline, opened with the backend ``options`` and run in the increments
    ``runs``, and the error that stopped it if any."""
    pipe = build()
    pipe.open(**options)
    error = None
    try:
        for duration in runs:
            pipe.run(duration=duration)
    except Exception as exc:  # noqa: BLE001 - compared below
        error = f"{type(exc).__name__}: {exc}"
    return pipe, error


def summary(pipe, error):
    stats = {node: (s.ticks, s.steps, s.skips, s.errors) for node, s in pipe.stats().items()}
    return records(pipe.trace), stats, error


def outcome(build, runs, **options):
    """Run ``build()``'s pipeline in the increments ``runs``; the records, stats, and error if any."""
    return summary(*ran(build, runs, **options))


def assert_same(build, runs=(1.0,), min_compiled=1, **options):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RetrieverWarning)
        pipe, error = ran(build, runs, **options)
        compiled = pipe.session.generated_ticks()
        fast = summary(pipe, error)
        pipe, error = ran(build, runs, generate_ticks=False, **options)
        assert pipe.session.generated_ticks() == frozenset()
        generic = summary(pipe, error)
    assert len(compiled) >= min_compiled, f"only {sorted(compiled)} compiled"
    assert fast[2] == generic[2]
    assert fast[1] == generic[1]
    (fast_events, fast_steps), (events, steps) = fast[0], generic[0]
    assert len(fast_steps) == len(steps) and len(fast_events) == len(events)
    for a, b in zip(fast_steps, steps):
        assert a == b
    for a, b in zip(fast_events, events):
        assert a == b
    return fast


# ---------------------------------------------------------------------------------------------
# Flows that take every route through a compiled tick
# ---------------------------------------------------------------------------------------------
@io
@dataclass
class Num:
    x: Any


@io
@dataclass
class Two:
    a: Any = None
    b: Any = None


@io
@dataclass
class ReqOpt:
    a: Any
    b: Optional[Any]


@io
@dataclass
class WithUnfed:
    a: Any
    extra: Optional[Any]


class Count(Flow[None, Num]):
    """k, with no event every ``sparse``-th tick, a dict every ``as_dict``-th, None every ``none``-th."""

    def __init__(self, sparse: int = 0, as_dict: int = 0, none: int = 0, fail: int = 0):
        self.sparse, self.as_dict, self.none, self.fail, self.k = sparse, as_dict, none, fail, 0

    def step(self) -> Num:
        self.k += 1
        if self.fail and self.k % self.fail == 0:
            raise ValueError(f"fail at {self.k}")
        if self.none and self.k % self.none == 0:
            return None
        if self.as_dict and self.k % self.as_dict == 0:
            return {"x": -self.k}
        return Num(None if self.sparse and self.k % self.sparse == 0 else self.k)


class Split(Flow[Num, Two]):
    def step(self, inp: Num) -> Two:
        return Two(a=inp.x, b=None if inp.x % 3 == 0 else inp.x * 10)


class Join(Flow[ReqOpt, Num]):
    def step(self, inp: ReqOpt) -> Num:
        return Num((inp.a, inp.b))


class UsesUnfed(Flow[WithUnfed, Num]):
    def step(self, inp: WithUnfed) -> Num:
        return Num((inp.a, inp.extra))


class Plain(Flow[int, int]):
    """One typed port in, one out (not @io)."""

    def step(self, x: int) -> int:
        return x + 1


class Relay(Flow[Num, Num]):
    def step(self, inp: Num) -> Num:
        return Num(inp.x)


class Both(Flow[Two, Num]):
    def step(self, inp: Two) -> Num:
        return Num((inp.a, inp.b))


class Untyped(Flow):
    def step(self, x, y=7, z: Optional[int] = None):
        if isinstance(x, int) and x % 5 == 0:
            return None
        return {"out": (x, y, z), "side": None if isinstance(x, int) and x % 2 else x, "unwired": 1}


class UntypedSource(Flow):
    def __init__(self):
        self.k = 0

    def step(self):
        self.k += 1
        return {"x": self.k}


def chain(variant: str):
    def build():
        with Pipeline(f"chain_{variant}") as pipe:
            if variant == "typed":
                prev = Count().named("src") @ Rate(1000)
                for i in range(1, 4):
                    prev = prev.then(Join().named(f"s{i}") @ Rate(1000), map={"x": "a"}, sync=Latest())
            else:
                prev = UntypedSource().named("src") @ Rate(1000)
                for i in range(1, 4):  # the source's port is "x", each Untyped's "out"
                    prev = prev.then(Untyped().named(f"s{i}") @ Rate(1000), map={"x" if i == 1 else "out": "x"},
                                     sync=Latest())
        return pipe
    return build


def mixed():
    """Fan-in, multi-output, optional and unfed ports, typed single ports, latency, delays,
    triggers in microsteps, Hybrid clocks, outputs of another type, errors that continue."""
    with Pipeline("mixed") as pipe:
        a = Count(sparse=4, as_dict=7, none=11).named("a") @ Rate(100)
        b = Count(sparse=3).named("b").configure(latency=0.004) @ Rate(30, offset=0.002)
        split = Split().named("split") @ Trigger()
        join = Join().named("join") @ Rate(100)
        join2 = Join().named("join2") @ Hybrid(50, trigger=["a"])
        unfed = UsesUnfed().named("unfed") @ Rate(40)
        both = Both().named("both") @ Trigger("b")
        plain_src = Count().named("psrc").configure(on_error="skip_tick") @ Rate(60)
        plain = Plain().named("plain") @ Trigger()
        plain2 = Plain().named("plain2") @ Rate(60)
        u = Untyped().named("u") @ Rate(100)
        u2 = Untyped().named("u2") @ Trigger()
        flaky = Count(fail=5).named("flaky").configure(on_error="skip_tick") @ Rate(100)
        pipe.connect(a, split, map={"x": "x"}, sync=Latest())
        pipe.connect(split, join, map={"a": "a"}, sync=Latest())
        pipe.connect(split, join, map={"b": "b"}, sync=Latest(), delay=0.01)
        pipe.connect(b, join2, map={"x": "a"}, sync=Latest())
        pipe.connect(a, join2, map={"x": "a"}, sync=Latest())  # fan-in: two producers, one port
        pipe.connect(flaky, join2, map={"x": "b"}, sync=Latest(), delay=0.003)
        pipe.connect(join, unfed, map={"x": "a"}, sync=Latest())
        pipe.connect(split, both, map={"a": "a", "b": "b"}, sync=Latest())
        pipe.connect(plain_src, plain, map={"x": "int"}, sync=Latest())
        pipe.connect(plain, plain2, map={"int": "int"}, sync=Latest())
        pipe.connect(a, u, map={"x": "x"}, sync=Latest())
        pipe.connect(u, u2, map={"out": "x"}, sync=Latest())
        pipe.connect(u, u2, map={"side": "y"}, sync=Latest(), delay=0.005)
    return pipe


def test_chains_compile_every_node_and_match():
    for variant in ("typed", "untyped"):
        assert_same(chain(variant), runs=(0.2, 0.0005, 0.3), min_compiled=4)


def test_mixed_graph_matches():
    assert_same(mixed, runs=(0.5, 0.25, 0.25), min_compiled=10)


def one_group_consumers_first():
    """One Rate schedule, so every tick is the fused group's: each join runs before the counts
    that feed it (consumers first), and sees on each edge only what is visible at its tick."""
    with Pipeline("one_group") as pipe:
        plain = Join().named("plain") @ Rate(100)  # a: undelayed, no latency: every entry is visible
        late = Join().named("late") @ Rate(100)  # a: from a producer whose outputs land 1.5 ticks on
        delayed = Join().named("delayed") @ Rate(100)  # a: an edge delayed by 1.5 ticks
        fan = Join().named("fan") @ Rate(100)  # a: fed by two producers, one of them late
        src = Count().named("src") @ Rate(100)
        let = Count().named("let").configure(latency=0.015) @ Rate(100)
        pipe.connect(src, plain, map={"x": "a"}, sync=Latest())
        pipe.connect(let, late, map={"x": "a"}, sync=Latest())
        pipe.connect(src, delayed, map={"x": "a"}, sync=Latest(), delay=0.015)
        pipe.connect(src, fan, map={"x": "a"}, sync=Latest())
        pipe.connect(let, fan, map={"x": "a"}, sync=Latest())
        # a cycle: no order puts each before its producer, so c2 runs after c1 and must not see
        # c1's output of the same tick
        c1, c2 = Join().named("c1") @ Rate(100), Join().named("c2") @ Rate(100)
        pipe.connect(src, c1, map={"x": "a"}, sync=Latest())
        pipe.connect(c1, c2, map={"x": "a"}, sync=Latest())
        pipe.connect(c2, c1, map={"x": "b"}, sync=Latest())
    return pipe


def test_a_fused_group_run_consumers_first_sees_what_the_generic_path_sees():
    session = InprocSession(one_group_consumers_first().compile())
    order = list(session.tick_order()[0])
    assert order.index("plain") < order.index("src") and order.index("late") < order.index("let")
    assert order.index("fan") < order.index("src") and order.index("fan") < order.index("let"), order
    assert order.index("c1") < order.index("c2"), order
    assert_same(one_group_consumers_first, runs=(0.2, 0.05, 0.1), min_compiled=6)


def test_mixed_graph_matches_under_tie_breaking():
    for seed in (0, 1, 7):
        assert_same(mixed, tie_break_seed=seed, min_compiled=10)


class Values(Flow[None, Num]):
    """Each tick's value the next of ``VALUES`` (every msgpack form an int takes, floats, others)."""

    VALUES = [0, 1, 127, 128, 255, 256, 65535, 65536, 2**32 - 1, 2**32, 2**64 - 1, 2**70, -1, -32, -33, -129,
              -2**31, -2**63, 1.5, -0.0, float("inf"), float("nan"), 1e300, True, False, "s", b"b", [1], None]

    def __init__(self):
        self.k = -1

    def step(self) -> Num:
        self.k += 1
        return Num(self.VALUES[self.k % len(self.VALUES)])


def logged_records(build, runs):
    """Run ``build()`` for ``runs`` with the log's records made as the tape is expanded
    (Trace.log_records: heads of channel 42 for step records, 7 for every port's events), as a
    writer takes them: ``(pipe, step records, event records)``, each None where none was made."""
    from retriever.log.mcap_records import MESSAGE_FIELDS, MESSAGE_HEAD

    def fixed(size, channel):
        return MESSAGE_HEAD.pack(5, MESSAGE_FIELDS + size, channel, 0, 0, 0)[:11]

    pipe = build()
    pipe.step(0.0)
    trace = pipe.session.trace
    trace.log_records(struct.Struct("<11sIQQ").pack, lambda size: fixed(size, 42),
                      lambda node, port: tuple(fixed(size, 7) for size in range(12)),
                      lambda data_format: struct.Struct("<11sIQQ" + data_format).pack)
    steps: list = []
    events: list = []
    for duration in runs:
        pipe.run(duration=duration)
        made, first, n_steps, made_events, first_event, n_events = trace.take_log(0, 0)
        assert first == len(steps) and n_steps == len(steps) + len(made) == len(trace.raw_steps)
        assert first_event == len(events) and n_events == len(events) + len(made_events) == len(trace.raw_events)
        steps += made
        events += made_events
    trace.stop_log()
    return pipe, steps, events


def test_the_step_records_compiled_ticks_make_for_the_log_are_the_writers():
    """What an expander makes for the log (Trace.log_records) of each step record it expands: where
    it makes one, the Message record of the step with the head the writer gives it and data that
    decode to the step's fields; where it does not (another shape, a plain record), None, for the
    writer. Made for the steps of a chain of plain ints (all but its first skipped ticks), for
    some of the mixed graph's."""
    from retriever.log.format import decode_step
    from retriever.log.mcap_records import MESSAGE_HEAD

    def plain_chain():
        with Pipeline("plain_chain") as pipe:
            prev = Count().named("src") @ Rate(1000)
            for i, clock in enumerate([Trigger(), Rate(1000), Trigger()]):
                prev = prev.then(Plain().named(f"p{i}") @ clock, map={"x" if i == 0 else "int": "int"},
                                 sync=Latest())
        return pipe

    # (the last graph's cycle nests its values deeper than a log takes: not logged)
    for build, runs, least, logged in ((plain_chain, (0.2, 0.0005, 0.3), 0.99, True), (mixed, (0.5, 0.25), 0.1, True),
                                       (one_group_consumers_first, (0.3,), 0.1, False)):
        pipe, made, _ = logged_records(build, runs)
        trace = pipe.session.trace
        assert len(made) == len(trace.raw_steps) > 100
        assert sum(record is not None for record in made) >= least * len(made)
        for index, (record, step) in enumerate(zip(made, trace.raw_steps)):
            if record is None:
                continue
            node, tag, consumed, produced, status, detail, start, wall = step
            op, length, channel, sequence, log_time, publish = MESSAGE_HEAD.unpack_from(record)
            assert (op, length, channel, sequence, log_time, publish) == (
                5, len(record) - 9, 42, index, tag[0], start)
            assert decode_step(record[MESSAGE_HEAD.size:]) == (node, tag[1], consumed, produced, status, detail, wall)
        assert not logged or read_steps_equal(build)


def test_the_event_records_compiled_ticks_make_for_the_log_are_the_writers():
    """What an expander makes for the log (Trace.log_records) of each event it expands: where it
    makes one (a float, an int from 0 to 2**32 - 1, a microstep below 128), byte for byte the record
    the writer makes of any event, the head and the codec's ``[microstep, value]``; None for every
    other (another value, an event of a plain record, a node of two outputs), for the writer. Every
    kind of value, at microsteps past 127 too (a chain of Trigger flows), and the mixed graph's."""
    from retriever.codec import Encoder
    from retriever.log.mcap_records import MESSAGE_FIELDS, MESSAGE_HEAD

    def values():
        with Pipeline("values") as pipe:
            prev = Values().named("src") @ Rate(1000)
            for i in range(3):
                prev = prev.then(Relay().named(f"r{i}") @ Rate(1000), sync=Latest())
        return pipe

    def long_trigger_chain():
        with Pipeline("long") as pipe:
            prev = Values().named("src") @ Rate(100)
            for i in range(140):
                prev = prev.then(Relay().named(f"t{i:03}") @ Trigger(), sync=Latest())
        return pipe

    encode = Encoder().pack
    for build, runs, least, at_most in ((values, (0.2, 0.0005, 0.3), 0.45, 0.55), (long_trigger_chain, (0.05,), 0.4, 0.98),
                                        (mixed, (0.5, 0.25), 0.2, 0.99)):
        pipe, _, made = logged_records(build, runs)
        trace = pipe.session.trace
        assert len(made) == len(trace.raw_events) > 100
        assert least * len(made) <= sum(record is not None for record in made) <= at_most * len(made)
        ports: dict[str, set] = {}
        for _, node, port, *_ in trace.raw_events:
            ports.setdefault(node, set()).add(port)
        for record, (tag, node, port, seq, value, published) in zip(made, trace.raw_events):
            if record is not None:
                data = encode([tag[1], value])
                assert record == MESSAGE_HEAD.pack(5, MESSAGE_FIELDS + len(data), 7, seq, tag[0], published) + data
            else:
                assert (tag[1] >= 128 or type(value) not in (int, float) or not 0 <= value < 2**32
                        or len(ports[node]) > 1), (node, tag, value)
        assert any(tag[1] >= 128 for tag, *_ in trace.raw_events) == (build is long_trigger_chain)


def read_steps_equal(build) -> bool:
    """A logged run of ``build()`` reads back as its trace (its records made as above)."""
    import tempfile
    from pathlib import Path

    from retriever import read_log

    with tempfile.TemporaryDirectory() as folder:
        again = build()
        trace = again.run(duration=0.5, log=Path(folder) / "run.mcap")
        return read_log(Path(folder) / "run.mcap").trace() == trace


def test_stop_on_error_matches():
    def build():
        with Pipeline("stop") as pipe:
            src = Count(fail=13).named("src") @ Rate(100)
            src.then(Join().named("j") @ Rate(100), map={"x": "a"}, sync=Latest())
        return pipe

    fast = assert_same(build, min_compiled=2)
    assert fast[2].startswith(StepError.__name__)


class TwoUnencodable(Flow[Num, Two]):
    def step(self, inp: Num) -> Two:
        return Two(a=[inp.x], b={inp.x} if inp.x == 5 else (inp.x,))


class OneUnencodable(Flow[int, int]):
    def step(self, x: int) -> int:
        return {x} if x == 5 else x


class UntypedUnencodable(Flow):
    def step(self, x):
        return {"out": [x], "side": {x} if x == 5 else {"k": x}}


@pytest.mark.parametrize("flow, ports", [(TwoUnencodable, {"x": "x"}), (OneUnencodable, {"x": "int"}),
                                         (UntypedUnencodable, {"x": "x"})], ids=["io", "single", "untyped"])
def test_an_unencodable_output_stops_both_paths_alike(flow, ports):
    """The compiled ticks check outputs not of a plain type before recording them, as _emit does."""
    def build():
        with Pipeline("unencodable") as pipe:
            src = Count().named("src") @ Rate(100)
            pipe.connect(src, flow().named("f") @ Rate(100), map=ports, sync=Latest())
        return pipe

    fast = assert_same(build, min_compiled=2)
    assert fast[2].startswith("CodecError: f.") and "the step at t=0.050000000s m=0 returned a value" in fast[2]
    assert fast[0][1][-1][4] == "error"


class Exits(Flow[Num, Num]):
    def step(self, inp: Num) -> Num:
        if inp.x % 4 == 0:
            raise SystemExit(inp.x)
        return Num(inp.x)


@pytest.mark.parametrize("on_error", ["stop", "skip_tick"])
def test_sys_exit_in_a_step_is_its_error_on_both_paths(on_error):
    def build():
        with Pipeline("exits") as pipe:
            src = Count().named("src") @ Rate(100)
            src.then(Exits().named("e").configure(on_error=on_error) @ Rate(100), map={"x": "x"}, sync=Latest())
        return pipe

    fast = assert_same(build, min_compiled=2)
    if on_error == "stop":
        assert fast[2].startswith("StepError: e.step() raised SystemExit: 4")
    else:
        assert fast[2] is None and fast[1]["e"][3] == 24


def test_reset_then_run_repeats_the_trace():
    pipe = mixed()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RetrieverWarning)
        first = records(pipe.run(duration=0.3))
        pipe.reset()
        again = records(pipe.run(duration=0.3))
    assert first == again


@SETTINGS
@given(spec=graphs())
def test_random_graphs_match(spec):
    """The random multi-rate graphs of the schedule-independence properties (Mix/Need flows
    with Latest edges compile; every other policy stays generic), compiled vs generic."""
    def build():
        return spec.build()

    def run_in_budget(**options):
        with budget():
            return outcome(build, (DURATION,), **options)

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RetrieverWarning)
        fast = run_in_budget()
        generic = run_in_budget(generate_ticks=False)
    assert fast == generic


def test_a_tick_between_runs_keeps_seqs_unique():
    """session.tick() (the replay hook) runs the generic path between two runs of compiled ticks."""
    def ids(pipe):
        return [e[1:4] for e in pipe.trace.raw_events]

    results = []
    for options in ({}, {"generate_ticks": False}):
        pipe = chain("typed")()
        pipe.run(duration=0.01, **options)
        session = pipe.session
        session.tick("src", (pipe.trace.raw_steps[-1][1][0], 5))
        pipe.run(duration=0.01)
        results.append((records(pipe.trace), {n: vars(s) | {"step_ns": 0} for n, s in pipe.stats().items()}))
        assert len(set(ids(pipe))) == len(ids(pipe))
    assert results[0] == results[1]


class Ping(Flow[Num, Num]):
    def step(self, inp: Num) -> Num:
        return Num(inp.x + 1)


def assert_same_going_on(build, runs=(0.1, 0.1)):
    """Run ``build()``'s pipeline in the increments ``runs``, going on after each error, with the
    compiled ticks and with the generic ones: the same records, stats and errors."""
    def going_on(**options):
        pipe, errors = build(), []
        pipe.open(**options)
        for duration in runs:
            try:
                pipe.run(duration=duration)
            except Exception as exc:  # noqa: BLE001 - compared below
                errors.append(f"{type(exc).__name__}: {exc}")
        stats = {node: (s.ticks, s.steps, s.skips, s.errors) for node, s in pipe.stats().items()}
        return (records(pipe.trace), stats, errors), pipe.session.generated_ticks()

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RetrieverWarning)
        fast, compiled = going_on()
        generic, _ = going_on(generate_ticks=False)
    assert set(compiled) == set(fast[1]) and fast == generic
    return fast


def test_a_zeno_cycle_stops_both_paths_alike():
    """Two Trigger flows in an instantaneous cycle, one fed by two edges (fan-in): past
    max_microsteps the run stops with a CausalityError at the same record on both paths, and
    the next run stops so again."""
    def build():
        with Pipeline("zeno", max_microsteps=20) as pipe:
            kick = Count().named("kick") @ Rate(10)
            a, b = Ping().named("a") @ Trigger(), Ping().named("b") @ Trigger()
            pipe.connect(kick, a, sync=Latest())
            pipe.connect(a, b, sync=Latest())
            pipe.connect(b, a, sync=Latest())
        return pipe

    fast = assert_same_going_on(build, runs=(0.1, 0.25))
    assert [e.split(":")[0] for e in fast[2]] == ["CausalityError", "CausalityError"]


class FailsAt(Flow[Num, Num]):
    def step(self, inp: Num) -> Num:
        if inp.x == 7:
            raise ValueError("seven")
        return Num(inp.x)


def test_a_run_goes_on_after_an_error_between_microsteps_alike():
    """A step that stops the run at microstep 1, after another tick there triggered one at
    microstep 2: the next run starts with that tick, on both paths."""
    def build():
        with Pipeline("cascade") as pipe:
            src = Count().named("src") @ Rate(100)
            a, z = Ping().named("a") @ Trigger(), FailsAt().named("z") @ Trigger()
            pipe.connect(src, a, sync=Latest())
            pipe.connect(src, z, sync=Latest())
            pipe.connect(a, Ping().named("b") @ Trigger(), sync=Latest())
        return pipe

    fast = assert_same_going_on(build)
    # at every tick: the second run went on from the error's 0.06 s for 0.1 s, to 0.16 s
    assert len(fast[2]) == 1 and fast[1]["b"][1] == 16
    assert ("b", (60_000_000, 2)) in [s[:2] for s in fast[0][1]]  # triggered before the error at (0.06 s, 1)


def test_a_chain_of_trigger_flows_matches():
    """A Rate source and Trigger flows, each triggering the next: one function runs the chain
    while each tick is the only one due; a flow also triggered from elsewhere, an empty output,
    an error in the middle of the chain and a flow of the chain fed by a delayed edge break it."""
    def build():
        with Pipeline("chain") as pipe:
            prev = Count(none=5).named("src") @ Rate(100)
            for name in ("c1", "c2", "c3", "c4"):
                flow = (FailsAt() if name == "c3" else Ping()).named(name).configure(on_error="skip_tick")
                prev = prev.then(flow @ Trigger(), sync=Latest())
            side = Count(sparse=3).named("side") @ Rate(50, offset=0.01)
            pipe.connect(side, pipe.flows[2], sync=Latest(), map={"x": "x"})  # c2, also from side,
            pipe.connect(side, pipe.flows[4], sync=Latest(), map={"x": "x"}, delay=0.02)  # and c4, later
        return pipe

    assert_same(build, runs=(0.3, 0.2), min_compiled=6)



@io
@dataclass
class Trio:
    a: Any
    b: Optional[Any]
    c: Optional[Any]


class Three(Flow[Trio, Num]):
    def step(self, inp: Trio) -> Num:
        if inp.a == 8:
            raise ValueError("eight")
        return Num((inp.a, inp.b, inp.c))


@pytest.mark.parametrize("on_error", ["skip_tick", "stop"])
def test_a_lone_group_and_the_chain_it_triggers_match(on_error):
    """A rate group with nothing else due runs its ticks back to back and the chain of Trigger
    flows it triggers inline; a chain's links skip the visibility test on every input one
    producer alone feeds (each runs as the only tick at its tag). Here a link also reads a flow
    of the group (events at the microstep the chain starts at) and a flow on another schedule
    (the group is alone only between its ticks), events have gaps, the head fails at one tick
    (under stop, the runs go on after it) and a link after it at another."""
    def build():
        with Pipeline("lone") as pipe:
            src = Count(none=5).named("src") @ Rate(100)
            mate = Count(sparse=3).named("mate") @ Rate(100)
            slow = Count().named("slow") @ Rate(30, offset=0.002)
            head = src.then(FailsAt().named("c1").configure(on_error=on_error) @ Trigger(), sync=Latest())
            three = head.then(Three().named("c2").configure(on_error=on_error) @ Trigger("a"), map={"x": "a"},
                              sync=Latest())
            pipe.connect(mate, three, map={"x": "b"}, sync=Latest())
            pipe.connect(slow, three, map={"x": "c"}, sync=Latest())
            three.then(Join().named("c3") @ Trigger(), map={"x": "a"}, sync=Latest())
        return pipe

    fast = assert_same_going_on(build, runs=(0.05, 0.1, 0.1, 0.1))
    assert [e.split(":")[0] for e in fast[2]] == (["StepError"] * 2 if on_error == "stop" else [])
    c2 = [s for s in fast[0][1] if s[0] == "c2" and s[4] == "ok"]
    assert len(c2) > 8 and {s[1][1] for s in c2} == {2}  # at the microstep after c1's
    assert {"b", "c"} <= {port for s in c2 for port in s[2]}



def test_a_lone_group_that_fails_after_triggering_a_chain_goes_on_with_it():
    """A flow of a lone rate group fails (under stop) after another of the group triggered the
    chain that follows: the next run starts with that chain's tick, on both paths."""
    def build():
        with Pipeline("lone_fails") as pipe:
            src = Count().named("src") @ Rate(100)
            Count(fail=4).named("zfails") @ Rate(100)  # after src in the group's order (by name)
            src.then(Ping().named("c1") @ Trigger(), sync=Latest()).then(Ping().named("c2") @ Trigger(), sync=Latest())
        return pipe

    fast = assert_same_going_on(build, runs=(0.1, 0.1))
    assert [e.split(":")[0] for e in fast[2]] == ["StepError"] * 2  # (at its 4th tick and its 8th)
    assert ("c1", (30_000_000, 1)) in [s[:2] for s in fast[0][1]]  # src's fourth tick triggered it, and zfails failed



@pytest.mark.parametrize("on_error", ["skip_tick", "stop"])
def test_a_lone_group_runs_its_chain_only_at_the_ticks_that_trigger_it(on_error):
    """A lone group's node triggers the chain's head at every other tick, another node triggers
    two more flows at every tick (so the chain's head waits with them, and the loop leaves the
    chain); one of those fails now and then: the head runs at the ticks that trigger it, no
    others, and after a failure the run goes on from where it was (found by a fuzz of a review:
    the loop kept the head to run from one tick to the next)."""
    def build():
        with Pipeline("lone_two") as pipe:
            a = Count(none=2).named("a") @ Rate(100)
            b = Count().named("b") @ Rate(100)
            a.then(Ping().named("h") @ Trigger(), sync=Latest()).then(Ping().named("h2") @ Trigger(), sync=Latest())
            b.then(Ping().named("x") @ Trigger(), sync=Latest())
            b.then(FailsAt().named("y").configure(on_error=on_error) @ Trigger(), sync=Latest())
        return pipe

    fast = assert_same_going_on(build, runs=(0.05, 0.1, 0.1))
    h = [s[1] for s in fast[0][1] if s[0] == "h"]
    at = [(t * 10_000_000, 1) for t in range(0, 25, 2)]  # a's ticks with an event
    if on_error == "skip_tick":
        assert h == at
    else:  # the second run stopped at y's failure, at 60 ms; the third went on
        assert set(h) <= set(at) and (60_000_000, 1) in h and (80_000_000, 1) in h


class Interrupts(Flow[Num, Num]):
    """Raises KeyboardInterrupt at its third step (as a Ctrl-C there would)."""

    def __init__(self):
        self.n = 0

    def step(self, inp: Num) -> Num:
        self.n += 1
        if self.n == 3:
            raise KeyboardInterrupt
        return Num(inp.x)


def test_a_step_interrupted_by_ctrl_c_counts_its_tick_on_both_paths():
    """A Ctrl-C in a compiled chain link's step: the run stops there, and the interrupted tick
    is counted, as the generic path counts it (its stats differed)."""
    def going_on(**options):
        with Pipeline("interrupted") as pipe:
            prev = Count().named("src") @ Rate(100)
            for name in ("c1", "c2", "c3"):
                prev = prev.then((Interrupts() if name == "c2" else Ping()).named(name) @ Trigger(), sync=Latest())
        pipe.open(**options)
        stopped = []
        for duration in (0.1, 0.1):
            try:
                pipe.run(duration=duration)
            except KeyboardInterrupt:
                stopped.append(duration)
        stats = {node: (s.ticks, s.steps, s.skips, s.errors) for node, s in pipe.stats().items()}
        return records(pipe.trace), stats, stopped

    fast = going_on()
    generic = going_on(generate_ticks=False)
    assert fast == generic and fast[2] == [0.1]
    ticks, steps, _, _ = fast[1]["c2"]
    assert ticks == steps + 1  # the interrupted one


def test_stats_read_from_another_thread_while_a_run_goes_on_change_nothing_it_records():
    """pipe.stats() polled from another thread during a background run, whose compiled ticks take
    the generic path at every step (outputs of a type the codec must look at): every event id is
    issued once, and the trace and the counts are those of a run nobody watched (a flush from
    that thread used to write a tick's stale seq over the one emit had just counted on)."""
    def build():
        with Pipeline("watched") as pipe:
            prev = Count().named("src") @ Rate(1000)
            for i in range(4):
                prev = prev.then(Join().named(f"c{i}") @ Trigger(), map={"x": "a"}, sync=Latest())
        return pipe

    watched = build()
    handle = watched.run(duration=3, blocking=False)
    polls = 0
    while not handle.done:
        watched.stats()
        polls += 1
    handle.wait()
    alone = build()
    alone.run(duration=3)
    ids = [e[1:4] for e in watched.trace.raw_events]
    assert polls > 1 and len(ids) == len(set(ids)) == 15_000
    assert records(watched.trace) == records(alone.trace)
    assert ({n: (s.ticks, s.steps) for n, s in watched.stats().items()}
            == {n: (s.ticks, s.steps) for n, s in alone.stats().items()})



def test_stats_read_during_a_long_step_count_what_ran_so_far(monkeypatch):
    """pipe.stats() from another thread while the run's thread is in a long step (the loop does
    not come round to flush within FLUSH_WAIT_S): the counts as of now, in copies; and a step
    that reads pipe.stats() in the run's own thread gets them so too, changing nothing the run
    records or counts."""
    monkeypatch.setattr(InprocSession, "FLUSH_WAIT_S", 0.0)
    reached, release, seen = threading.Event(), threading.Event(), []

    class Blocks(Flow[Num, Num]):
        def step(self, inp: Num) -> Num:
            if inp.x == 500:
                reached.set()
                release.wait(60)
            if inp.x % 100 == 0:
                seen.append(pipe.stats()["src"].steps)  # in the run's thread
            return Num(inp.x)

    def build():
        with Pipeline("long_step") as built:
            (Count().named("src") @ Rate(1000)).then(Blocks().named("b") @ Trigger(), sync=Latest())
        return built

    pipe = build()
    handle = pipe.run(duration=1, blocking=False)
    assert reached.wait(60)
    during = pipe.stats()
    release.set()
    handle.wait()
    assert (during["src"].steps, during["b"].steps) == (500, 499)
    assert seen == list(range(100, 1001, 100))
    alone = build()
    Blocks.step, plain = (lambda self, inp: Num(inp.x)), Blocks.step
    alone.run(duration=1)
    Blocks.step = plain
    assert records(pipe.trace) == records(alone.trace)
    assert ({n: (s.ticks, s.steps) for n, s in pipe.stats().items()}
            == {n: (s.ticks, s.steps) for n, s in alone.stats().items()} == {"src": (1000, 1000), "b": (1000, 1000)})


def test_each_compiled_step_records_when_it_ran():
    """The wall-clock fields, which traces do not compare: every step of a lone group and its
    chain (whose links keep short records: their start is the record's before) ran within the
    run, and each step of a tick and its chain started when the one before it ended."""
    with Pipeline("when") as pipe:
        prev = Count().named("src") @ Rate(100)
        for name in ("c1", "c2", "c3"):
            prev = prev.then(Ping().named(name) @ Trigger(), sync=Latest())
    before = time.time_ns()
    pipe.run(duration=0.2)
    after = time.time_ns()
    steps = pipe.trace.steps
    assert len(steps) == 4 * 20
    for step in steps:
        assert before <= step.wall_start_ns and step.wall_ns >= 0 and step.wall_start_ns + step.wall_ns <= after
    for tick in zip(*[iter(steps)] * 4):
        assert [s.node for s in tick] == ["src", "c1", "c2", "c3"] and {s.tag[0] for s in tick} == {tick[0].tag[0]}
        for one, then in zip(tick, tick[1:]):
            assert then.wall_start_ns == one.wall_start_ns + one.wall_ns


class Reordered(Flow):
    """Its parameters in another order than its edges are declared in: called by position, in its own order."""

    def step(self, b, a):
        return {"d": (a, b)}


class KeywordOnly(Flow):
    def step(self, *, a, b=0):
        return {"d": (a, b)}


def _keywords_only(claim):
    """A decorator whose wrapper takes only keywords and says it takes what the step takes:
    through functools.wraps (``__wrapped__``), or with a ``__signature__`` of its own."""
    def decorate(step):
        def wrapper(self, **values):
            return step(self, **values)
        if claim == "wraps":
            return functools.wraps(step)(wrapper)
        wrapper.__signature__ = inspect.signature(step)
        return wrapper
    return decorate


class Wrapped(Flow):
    @_keywords_only("wraps")
    def step(self, a, b):
        return {"d": (a, b)}


class ClaimsASignature(Flow):
    @_keywords_only("__signature__")
    def step(self, a, b):
        return {"d": (a, b)}


class StepOnTheInstance(Flow):
    """Its class says step(self, a, b); the step it has is another, with its parameters swapped."""

    def __init__(self):
        self.step = lambda b, a: {"d": (a, b)}

    def step(self, a, b):
        raise AssertionError("not this one")


class Pair(Flow):
    def __init__(self):
        self.k = 0

    def step(self):
        self.k += 1
        return {"a": self.k, "b": -self.k}


@pytest.mark.parametrize("flow", [Reordered, KeywordOnly, Wrapped, ClaimsASignature, StepOnTheInstance])
def test_an_untyped_step_gets_each_input_by_its_name_on_both_paths(flow):
    """The compiled tick passes inputs by position only where step() takes them so, in its own order:
    not to a keyword-only parameter, nor through a wrapper that takes only keywords (whatever
    signature it claims), nor to a step set on the instance (its class's signature is not its own)."""
    def build():
        with Pipeline(f"names_{flow.__name__}") as pipe:
            src = Pair().named("src") @ Rate(100)
            pipe.connect(src, flow().named("sink") @ Trigger(), map={"a": "a"}, sync=Latest())
            pipe.connect(src, pipe.flows[1], map={"b": "b"}, sync=Latest())
        return pipe

    (events, _), _, error = assert_same(build, runs=(0.1,), min_compiled=2)
    assert error is None
    assert [e[4] for e in events if e[1] == "sink"] == [(k, -k) for k in range(1, 11)]
