"""retriever.plan: a graph's wiring, node by node, the same from the graph and from its IR."""

from __future__ import annotations

import json
import warnings
from dataclasses import dataclass
from typing import Any, Optional

from hypothesis import given

from retriever import IR, MISSING, Flow, Latest, Pipeline, Queue, Rate, RetrieverWarning, Trigger, Window, io
from retriever.plan import (UNFED, Consumer, Feed, Plan, bind_inputs, nodes_on_a_cycle, plan_graph, plan_ir,
                            tie_order)

from .backends.test_schedule_independence import SETTINGS, graphs


@io
@dataclass
class Num:
    x: Any


@io
@dataclass
class Three:
    a: Any
    b: Optional[Any]
    c: Any = 7


class Source(Flow[None, Num]):
    def step(self, inp: None) -> Num:
        return Num(1)


class Echo(Flow[Num, Num]):
    def step(self, inp: Num) -> Num:
        return inp


class Sink(Flow[Three, Num]):
    def step(self, inp: Three) -> Num:
        return Num(inp.a)


def compiled(pipe: Pipeline):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RetrieverWarning)
        return pipe.compile()


def cycle_pipeline() -> Pipeline:
    """src feeds a ⇄ b, an instantaneous cycle of two Trigger flows; b feeds c after a delay."""
    with Pipeline("plan") as pipe:
        src = Source().configure(name="src") @ Rate(10)
        a = Echo().configure(name="a") @ Trigger()
        b = Echo().configure(name="b") @ Trigger()
        c = Echo().configure(name="c", latency=0.01) @ Trigger()
        pipe.connect(src, a, sync=Latest())
        pipe.connect(b, a, sync=Latest())
        pipe.connect(a, b, sync=Queue(4))
        pipe.connect(b, c, sync=Window(buffer_size=2), delay=0.02, deadline=0.5)
    return pipe


def test_a_node_plan_says_what_feeds_it_where_its_outputs_go_and_its_cycles():
    plan = plan_graph(compiled(cycle_pipeline())).nodes
    assert list(plan) == ["src", "a", "b", "c"]
    assert plan["a"].feeds == [Feed("src", "x", "x", 0, True, 100_000_000, 0), Feed("b", "x", "x", 0, True, 100_000_000, 0)]
    assert plan["a"].sources("x") == [("src", "x"), ("b", "x")]
    assert plan["c"].feeds == [Feed("b", "x", "x", 20_000_000, True, 500_000_000, 0)]
    assert plan["c"].policies == {"x": Window(buffer_size=2)}
    assert plan["b"].consumers == {"x": [Consumer("a", "x", 0, True), Consumer("c", "x", 20_000_000, True)]}
    assert plan["c"].latency_ns == 10_000_000 and plan["c"].consumers == {}
    assert sorted(plan["a"].cycle) == sorted(plan["b"].cycle) == ["a", "b"]
    assert plan["a"].instant_ports == plan["b"].instant_ports == frozenset({"x"})
    assert plan["src"].cycle is None and plan["src"].instant_ports == frozenset()
    assert [n for n in plan if plan[n].on_a_cycle] == ["a", "b"]


def test_cycles_are_found_through_any_number_of_nodes():
    edges = [("a", "b"), ("b", "c"), ("c", "a"), ("c", "d"), ("e", "e")]
    assert [n for n in "abcde" if n in nodes_on_a_cycle(edges)] == ["a", "b", "c", "e"]


def test_the_tie_order_puts_each_node_before_those_that_feed_it_then_goes_by_id():
    with Pipeline("fan") as pipe:
        src = Source().configure(name="src") @ Rate(10)
        for name in ("b", "a"):
            pipe.connect(src, Echo().configure(name=name) @ Trigger(), sync=Latest())
    assert tie_order(plan_graph(compiled(pipe))) == {"a": 0, "b": 1, "src": 2}
    # c feeds nothing; the cycle a ⇄ b and src, which feeds it, cannot be ordered so: by id
    assert tie_order(plan_graph(compiled(cycle_pipeline()))) == {"c": 0, "a": 1, "b": 2, "src": 3}


def test_a_plan_goes_through_json_unchanged():
    graph = compiled(cycle_pipeline())
    plan = plan_graph(graph)
    assert Plan.from_data(json.loads(json.dumps(plan.to_data())), graph.to_ir()) == plan


@SETTINGS
@given(spec=graphs())
def test_the_plan_of_a_graph_is_that_of_its_ir(spec):
    graph = compiled(spec.build())
    from_ir = plan_ir(IR.from_json(graph.to_ir().to_json()))
    assert from_ir == plan_graph(graph)
    assert Plan.from_data(json.loads(json.dumps(from_ir.to_data())), graph.to_ir()) == from_ir


def test_binding_gives_fed_ports_a_buffer_each_and_unfed_ones_their_fallback_or_nothing():
    with Pipeline("bind") as pipe:
        src = Source().configure(name="src") @ Rate(10)
        sink = Sink().configure(name="sink") @ Rate(10)
        pipe.connect(src, sink, sync=Latest(), map={"x": "c"})
    graph = compiled(pipe)
    node = graph.nodes["sink"]
    inputs, fallbacks = bind_inputs(plan_graph(graph).nodes["sink"], node.inputs)
    assert [(port, policy) for port, _, policy, _ in inputs] == [("a", UNFED), ("c", Latest())]
    assert list(fallbacks) == ["b"] and fallbacks["b"] is node.inputs["b"]
    assert UNFED.select(inputs[0][1], (0, 0)) == (MISSING, None, 0, None)
