"""A graph's wiring, node by node, computed once: what feeds each input and how it is selected,
where each output goes, and which cycles a node is on.

Every backend wires a node the same way, from one :class:`Plan`: the in-process backend from the
:class:`~retriever.graph.Graph` it runs (:func:`plan_graph`), a worker process from the run's IR
(:func:`plan_ir`), which is the same plan (tests/test_plan.py holds the two equal). A plan is
plain data: :meth:`Plan.to_data` and :meth:`Plan.from_data` carry it as JSON-safe values, so it can
travel in a worker's spec.

    Graph ──plan_graph──┐                       per node: NodePlan
                        ├──▶ Plan ──▶ nodes ──▶   feeds       edges in (source, delay, trigger, deadline)
    IR ─────plan_ir─────┘                         policies    per fed input port, its sync policy
                                                  consumers   per output port, edges out
                                                  cycle, instant_ports, on_a_cycle

What a plan cannot know is a flow's own ports (which input has a default): :func:`bind_inputs`
joins a node's plan with them into the ``(port, buffer, policy, port spec)`` list a tick selects
from (retriever.tick) and the optional ports nothing feeds.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

from .clocks import clock_from_ir
from .ir import DEFAULT_DEADLINE, IR
from .sync import MISSING, PortBuffer, SyncPolicy, policy_from_ir
from .time import seconds_to_ns

if TYPE_CHECKING:
    from .flow._base import PortSpec
    from .graph import Graph


@dataclass(frozen=True)
class Feed:
    """One edge into a node: from ``src.src_port`` to its input ``port``."""

    src: str
    src_port: str
    port: str
    delay_ns: int
    triggers: bool  # whether an event on it makes the node tick (its clock's trigger ports)
    deadline_ns: int  # real time: the longest a tick waits for this edge (the pipeline's if unset)
    src_latency_ns: int  # the producer's logical execution time (0: none)


@dataclass(frozen=True)
class Consumer:
    """One edge out of a node's output port, to ``dst.dst_port``."""

    dst: str
    dst_port: str
    delay_ns: int
    triggers: bool  # whether an event on it makes ``dst`` tick


@dataclass
class NodePlan:
    """The wiring of one node."""

    id: str
    latency_ns: int
    #: the edges into it, in the graph's edge order (fan-in: several into one port)
    feeds: list[Feed] = field(default_factory=list)
    #: per input port an edge feeds, its sync policy; a port absent here is fed by nothing
    policies: dict[str, SyncPolicy] = field(default_factory=dict)
    #: per output port with edges, those edges in the graph's edge order
    consumers: dict[str, list[Consumer]] = field(default_factory=dict)
    #: the instantaneous cycle it is on (the first the graph lists), if one
    cycle: list[str] | None = None
    #: on that cycle, its output ports whose events trigger a tick at their own instant: those of
    #: its undelayed edges into a trigger port (past max_microsteps an event there is a Zeno loop)
    instant_ports: frozenset[str] = frozenset()
    #: whether a path of edges leads from it back to it (delays and clocks aside)
    on_a_cycle: bool = False

    def sources(self, port: str) -> list[tuple[str, str]]:
        """The ``(node, port)`` of each edge that feeds input ``port``, in edge order."""
        return [(f.src, f.src_port) for f in self.feeds if f.port == port]

    def to_data(self) -> dict:
        return {
            "id": self.id, "latency_ns": self.latency_ns,
            "feeds": [[f.src, f.src_port, f.port, f.delay_ns, f.triggers, f.deadline_ns, f.src_latency_ns]
                      for f in self.feeds],
            "policies": {port: policy.to_ir() for port, policy in self.policies.items()},
            "consumers": {port: [[c.dst, c.dst_port, c.delay_ns, c.triggers] for c in edges]
                          for port, edges in self.consumers.items()},
            "cycle": self.cycle, "instant_ports": sorted(self.instant_ports), "on_a_cycle": self.on_a_cycle,
        }

    @classmethod
    def from_data(cls, data: dict) -> NodePlan:
        return cls(data["id"], data["latency_ns"], [Feed(*f) for f in data["feeds"]],
                   {port: policy_from_ir(doc) for port, doc in data["policies"].items()},
                   {port: [Consumer(*c) for c in edges] for port, edges in data["consumers"].items()},
                   data["cycle"], frozenset(data["instant_ports"]), data["on_a_cycle"])


@dataclass
class Plan:
    """Every node's wiring, by node id (in the graph's node order)."""

    nodes: dict[str, NodePlan]

    def to_data(self) -> dict:
        """The plan as JSON-safe values (policies in their IR form)."""
        return {"nodes": [node.to_data() for node in self.nodes.values()]}

    @classmethod
    def from_data(cls, data: dict) -> Plan:
        return cls({node.id: node for node in map(NodePlan.from_data, data["nodes"])})


# ---------------------------------------------------------------------------------------------
# Making a plan: from a graph or from an IR, by one rule (_plan)
# ---------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class _Edge:
    src: str
    src_port: str
    dst: str
    dst_port: str
    sync: SyncPolicy
    delay_ns: int
    deadline_ns: int


