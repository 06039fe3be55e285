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

A shipped plan
--------------
The zenoh coordinator makes the plan once and ships it in each worker's spec, beside the IR; a
worker wires its node as that plan says. A spec that reaches a worker daemon came from the
network, so :meth:`Plan.from_data` reads it against the IR it travels with as an exact decoder
(raising IRError at the first problem, naming the field): every field there and no other, of
its type, in range (ns: 0 to 2**63 - 1), lists no longer than the IR's nodes or edges; every
node of the IR planned once; every name a node of the IR or a port it declares; each node's
latency, and whether an edge into a port triggers, as the IR's node and clock say; each feed
mirrored by a consumer at its source (and the other way round); a policy, of the IR's
vocabulary, for each fed port and no other; ``on_a_cycle`` and ``instant_ports`` what the feeds
and consumers imply; a cycle of distinct nodes, the node among them. Nothing in it is imported
or called: a policy is one of the IR's adapters, built as the IR's are (sync.policy_from_ir).

What a checked plan still chooses is which edges join the IR's ports, and their policies,
delays, deadlines and instantaneous cycles: what the IR's ``edges`` and ``topology`` say (the
IR does not check its cycles), and the IR comes from the same sender. So whatever a checked plan
makes a worker do, an IR its sender could have sent instead would make it do too: the worker
takes the plan as its node's wiring without making its own, the coordinator being the authority
of its run. (Refusing a plan unequal to ``plan_ir(ir)`` would leave every worker making the
plan anyway, and shipping it would save nothing.) A spec without a plan (an older
coordinator's, or one written by hand) is wired from ``plan_ir(ir)``.
"""

from __future__ import annotations

import reprlib
from collections import Counter
from heapq import heappop, heappush
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

from .clocks import clock_from_ir
from .errors import IRError
from .ir import DEFAULT_DEADLINE, IR
from .sync import MISSING, PortBuffer, SyncPolicy, policy_from_ir
from .time import MAX_TIME_NS, seconds_to_ns

if TYPE_CHECKING:
    from .flow.core import PortSpec
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


@dataclass
class Plan:
    """Every node's wiring, by node id (in the graph's node order)."""

    nodes: dict[str, NodePlan]

    def to_data(self) -> dict:
        """The plan as JSON-safe values (policies in their IR form)."""
        return {"nodes": [node.to_data() for node in self.nodes.values()]}

    @classmethod
    def from_data(cls, data: Any, ir: IR) -> Plan:
        """The plan ``data`` carries, checked against ``ir``, the IR it travels with (the module's
        docstring, A shipped plan). Raises IRError naming the first field that is wrong."""
        return _PlanReader(ir).plan(data)


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
    return _plan(_ir_nodes(ir), edges, ir.topology.get("instantaneous_cycles", []))


def _ir_nodes(ir: IR) -> dict[str, tuple[int, Callable[[str], bool]]]:
    """Per node of ``ir``, its latency (ns) and its clock's ``triggers_on``."""
    return {n["id"]: (seconds_to_ns(n["config"].get("latency") or 0.0), clock_from_ir(n["config"]["clock"]).triggers_on)
            for n in ir.nodes}


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
            plan.instant_ports = _instant_ports(plan.consumers)
    return Plan(plans)


def _instant_ports(consumers: dict[str, list[Consumer]]) -> frozenset[str]:
    """A node's output ports with an undelayed edge into a trigger port (on a cycle, those whose
    events make a tick at their own instant)."""
    return frozenset(port for port, out in consumers.items() if any(c.triggers and not c.delay_ns for c in out))


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


