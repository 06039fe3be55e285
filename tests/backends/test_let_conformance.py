"""Conformance in real time: graphs whose flows all declare latency (LET) give, on every backend,
the trace of the in-process reference (docs/realtime.md: "with LET flows and no incomplete edges, a
real-time run is as deterministic as a virtual-time run").

Each test builds one LET graph covering a part of §3–§4 — every clock, every policy, the MISSING
rules, delay, fan-in, sparse outputs, a cycle — runs it for one second on each backend, checks the
invariants every trace satisfies, and on real-time backends compares with ``inproc``. Deadlines
are generous (real-time ticks wait for complete inputs, so a slow machine makes the run late,
never different). Rates stay ≤ 20 Hz and latencies ≥ 5 ms, so a loaded 2-core machine keeps up.
"""

import pytest

from retriever import (
    ActionChunking, Exact, Hybrid, Latest, LatestDistinct, Pipeline, Queue, Rate, Trigger, Window,
)

from .test_conformance import (
    BurstRecorder, BurstSource, ChunkSource, CycleMonitor, CyclePolicy, Echo, EchoOpt, MissingRecorder, PairEcho,
    PairSource, Restartable, SkipRecorder, Source, SparseSource, UntypedSparse, WindowQueueRecorder,
)

# "dora-grouped": dora with the flows in two processes, alternately (configure(process=)): a group
# is one dora node; edges between its members stay in its process, the others go over dora.
REALTIME_BACKENDS = ["inproc", "zenoh", "dora", "dora-grouped"]
DURATION = 1.0
GENEROUS = 5.0  # seconds a tick may wait for its inputs


@pytest.fixture(params=REALTIME_BACKENDS)
def rt_backend(request) -> str:
    return request.param


def run_on(build, backend, check_trace):
    """Run the graph ``build()`` returns on ``backend``; on a real-time backend, also on ``inproc``
    and require the identical trace."""
    pipe = build()
    grouped = backend.endswith("-grouped")
    if grouped:
        backend = backend.removesuffix("-grouped")
        processes = ["even", "odd"]
        for i, node in enumerate(pipe.compile().nodes.values()):
            node.flow.configure(process=processes[i % 2])
    options = {"quiet": True} if backend != "inproc" else {}
    trace = pipe.run(duration=DURATION, backend=backend, **options)
    if grouped:
        assert len(set(pipe.session.worker_pids().values())) == min(2, len(pipe.compile().nodes))
    check_trace(pipe, trace)
    assert trace.events and trace.steps
    if backend != "inproc":
        reference = build().run(duration=DURATION, backend="inproc")
        difference = trace.first_difference(reference)
        assert difference is None, f"{backend} differs from inproc: {difference}"
        assert trace.digest() == reference.digest()
    return trace


def let_pipeline(name):
    return Pipeline(name, deadline=GENEROUS)


def test_rate_trigger_hybrid_and_latest(rt_backend, check_trace):
    def build():
        with let_pipeline("clocks") as pipe:
            src = Source().named("src").configure(latency=0.01) @ Rate(20)
            echo = Echo().named("echo").configure(latency=0.005) @ Trigger("x")
            slow = EchoOpt().named("slow").configure(latency=0.02) @ Rate(10, offset=0.015)
            hybrid = EchoOpt().named("hybrid").configure(latency=0.005) @ Hybrid(5, trigger=["x"])
            src.then(echo, sync=Latest(), map={"value": "x"})
            echo.then(slow, sync=Latest(), map={"saw": "x"})
            src.then(hybrid, sync=Latest(), map={"value": "x"})
        return pipe

    trace = run_on(build, rt_backend, check_trace)
    assert len(trace.steps_of("echo")) == 20 and len(trace.steps_of("hybrid")) >= 20


def test_window_queue_and_latest_distinct(rt_backend, check_trace):
    def build():
        with let_pipeline("policies") as pipe:
            src = Source().named("src").configure(latency=0.005) @ Rate(20)
            rec = WindowQueueRecorder().named("rec").configure(latency=0.01) @ Rate(10, offset=0.003)
            src.then(rec, sync=Window(buffer_size=3), map={"value": "win"})
            src.then(rec, sync=Queue(maxsize=1), map={"value": "q"})
            src.then(rec, sync=Queue(), map={"value": "q_all"})
            slow = Source().named("slow").configure(latency=0.01) @ Rate(4)
            distinct = EchoOpt().named("distinct").configure(latency=0.005) @ Rate(20, offset=0.001)
            slow.then(distinct, sync=LatestDistinct(), map={"value": "x"})
        return pipe

    trace = run_on(build, rt_backend, check_trace)
    assert any((s.detail or {}).get("q") for s in trace.steps_of("rec"))  # Queue(maxsize=1) dropped some