def plan_graph(graph: Graph) -> Plan:
    """The plan of a compiled graph."""
    default_ns = seconds_to_ns(graph.deadline)
    edges = [_Edge(e.src, e.src_port, e.dst, e.dst_port, e.sync, e.delay_ns,
                   default_ns if e.deadline is None else seconds_to_ns(e.deadline)) for e in graph.edges]
    nodes = {node.id: (node.settings.latency_ns, node.triggers_on) for node in graph.nodes.values()}
    return _plan(nodes, edges, graph.instantaneous_cycles)


def plan_ir(ir: IR) -> Plan:
    """The plan of an IR: the same as that of the graph it was made from."""
    default_deadline = ir.doc["metadata"].get("deadline", DEFAULT_DEADLINE)
    edges = []
    for e in ir.edges:
        deadline = e.get("deadline")
        edges.append(_Edge(e["source"]["node"], e["source"]["port"], e["destination"]["node"],
                           e["destination"]["port"], policy_from_ir(e["adapter"]), seconds_to_ns(e.get("delay", 0.0)),
                           seconds_to_ns(default_deadline if deadline is None else deadline)))
    nodes = {n["id"]: (seconds_to_ns(n["config"].get("latency") or 0.0), clock_from_ir(n["config"]["clock"]).triggers_on)
             for n in ir.nodes}
    return _plan(nodes, edges, ir.topology.get("instantaneous_cycles", []))


def _plan(nodes: dict[str, tuple[int, Callable[[str], bool]]], edges: list[_Edge],
          instantaneous_cycles: list[list[str]]) -> Plan:
    """``nodes``: per node id, its latency and its clock's ``triggers_on``."""
    plans = {node_id: NodePlan(node_id, latency_ns) for node_id, (latency_ns, _) in nodes.items()}
    for e in edges:
        triggers = nodes[e.dst][1](e.dst_port)
        dst = plans[e.dst]
        dst.feeds.append(Feed(e.src, e.src_port, e.dst_port, e.delay_ns, triggers, e.deadline_ns,
                              plans[e.src].latency_ns))
        dst.policies[e.dst_port] = e.sync
        plans[e.src].consumers.setdefault(e.src_port, []).append(Consumer(e.dst, e.dst_port, e.delay_ns, triggers))
    cyclic = nodes_on_a_cycle((e.src, e.dst) for e in edges)
    for plan in plans.values():
        plan.on_a_cycle = plan.id in cyclic
        plan.cycle = next((list(c) for c in instantaneous_cycles if plan.id in c), None)
        if plan.cycle is not None:
            plan.instant_ports = frozenset(port for port, out in plan.consumers.items()
                                           if any(c.triggers and not c.delay_ns for c in out))
    return Plan(plans)


def nodes_on_a_cycle(edges: Iterable[tuple[str, str]]) -> set[str]:
    """The nodes a path of ``(source, destination)`` edges leads from back to themselves."""
    after: dict[str, set[str]] = {}
    for src, dst in edges:
        after.setdefault(src, set()).add(dst)
    found = set()
    for start in after:
        seen: set[str] = set()
        todo = list(after[start])
        while todo:
            n = todo.pop()
            if n == start:
                found.add(start)
                break
            if n not in seen:
                seen.add(n)
                todo.extend(after.get(n, ()))
    return found


# ---------------------------------------------------------------------------------------------
# Binding a node's plan to its flow's ports
# ---------------------------------------------------------------------------------------------
class Unfed:
    """The policy of a required input port no edge feeds: it selects nothing at every tick, so
    every tick of the node is skipped (``compile_graph`` warns of it)."""

    def select(self, buf: PortBuffer, tau: tuple[int, int]) -> tuple[Any, None, int, None]:
        return MISSING, None, 0, None

    def commit_to(self, buf: PortBuffer, commit: Any) -> None:
        """Nothing to commit: it never selects."""


UNFED = Unfed()


def bind_inputs(plan: NodePlan, ports: dict[str, PortSpec], new_buffer: Callable[[], PortBuffer] = PortBuffer,
                ) -> tuple[list[tuple[str, PortBuffer, Any, PortSpec]], dict[str, PortSpec]]:
    """A node's inputs as a tick selects them (retriever.tick.select_inputs): ``(port, buffer,
    policy, port spec)`` per port an edge feeds (one ``new_buffer()`` each, which every edge into
    it fills) or that is required (:data:`UNFED`), in the flow's port order; and the optional
    ports nothing feeds, which take their fallback at every tick."""
    inputs, fallbacks = [], {}
    for port, spec in ports.items():
        policy = plan.policies.get(port)
        if policy is not None:
            inputs.append((port, new_buffer(), policy, spec))
        elif spec.required:
            inputs.append((port, PortBuffer(), UNFED, spec))
        else:
            fallbacks[port] = spec
    return inputs, fallbacks