def tie_order(plan: Plan) -> dict[str, int]:
    """Per node, its place in the order the ticks of one tag run in: each node before the nodes
    that feed it, where edges allow, else by id (a cycle, and what feeds it). Which of a tag's
    ticks runs first changes nothing a run records but their order (every output comes at least
    a microstep later), except in a run that stops during a tag (``sys.exit(0)`` in a step, an
    error under ``on_error="stop"``): the tag's ticks that ran before the stop are recorded, those
    after it are not. The in-process backend runs a tag's ticks in this order; a zenoh run in
    virtual time, whose nodes run a tag's ticks each in its own process, cuts its record by it."""
    ids = sorted(plan.nodes)
    consumers = {n: {c.dst for out in plan.nodes[n].consumers.values() for c in out if c.dst != n} for n in ids}
    producers: dict[str, list[str]] = {n: [] for n in ids}
    for p in ids:
        for c in consumers[p]:
            producers[c].append(p)
    waiting = {n: len(cs) for n, cs in consumers.items()}  # per node, its consumers not yet placed
    ready = [n for n in ids if not waiting[n]]  # (sorted: a heap)
    order = []
    while ready:
        n = heappop(ready)
        order.append(n)
        for p in producers[n]:
            waiting[p] -= 1
            if not waiting[p]:
                heappush(ready, p)
    placed = set(order)
    order += [n for n in ids if n not in placed]
    return {n: at for at, n in enumerate(order)}


# ---------------------------------------------------------------------------------------------
# Reading a shipped plan: an exact decoder, checked against the IR it travels with
# ---------------------------------------------------------------------------------------------
#: what a shipped plan's problems name as their source
PLAN_SOURCE = "the run's plan"
_NODE_FIELDS = ("id", "latency_ns", "feeds", "policies", "consumers", "cycle", "instant_ports", "on_a_cycle")
_FEED_FIELDS = ("src", "src_port", "port", "delay_ns", "triggers", "deadline_ns", "src_latency_ns")
_CONSUMER_FIELDS = ("dst", "dst_port", "delay_ns", "triggers")