def test_exact_and_window_duration(rt_backend, check_trace):
    def build():
        with let_pipeline("exact") as pipe:
            src = Source().named("src").configure(latency=0.1) @ Rate(10)  # events at (100k + 100 ms, 0)
            exact = EchoOpt().named("exact").configure(latency=0.005) @ Rate(20)
            near = EchoOpt().named("near").configure(latency=0.005) @ Rate(20, offset=0.01)
            src.then(exact, sync=Exact(), map={"value": "x"})
            src.then(near, sync=Exact(tolerance=0.02), map={"value": "x"})
        return pipe

    run_on(build, rt_backend, check_trace)


def test_bursts_and_their_consumers(rt_backend, check_trace):
    """A Burst is one message on a real-time backend: its events, ids and the policies' picks
    among events at one tag are those in-process; LET held outputs and a Trigger consumer too."""
    def build():
        with let_pipeline("bursts") as pipe:
            src = BurstSource(sizes=[3, 0, 1, 40]).named("src").configure(latency=0.01) @ Rate(20)
            rec = BurstRecorder().named("rec").configure(latency=0.005) @ Trigger("q")
            src.then(rec, sync=Queue(maxsize=30), map={"value": "q"})
            src.then(rec, sync=Latest(), map={"value": "last"})
            src.then(rec, sync=LatestDistinct(), map={"value": "distinct"})
            src.then(rec, sync=Window(buffer_size=2), map={"value": "win"})
            src.then(rec, sync=Exact(), map={"value": "exact"})
            late = EchoOpt().named("late").configure(latency=0.005) @ Rate(10, offset=0.003)
            src.then(late, sync=Queue(), map={"value": "x"})
        return pipe

    trace = run_on(build, rt_backend, check_trace)
    assert len(trace.events_of("src", "value")) == 5 * (3 + 1 + 40)
    assert any((s.detail or {}).get("q") == 10 for s in trace.steps_of("rec"))  # 40 at once, maxsize 30


def test_action_chunking(rt_backend, check_trace):
    def build():
        with let_pipeline("chunks") as pipe:
            policy = ChunkSource().named("policy").configure(latency=0.02) @ Rate(5)
            ctrl = Echo().named("ctrl").configure(latency=0.005) @ Rate(20, offset=0.001)
            policy.then(ctrl, sync=ActionChunking(control_hz=20, chunk_steps=8), map={"chunk": "x"})
        return pipe

    run_on(build, rt_backend, check_trace)


def test_missing_rules_skips_and_sparse_outputs(rt_backend, check_trace):
    def build():
        with let_pipeline("missing") as pipe:
            req = Source(only=[2, 3, 6, 7]).named("req").configure(latency=0.01) @ Rate(10)
            opt = Source(only=[4, 5]).named("opt").configure(latency=0.01) @ Rate(10, offset=0.002)
            rec = MissingRecorder().named("rec").configure(latency=0.005) @ Rate(10, offset=0.05)
            req.then(rec, sync=Latest(staleness=0.15), map={"value": "req"})
            opt.then(rec, sync=LatestDistinct(), map={"value": "opt"})
            img = Source(only=[1, 2, 5]).named("img").configure(latency=0.01) @ Rate(10)
            skip = SkipRecorder().named("skip").configure(latency=0.005) @ Rate(10, offset=0.03)
            img.then(skip, sync=Latest(staleness=0.05), map={"value": "img"})
            img.then(skip, sync=Queue(), map={"value": "q"})
            img.then(skip, sync=LatestDistinct(), map={"value": "ld"})
            sparse = SparseSource().named("sparse").configure(latency=0.01) @ Rate(10)
            on_even = Echo().named("on_even").configure(latency=0.005) @ Trigger("x")
            untyped = UntypedSparse().named("untyped").configure(latency=0.005) @ Trigger("value")
            on_odd = Echo().named("on_odd").configure(latency=0.005) @ Trigger("x")
            sparse.then(on_even, map={"even": "x"})
            sparse.then(untyped, map={"every": "value"})
            untyped.then(on_odd, map={"odd": "x"})
        return pipe

    trace = run_on(build, rt_backend, check_trace)
    assert any(s.status == "skipped" for s in trace.steps_of("rec"))
    assert any(s.status == "skipped" for s in trace.steps_of("skip"))


