"""worker/build.py, build_loop: a node loop wired as the run's plan says (retriever.plan, as JSON), the
coordinator's alike the IR's own."""

from __future__ import annotations

import json
import warnings

import pytest

from retriever import Latest, Pipeline, Queue, Rate, RetrieverWarning, Trigger
from retriever.backends.zenoh.worker.build import build_loop
from retriever.errors import IRError
from retriever.plan import plan_graph

from .semantics_flows import Counter, WhereRun
from .specs import run_spec


def wiring(loop) -> tuple:
    """What build_loop wired: each input's port, policy and buffer's trim batch; the unfed optional
    ports; each edge in; and what the loop knows of cycles and consumers."""
    steps, streams, outputs = loop.steps, loop.streams, loop.outputs
    inputs = [(port, policy, buf.trim_batch) for port, buf, policy, _ in steps.inputs]
    edges = [(e.src, e.src_port, e.port, e.delay_ns, e.triggers, e.deadline_ns, e.src_latency_ns,
              next(i for i, (_, buf, _, _) in enumerate(steps.inputs) if buf is e.buf)) for e in streams.edges]
    return (inputs, sorted(steps.fallbacks), edges, outputs.cycle, outputs.instant_ports, loop.inline,
            outputs.consumed)


def test_a_loop_is_wired_alike_from_the_plan_in_its_spec_and_from_the_ir(session):
    with Pipeline("wired") as pipe:
        count = Counter().configure(name="count") @ Rate(hz=20)
        echo = WhereRun().configure(name="where") @ Trigger("x")
        count.then(echo, sync=Queue(3), map={"value": "x"}, delay=0.01)
        echo.then(count, sync=Latest(), map={"report": "x"})
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RetrieverWarning)
        graph = pipe.compile()
    ir = graph.to_ir().doc
    shipped = json.loads(json.dumps(plan_graph(graph).to_data()))
    for node in ("count", "where"):
        made_here = build_loop(run_spec(ir, "wired-test"), node, session)
        from_spec = build_loop(run_spec(ir, "wired-test", plan=shipped), node, session)
        assert wiring(made_here) == wiring(from_spec)
    where = wiring(made_here)
    assert where[0] == [("x", Queue(3), 1)] and where[2] == [("count", "value", "x", 10_000_000, True, 100_000_000, 0, 0)]
    assert where[3] is None and where[5] is False, "on a cycle (not an instantaneous one): it steps on its main thread"


def test_a_loop_is_not_built_from_a_plan_its_ir_refutes(session):
    with Pipeline("refuted") as pipe:
        count = Counter().configure(name="count") @ Rate(hz=20)
        echo = WhereRun().configure(name="where") @ Trigger("x")
        count.then(echo, sync=Latest(), map={"value": "x"})
    graph = pipe.compile()
    shipped = json.loads(json.dumps(plan_graph(graph).to_data()))
    shipped["nodes"][1]["feeds"][0][0] = "elsewhere"  # a producer the run has not
    with pytest.raises(IRError, match=r"node 'where'.feeds\[0\].src: expected a node id of the IR, got str 'elsewhere'"):
        build_loop(run_spec(graph.to_ir().doc, "refuted-test", plan=shipped), "where", session)
