"""The coordinator ships the run's plan (retriever.plan) in every worker's spec, a worker daemon
forwards it, and each worker is wired as it says: the run's trace is the in-process one."""

from __future__ import annotations

import json
import warnings
from pathlib import Path

import zenoh

from retriever import Flow, Latest, Pipeline, Rate, RetrieverWarning, Trigger, Window
from retriever.backends.zenoh.command import WORKER_MODULE
from retriever.backends.zenoh.hub import peer_config
from retriever.backends.zenoh.daemon.runs import DaemonRuns
from retriever.plan import plan_graph

from ..test_conformance import CycleMonitor, CyclePolicy, Echo, Source, Value
from .specs import run_spec


class ShippedPlan(Flow[None, Value]):
    """At its first tick, the plan in its worker process's spec (the file its command line names:
    retriever.backends.zenoh.command), or a word saying it runs in no worker process."""

    def __init__(self):
        self.ticks = 0

    def step(self, inp: None) -> Value:
        self.ticks += 1
        if self.ticks > 1:
            return Value(None)
        args = Path("/proc/self/cmdline").read_bytes().split(b"\0")
        if WORKER_MODULE.encode() not in args:
            return Value("in no worker process")
        spec = json.loads(Path(args[args.index(WORKER_MODULE.encode()) + 1].decode()).read_text())
        return Value(spec.get("plan", "no plan in its spec"))


def wired() -> Pipeline:
    """A cycle broken by a delay, fan-in and a window: each a part of a node's plan."""
    with Pipeline("shipped") as pipe:
        ShippedPlan().named("shipped") @ Rate(10)
        kick = Source(only=[0, 2]).named("kick") @ Rate(5)
        monitor = CycleMonitor(limit=4).named("monitor") @ Trigger("fb")
        policy = CyclePolicy().named("policy") @ Trigger("skill")
        echo = Echo().named("echo") @ Rate(4)
        kick.then(policy, sync=Latest(), map={"value": "skill"})
        monitor.then(policy, sync=Latest())
        policy.then(monitor, sync=Latest(), delay=0.01)
        policy.then(echo, sync=Window(buffer_size=2), map={"fb": "x"})
    return pipe


def others(trace) -> tuple[list, list]:
    """The trace's events and step records, but the plan reporter's, in tag order."""
    events = sorted((e for e in trace.events if e.node != "shipped"), key=lambda e: (e.tag, e.node, e.port, e.seq))
    steps = sorted((s.node, s.tag, s.status) for s in trace.steps if s.node != "shipped")
    return [(e.tag, e.node, e.port, e.seq, e.value) for e in events], steps


def test_each_worker_gets_the_plan_and_the_run_is_the_in_process_one():
    pipe = wired()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RetrieverWarning)
        made = json.loads(json.dumps(plan_graph(pipe.compile()).to_data()))
    trace = pipe.run(duration=1.0, backend="zenoh", virtual_time=True, quiet=True)
    assert trace.values_of("shipped", "value") == [made]
    pipe.reset()
    reference = pipe.run(duration=1.0, backend="inproc")
    assert reference.values_of("shipped", "value") == ["in no worker process"]
    assert others(trace) == others(reference)
    assert trace.values_of("echo", "saw"), "the pipeline ran: its sink saw events"


def test_a_worker_daemon_forwards_the_plan_to_its_workers(tmp_path):
    pipe = wired()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RetrieverWarning)
        graph = pipe.compile()
    spec = run_spec(graph.to_ir().doc, "shipped", plan=plan_graph(graph).to_data(), hub="tcp/127.0.0.1:7447")
    with zenoh.open(peer_config(shared_memory=False)) as session:
        runs = DaemonRuns(session, "w", "shipped", listen=(), secret=None, allowed=lambda module: True,
                          refusal=lambda module: "", paths=())
        try:
            local = runs.local_spec(spec, tmp_path, "r1")
        finally:
            runs.close()
    assert local.plan == spec.plan