def test_delay_and_fan_in(rt_backend, check_trace):
    def build():
        with let_pipeline("delay_fan_in") as pipe:
            a = Source(prefix="a").named("a").configure(latency=0.01) @ Rate(10)
            b = Source(prefix="b").named("b").configure(latency=0.01) @ Rate(10, offset=0.05)
            merged = Echo().named("merged").configure(latency=0.005) @ Trigger("x")
            a.then(merged, sync=Queue(), map={"value": "x"})
            b.then(merged, sync=Queue(), map={"value": "x"})
            late = Echo().named("late").configure(latency=0.005) @ Trigger("x")
            a.then(late, sync=Latest(), map={"value": "x"}, delay=0.03)
            pair = PairSource().named("pair").configure(latency=0.01) @ Rate(10, offset=0.02)
            both = PairEcho().named("both").configure(latency=0.005) @ Rate(20, offset=0.004)
            pair.then(both, sync=Latest())
        return pipe

    trace = run_on(build, rt_backend, check_trace)
    assert [s.tag[0] for s in trace.steps_of("late")][:2] == [40_000_000, 140_000_000]


def test_cycle_through_latency(rt_backend, check_trace):
    def build():
        with let_pipeline("cycle") as pipe:
            monitor = CycleMonitor(limit=6).named("monitor").configure(latency=0.02) @ Trigger("fb")
            policy = CyclePolicy().named("policy").configure(latency=0.03) @ Trigger("skill")
            kick = Source(only=[0]).named("kick").configure(latency=0.01) @ Rate(2)
            kick.then(policy, sync=Latest(), map={"value": "skill"})
            monitor.then(policy, sync=Latest())
            policy.then(monitor, sync=Latest())
        return pipe

    trace = run_on(build, rt_backend, check_trace)
    assert trace.values_of("policy", "fb") == [1, 2, 3, 4, 5, 6]


def test_quickstart_shape_with_latency_everywhere(rt_backend, check_trace):
    """Camera → policy (action chunks) → controller → feedback to the policy, all LET."""
    def build():
        with let_pipeline("agent") as pipe:
            cam = Source().named("camera").configure(latency=0.01) @ Rate(20)
            policy = PairEcho().named("policy").configure(latency=0.1) @ Rate(4)
            ctrl = EchoOpt().named("controller").configure(latency=0.005) @ Rate(20, offset=0.002)
            cam.then(policy, sync=Latest(), map={"value": "a"})
            policy.then(ctrl, sync=Latest(), map={"saw": "x"})
            ctrl.then(policy, sync=Latest(), map={"saw": "b"})
        return pipe

    run_on(build, rt_backend, check_trace)


# Where the flow restarts in place (a fresh flow in its process, from the next tick: a group's on
# zenoh, any on dora, which starts its processes once). Not a lone flow on zenoh: a new process
# takes over, and the ticks while it starts are not run (tests/backends/zenoh/test_restart_afresh.py).
@pytest.mark.parametrize("backend", ["inproc", "zenoh-grouped", "dora", "dora-grouped"])
def test_on_error_restart_in_place(backend, check_trace):
    """§5 on_error="restart" in real time: the failing tick is recorded as "error", the flow goes on
    from its initial state from the next tick, and its consumer sees the same (inproc: reset();
    elsewhere a fresh flow rebuilt from the IR, set up in the flow's process)."""
    def build():
        with let_pipeline("let_restart") as pipe:
            r = Restartable(fail_on=3).named("r").configure(latency=0.01, on_error="restart") @ Rate(10)
            sink = EchoOpt().named("sink").configure(latency=0.005) @ Trigger("x")
            r.then(sink, sync=Latest(), map={"n": "x"})
            near = EchoOpt().named("near").configure(latency=0.005) @ Rate(20, offset=0.002)  # (grouped: r's neighbour)
            r.then(near, sync=Latest(), map={"n": "x"})
        return pipe

    trace = run_on(build, backend, check_trace)
    assert [s.status == "error" for s in trace.steps_of("r")] == [False, False, True] * 3 + [False]
    assert trace.values_of("r", "n") == [1, 2] * 3 + [1]
    assert trace.values_of("sink", "saw") == [1, 2] * 3 + [1]
