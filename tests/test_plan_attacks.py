"""Plan.from_data is an entry point for what arrives from the network: a worker daemon's spec
carries the coordinator's plan beside the IR (retriever.plan, A shipped plan). Every way a plan
can be wrong is refused with an IRError naming the field, never a crash, and a refused message
stays short whatever the plan held."""

from __future__ import annotations

import copy
import json

import msgpack
import pytest

from retriever.errors import IRError
from retriever.plan import PLAN_SOURCE, Plan, plan_graph

from .test_plan import compiled, cycle_pipeline

GRAPH = compiled(cycle_pipeline())  # src → a ⇄ b (an instantaneous cycle), b → c (delayed)
IR_OF = GRAPH.to_ir()
GENUINE = json.loads(json.dumps(plan_graph(GRAPH).to_data()))
NODES = {n["id"]: i for i, n in enumerate(GENUINE["nodes"])}


def node(data: dict, nid: str) -> dict:
    return data["nodes"][NODES[nid]]


def refused(data, *fragments: str) -> str:
    with pytest.raises(IRError) as caught:
        Plan.from_data(data, IR_OF)
    message = str(caught.value)
    assert PLAN_SOURCE in message and len(message) < 1000, message
    for fragment in fragments:
        assert fragment in message, message
    return message


def changed(change) -> dict:
    data = copy.deepcopy(GENUINE)
    change(data)
    return data


def test_the_genuine_plan_is_read_as_made():
    assert Plan.from_data(copy.deepcopy(GENUINE), IR_OF) == plan_graph(GRAPH)


@pytest.mark.parametrize("change, where", [
    (lambda d: d.clear(), "the plan: missing nodes"),
    (lambda d: d.update(nodes="abc"), "nodes: expected a list"),
    (lambda d: d["nodes"].__setitem__(0, ["src"]), "nodes[0]: expected an object"),
    (lambda d: node(d, "src").update(id=7), "nodes[0].id: expected a node id of the IR, got int 7"),
    (lambda d: node(d, "c").update(latency_ns=0.01), "node 'c'.latency_ns: expected 10000000"),
    (lambda d: node(d, "c").update(latency_ns=True), "node 'c'.latency_ns"),
    (lambda d: node(d, "a").update(feeds={"0": 1}), "node 'a'.feeds: expected a list"),
    (lambda d: node(d, "c")["feeds"][0].__setitem__(3, "20000000"), "node 'c'.feeds[0].delay_ns: expected an integer"),
    (lambda d: node(d, "c")["feeds"][0].__setitem__(5, 1.5e9), "node 'c'.feeds[0].deadline_ns"),
    (lambda d: node(d, "a")["feeds"][0].__setitem__(4, 1), "node 'a'.feeds[0].triggers: expected true"),
    (lambda d: node(d, "a").update(on_a_cycle="yes"), "node 'a'.on_a_cycle: expected true or false"),
    (lambda d: node(d, "a").update(cycle="a"), "node 'a'.cycle: expected a list"),
    (lambda d: node(d, "a").update(instant_ports="x"), "node 'a'.instant_ports: expected ['x']"),
    (lambda d: node(d, "a").update(policies=[["x", {"latest": {}}]]), "node 'a'.policies: expected an object"),
    (lambda d: node(d, "b").update(consumers={"x": "a"}), "node 'b'.consumers.x: expected a list of 1 to 4"),
])
def test_a_field_of_the_wrong_type_is_refused_by_name(change, where):
    refused(changed(change), where)


@pytest.mark.parametrize("value", [-1, 2**63, 10**30])
def test_nanoseconds_out_of_range_are_refused(value):
    refused(changed(lambda d: node(d, "c")["feeds"][0].__setitem__(3, value)), "node 'c'.feeds[0].delay_ns",
            "from 0 to 2**63 - 1")