class _PlanReader:
    """Reads :meth:`Plan.to_data`'s form against ``ir`` (the module's docstring, A shipped plan)."""

    def __init__(self, ir: IR):
        self.nodes = {n["id"]: n for n in ir.nodes}
        self.ir_nodes = _ir_nodes(ir)
        self.max_edges = len(ir.edges)

    def plan(self, data: Any) -> Plan:
        items = _items(_fields(data, "the plan", ("nodes",))["nodes"], "nodes", len(self.nodes))
        plans: dict[str, NodePlan] = {}
        for i, item in enumerate(items):
            node = self.node(item, f"nodes[{i}]")
            if node.id in plans:
                raise _problem(f"nodes[{i}].id", f"node '{node.id}' is planned twice")
            plans[node.id] = node
        missing = [nid for nid in self.nodes if nid not in plans]
        if missing:
            raise _problem("nodes", f"no plan for node(s) {', '.join(missing)} of the IR")
        feeds = sum(len(p.feeds) for p in plans.values())
        if feeds > self.max_edges:
            raise _problem("nodes", f"{feeds} feeds in all, more than the IR's {self.max_edges} edges")
        _check_mirrored(plans)
        cyclic = nodes_on_a_cycle((f.src, p.id) for p in plans.values() for f in p.feeds)
        for p in plans.values():
            if p.on_a_cycle != (p.id in cyclic):
                raise _problem(f"node '{p.id}'.on_a_cycle", f"expected {str(p.id in cyclic).lower()} (whether a path "
                               f"of the plan's feeds leads from it back to it), got {str(p.on_a_cycle).lower()}")
        return Plan(plans)

    def node(self, data: Any, where: str) -> NodePlan:
        fields = _fields(data, where, _NODE_FIELDS)
        nid = _name(fields["id"], f"{where}.id", self.nodes, "a node id of the IR")
        where = f"node '{nid}'"
        latency_ns = _exact(fields["latency_ns"], f"{where}.latency_ns", self.ir_nodes[nid][0], "its latency in the IR")
        feeds = [self.feed(f, f"{where}.feeds[{i}]", nid)
                 for i, f in enumerate(_items(fields["feeds"], f"{where}.feeds", self.max_edges))]
        policies = self.policies(fields["policies"], f"{where}.policies", [f.port for f in feeds])
        consumers = self.consumers(fields["consumers"], f"{where}.consumers", nid)
        cycle = self.cycle(fields["cycle"], f"{where}.cycle", nid)
        instant = sorted(_instant_ports(consumers)) if cycle is not None else []
        if fields["instant_ports"] != instant:
            raise _problem(f"{where}.instant_ports", f"expected {instant} (on its cycle, the ports of its undelayed "
                           f"edges into trigger ports, sorted), got {_shown(fields['instant_ports'])}")
        on_a_cycle = _bool(fields["on_a_cycle"], f"{where}.on_a_cycle")
        return NodePlan(nid, latency_ns, feeds, policies, consumers, cycle, frozenset(instant), on_a_cycle)

    def feed(self, data: Any, where: str, nid: str) -> Feed:
        src, src_port, port, delay_ns, triggers, deadline_ns, src_latency_ns = _row(data, where, _FEED_FIELDS)
        src = _name(src, f"{where}.src", self.nodes, "a node id of the IR")
        src_port = _name(src_port, f"{where}.src_port", self.nodes[src]["outputs"], f"an output port of node '{src}'")
        port = _name(port, f"{where}.port", self.nodes[nid]["inputs"], f"an input port of node '{nid}'")
        triggers = _exact(triggers, f"{where}.triggers", self.ir_nodes[nid][1](port),
                          f"whether node '{nid}''s clock ticks on '{port}'")
        src_latency_ns = _exact(src_latency_ns, f"{where}.src_latency_ns", self.ir_nodes[src][0],
                                f"node '{src}''s latency in the IR")
        return Feed(src, src_port, port, _ns(delay_ns, f"{where}.delay_ns"), triggers,
                    _ns(deadline_ns, f"{where}.deadline_ns"), src_latency_ns)

    def policies(self, data: Any, where: str, fed: list[str]) -> dict[str, SyncPolicy]:
        docs = _mapping(data, where, len(fed))
        policies = {}
        for port, doc in docs.items():
            if type(port) is not str or port not in fed:
                raise _problem(where, f"a policy for {_shown(port)}, which no feed of the node goes into")
            try:
                policies[port] = policy_from_ir(doc)
            except (ValueError, TypeError, OverflowError) as e:
                raise _problem(f"{where}.{port}", f"{e}"[:200]) from None
        unset = [port for port in dict.fromkeys(fed) if port not in policies]
        if unset:
            raise _problem(where, f"no policy for fed input port(s) {', '.join(unset)}")
        return policies

    def consumers(self, data: Any, where: str, nid: str) -> dict[str, list[Consumer]]:
        consumers = {}
        for port, edges in _mapping(data, where, self.max_edges).items():
            port = _name(port, f"{where} (a key)", self.nodes[nid]["outputs"], f"an output port of node '{nid}'")
            items = _items(edges, f"{where}.{port}", self.max_edges, min_items=1)
            consumers[port] = [self.consumer(c, f"{where}.{port}[{i}]") for i, c in enumerate(items)]
        return consumers

    def consumer(self, data: Any, where: str) -> Consumer:
        dst, dst_port, delay_ns, triggers = _row(data, where, _CONSUMER_FIELDS)
        dst = _name(dst, f"{where}.dst", self.nodes, "a node id of the IR")
        dst_port = _name(dst_port, f"{where}.dst_port", self.nodes[dst]["inputs"], f"an input port of node '{dst}'")
        triggers = _exact(triggers, f"{where}.triggers", self.ir_nodes[dst][1](dst_port),
                          f"whether node '{dst}''s clock ticks on '{dst_port}'")
        return Consumer(dst, dst_port, _ns(delay_ns, f"{where}.delay_ns"), triggers)

    def cycle(self, data: Any, where: str, nid: str) -> list[str] | None:
        if data is None:
            return None
        cycle = [_name(n, f"{where}[{i}]", self.nodes, "a node id of the IR")
                 for i, n in enumerate(_items(data, where, len(self.nodes), min_items=1))]
        if nid not in cycle or len(set(cycle)) != len(cycle):
            raise _problem(where, f"expected distinct node ids, '{nid}' among them, got {_shown(cycle)}")
        return cycle


def _check_mirrored(plans: dict[str, NodePlan]) -> None:
    """Every feed of a node is a consumer of its source's, and the other way round."""
    into = Counter((f.src, f.src_port, p.id, f.port, f.delay_ns, f.triggers) for p in plans.values() for f in p.feeds)
    out = Counter((p.id, port, c.dst, c.dst_port, c.delay_ns, c.triggers)
                  for p in plans.values() for port, edges in p.consumers.items() for c in edges)
    for edges, what, lacks, end in ((into - out, "feed", "consumer", 2), (out - into, "consumer", "feed", 0)):
        for edge in edges:
            src, src_port, dst, dst_port, delay_ns, _ = edge
            raise _problem(f"node '{edge[end]}'.{what}s", f"its {what} {src}.{src_port} → {dst}.{dst_port} "
                           f"(delay {delay_ns} ns) has no {lacks} at the other end")