@pytest.mark.parametrize("change, where", [
    (lambda d: d["nodes"].extend([node(d, "c")] * 100_000), "nodes: expected a list of 0 to 4 items"),
    (lambda d: node(d, "a")["feeds"].extend([node(d, "a")["feeds"][0]] * 100_000), "node 'a'.feeds: expected a list"),
    (lambda d: node(d, "a").update(cycle=["a", "b"] * 50_000), "node 'a'.cycle: expected a list of 1 to 4 items"),
    (lambda d: node(d, "a").update(policies={f"p{i}": {"latest": {}} for i in range(100_000)}),
     "node 'a'.policies: expected an object of at most 2 keys"),
    (lambda d: node(d, "b").update(consumers={"x": [["a", "x", 0, True]] * 100_000}), "node 'b'.consumers.x"),
    (lambda d: node(d, "src").update(id="s" * 10_000_000), "nodes[0].id: expected a node id of the IR"),
    (lambda d: node(d, "a").update(instant_ports=["x"] * 1_000_000), "node 'a'.instant_ports"),
])
def test_huge_sizes_are_refused_with_a_short_message(change, where):
    refused(changed(change), where)


def test_a_plan_with_more_feeds_than_the_ir_has_edges_is_refused():
    def doubled(d):
        for nid in ("a", "b"):  # within each list's bound, and mirrored: only the total is too much
            node(d, nid)["feeds"] *= 2
        node(d, "src")["consumers"]["x"] *= 2
        node(d, "a")["consumers"]["x"] *= 2
        node(d, "b")["consumers"]["x"][:1] *= 2
    refused(changed(doubled), "nodes: 7 feeds in all, more than the IR's 4 edges")


@pytest.mark.parametrize("change, where", [
    (lambda d: node(d, "src").update(id="ghost"), "nodes[0].id: expected a node id of the IR, got str 'ghost'"),
    (lambda d: node(d, "a")["feeds"][0].__setitem__(0, "ghost"), "node 'a'.feeds[0].src: expected a node id"),
    (lambda d: node(d, "a")["feeds"][0].__setitem__(1, "y"), "feeds[0].src_port: expected an output port of node 'src'"),
    (lambda d: node(d, "a")["feeds"][0].__setitem__(2, "../x"), "feeds[0].port: expected an input port of node 'a'"),
    (lambda d: node(d, "b").update(consumers={"*": node(d, "b")["consumers"]["x"]}),
     "node 'b'.consumers (a key): expected an output port of node 'b'"),
    (lambda d: node(d, "b")["consumers"]["x"][0].__setitem__(0, "ghost"), "node 'b'.consumers.x[0].dst"),
    (lambda d: node(d, "b")["consumers"]["x"][0].__setitem__(1, "y"), "consumers.x[0].dst_port: expected an input port"),
    (lambda d: node(d, "c").update(policies={"y": {"latest": {}}}), "node 'c'.policies: a policy for str 'y'"),
    (lambda d: node(d, "c")["policies"].clear(), "node 'c'.policies: no policy for fed input port(s) x"),
])
def test_names_that_are_no_node_or_port_of_the_ir_are_refused(change, where):
    refused(changed(change), where)


@pytest.mark.parametrize("change, where", [
    (lambda d: d.update(evil=1), "the plan: unknown str 'evil'"),
    (lambda d: node(d, "a").pop("cycle"), "nodes[1]: missing cycle"),
    (lambda d: node(d, "a").update(__class__="os:system"), "nodes[1]: unknown str '__class__'"),
    (lambda d: node(d, "c")["feeds"][0].pop(), "node 'c'.feeds[0]: expected a list [src, src_port, port"),
    (lambda d: node(d, "c")["feeds"][0].append(0), "node 'c'.feeds[0]: expected a list"),
    (lambda d: node(d, "b")["consumers"]["x"][0].append("exec"), "node 'b'.consumers.x[0]: expected a list [dst"),
    (lambda d: d["nodes"].pop(), "nodes: no plan for node(s) c of the IR"),
    (lambda d: d["nodes"].__setitem__(3, node(d, "src")), "nodes[3].id: node 'src' is planned twice"),
])
def test_extra_or_missing_fields_and_nodes_are_refused(change, where):
    refused(changed(change), where)


@pytest.mark.parametrize("cycle, fragment", [
    (["a", "ghost"], "node 'a'.cycle[1]: expected a node id of the IR, got str 'ghost'"),
    (["b", "c"], "node 'a'.cycle: expected distinct node ids, 'a' among them"),
    (["a", "a"], "node 'a'.cycle: expected distinct node ids"),
    ([], "node 'a'.cycle: expected a list of 1 to 4 items"),
    ([None], "node 'a'.cycle[0]"),
])
def test_a_cycle_of_nodes_not_in_the_ir_or_not_through_its_node_is_refused(cycle, fragment):
    refused(changed(lambda d: node(d, "a").update(cycle=cycle)), fragment)


@pytest.mark.parametrize("change, where", [
    (lambda d: node(d, "src")["consumers"].clear(), "node 'a'.feeds: its feed src.x → a.x (delay 0 ns) has no consumer"),
    (lambda d: node(d, "a")["feeds"].pop(1), "node 'b'.consumers: its consumer b.x → a.x (delay 0 ns) has no feed"),
    (lambda d: node(d, "c")["feeds"][0].__setitem__(3, 0), "node 'c'.feeds: its feed b.x → c.x"),
    (lambda d: node(d, "src")["consumers"]["x"].append(["c", "x", 5, True]),
     "node 'src'.consumers: its consumer src.x → c.x (delay 5 ns) has no feed"),
    (lambda d: node(d, "c").update(on_a_cycle=True), "node 'c'.on_a_cycle: expected false"),
    (lambda d: node(d, "c").update(instant_ports=["x"]), "node 'c'.instant_ports: expected []"),
    (lambda d: node(d, "a").update(instant_ports=[]), "node 'a'.instant_ports: expected ['x']"),
    (lambda d: node(d, "a")["feeds"][0].__setitem__(6, 5), "node 'a'.feeds[0].src_latency_ns: expected 0"),
    (lambda d: node(d, "b")["consumers"]["x"][1].__setitem__(3, False), "node 'b'.consumers.x[1].triggers: expected true"),
])
def test_a_plan_that_contradicts_itself_or_its_ir_is_refused(change, where):
    refused(changed(change), where)


@pytest.mark.parametrize("doc, fragment", [
    ({"os:system": {"command": "touch /tmp/x"}}, "unknown sync policy 'os:system'"),
    ({"latest": {"staleness": "soon"}}, "node 'c'.policies.x"),
    ({"queue": {"maxsize": 4}, "latest": {}}, "an adapter must be an object with one key"),
    ({"window": {"buffer_size": 2, "__init__": 1}}, "node 'c'.policies.x: adapter window: bad parameters"),
    ({"window": {"buffer_size": [0] * 100_000}}, "node 'c'.policies.x"),
])
def test_a_policy_is_one_of_the_irs_adapters_or_refused(doc, fragment):
    refused(changed(lambda d: node(d, "c")["policies"].update(x=doc)), fragment)


@pytest.mark.parametrize("value", [b"\x00", msgpack.ExtType(4, b"os:system"), 10**5000, float("nan"), (1, 2),
                                   {1: 2}, [[[[[[[[]]]]]]]], object()],
                         ids=["bytes", "ext", "huge-int", "nan", "tuple", "int-key", "nested", "object"])
def test_values_json_cannot_hold_are_refused_wherever_they_stand(value):
    for place in (lambda d: d.update(nodes=value), lambda d: node(d, "a").update(id=value),
                  lambda d: node(d, "a")["feeds"][0].__setitem__(3, value), lambda d: node(d, "a").update(cycle=value),
                  lambda d: node(d, "a")["policies"].update(x=value), lambda d: node(d, "a").update(instant_ports=value)):
        refused(changed(place))