def _problem(where: str, what: str) -> IRError:
    return IRError(PLAN_SOURCE, [f"{where}: {what}"])


def _shown(value: Any) -> str:
    """A value of a plan's data in a message: its type and a short repr (never a huge one)."""
    try:
        return f"{type(value).__name__} {reprlib.repr(value)}"
    except ValueError:  # an int past sys.get_int_max_str_digits somewhere in it
        return f"{type(value).__name__} (holding an integer too long to show)"


def _fields(data: Any, where: str, names: tuple[str, ...]) -> dict:
    if type(data) is not dict:
        raise _problem(where, f"expected an object of {', '.join(names)}, got {_shown(data)}")
    missing = [n for n in names if n not in data]
    extra = [_shown(k) for k in data if k not in names]
    if missing or extra:
        raise _problem(where, "; ".join([*(["missing " + ", ".join(missing)] if missing else []),
                                         *(["unknown " + ", ".join(extra[:5])] if extra else [])]))
    return data


def _row(data: Any, where: str, names: tuple[str, ...]) -> list:
    if type(data) is not list or len(data) != len(names):
        raise _problem(where, f"expected a list [{', '.join(names)}], got {_shown(data)}")
    return data


def _items(data: Any, where: str, max_items: int, min_items: int = 0) -> list:
    if type(data) is not list or not min_items <= len(data) <= max_items:
        raise _problem(where, f"expected a list of {min_items} to {max_items} items, got {_shown(data)}")
    return data


def _mapping(data: Any, where: str, max_items: int) -> dict:
    if type(data) is not dict or len(data) > max_items:
        raise _problem(where, f"expected an object of at most {max_items} keys, got {_shown(data)}")
    return data


def _name(value: Any, where: str, known: dict, what: str) -> str:
    if type(value) is not str or value not in known:
        raise _problem(where, f"expected {what}, got {_shown(value)}")
    return value


def _ns(value: Any, where: str) -> int:
    if type(value) is not int or not 0 <= value <= MAX_TIME_NS:
        raise _problem(where, f"expected an integer of nanoseconds from 0 to 2**63 - 1, got {_shown(value)}")
    return value


def _bool(value: Any, where: str) -> bool:
    if type(value) is not bool:
        raise _problem(where, f"expected true or false, got {_shown(value)}")
    return value


def _exact(value: Any, where: str, expected: int | bool, what: str) -> Any:
    """``value``, which must be ``expected``, of its type."""
    if type(value) is not type(expected) or value != expected:
        raise _problem(where, f"expected {str(expected).lower() if type(expected) is bool else expected} ({what}), "
                       f"got {_shown(value)}")
    return value


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

    def selectable(self, buf: PortBuffer, after: tuple[int, int]) -> PortBuffer:
        """Nothing: it never selects (and no edge fills its buffer)."""
        return PortBuffer(buf.trim_batch)


UNFED = Unfed()


def bind_inputs(plan: NodePlan, ports: dict[str, PortSpec], new_buffer: Callable[[], PortBuffer] = PortBuffer,
                ) -> tuple[list[tuple[str, PortBuffer, Any, PortSpec]], dict[str, PortSpec]]:
    """A node's inputs as a tick selects them (retriever.tick.select_inputs): ``(port, buffer,
    policy, port spec)`` per port an edge feeds (one ``new_buffer()`` each, which every edge into
    it fills, bounded by its policy: sync.fill) or that is required (:data:`UNFED`), in the
    flow's port order; and the optional ports nothing feeds, which take their fallback at every tick."""
    inputs, fallbacks = [], {}
    for port, spec in ports.items():
        policy = plan.policies.get(port)
        if policy is not None:
            buf = new_buffer()
            buf.policy = policy  # what sync.bound keeps of it between ticks
            inputs.append((port, buf, policy, spec))
        elif spec.required:
            inputs.append((port, PortBuffer(), UNFED, spec))
        else:
            fallbacks[port] = spec
    return inputs, fallbacks
