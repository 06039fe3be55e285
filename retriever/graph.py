"""Compile a pipeline's declarations into a resolved, validated graph — a pure function.

``compile_graph`` resolves node ids and port matching, checks types, clocks and triggers, finds
cycles, and collects **every** problem before raising one :class:`GraphError`. The resulting
:class:`Graph` is what backends execute and what the IR serializes.
"""

from __future__ import annotations

import dataclasses
import inspect
import json
import os
import re
import sys
import types
import typing
from dataclasses import dataclass, field
from typing import Any

from .clocks import Clock
from .code import code_hashes
from .codec import type_path
from .errors import CodecError, GraphError, Problem
from .flow.core import NAME_MAX, Flow, FlowSettings, FlowSpec, PortSpec, flow_spec, settings_of, snake_case
from .ir import IR, IR_VERSION, SCRIPT_FOLDER_ATTR, param_to_ir, port_name_problem
from .sync import ActionChunking, SyncPolicy
from .time import NS_PER_S, exact_rational, seconds_to_ns
from .trace import DETAIL_KEYS

MAX_CYCLES_LISTED = 64


@dataclass
class DeclaredEdge:
    """An edge as the user wrote it; ports are resolved by ``compile_graph``."""

    src: Flow
    dst: Flow
    sync: SyncPolicy
    map: dict[str, str] | None
    delay: float
    qsize: int
    where: str | None
    deadline: float | None = None


@dataclass
class Node:
    """A flow placed in a graph, with its resolved id and ports."""

    id: str
    flow: Flow
    spec: FlowSpec
    inputs: dict[str, PortSpec]
    outputs: dict[str, PortSpec]
    params: dict[str, Any]
    rebuild_problem: str | None = None
    #: the rebuild problem is only that the class lives in ``__main__``: a backend that imports
    #: the main script the way multiprocessing does (the zenoh workers) can rebuild it
    rebuild_needs_main: bool = False

    @property
    def settings(self) -> FlowSettings:
        return settings_of(self.flow)

    @property
    def clock(self) -> Clock:
        return self.settings.clock  # type: ignore[return-value]

    def triggers_on(self, port: str) -> bool:
        return self.clock.triggers_on(port)


@dataclass
class Edge:
    """One resolved port-to-port connection."""

    src: str
    src_port: str
    dst: str
    dst_port: str
    sync: SyncPolicy
    delay: float = 0.0
    qsize: int = 10
    deadline: float | None = None  # real time: longest wait for this edge (None: the pipeline's)

    @property
    def delay_ns(self) -> int:
        return seconds_to_ns(self.delay)

    def __str__(self) -> str:
        return f"{self.src}.{self.src_port} → {self.dst}.{self.dst_port}"


@dataclass
class Graph:
    """A validated graph: nodes in registration order, edges in declaration order."""

    name: str
    nodes: dict[str, Node]
    edges: list[Edge]
    max_microsteps: int = 1000
    realtime: str = "soft"
    deadline: float = 0.1
    cycles: list[list[str]] = field(default_factory=list)
    instantaneous_cycles: list[list[str]] = field(default_factory=list)
    warnings: list[str] = field(default_factory=list)
    #: warnings about how edges were declared (a port matched by type alone): not the IR's, which
    #: names every port of every edge
    declaration_warnings: list[str] = field(default_factory=list)

    def to_ir(self) -> IR:
        return IR(graph_to_doc(self))


# ---------------------------------------------------------------------------------------------
# Type compatibility
# ---------------------------------------------------------------------------------------------
def _opaque(tp: Any) -> bool:
    return tp is Any or isinstance(tp, (str, typing.ForwardRef, typing.TypeVar)) or tp is inspect.Parameter.empty


def fits(out_t: Any, in_t: Any) -> bool:
    """Whether a value declared as ``out_t`` is acceptable where ``in_t`` is declared (lenient)."""
    if _opaque(out_t) or _opaque(in_t) or out_t == in_t:
        return True
    in_origin, out_origin = typing.get_origin(in_t), typing.get_origin(out_t)
    if in_origin in (typing.Union, types.UnionType):
        return any(fits(out_t, arm) for arm in typing.get_args(in_t))
    if out_origin in (typing.Union, types.UnionType):
        return all(fits(arm, in_t) for arm in typing.get_args(out_t))
    if in_origin is typing.Literal or out_origin is typing.Literal:
        return True
    in_cls, out_cls = in_origin or in_t, out_origin or out_t
    if not (isinstance(in_cls, type) and isinstance(out_cls, type)):
        return True
    if in_cls is float and out_cls is int:  # PEP 484 numeric tower
        return True
    if in_cls is complex and out_cls in (int, float):
        return True
    try:
        if not issubclass(out_cls, in_cls):
            return False
    except TypeError:
        return True
    in_args, out_args = typing.get_args(in_t), typing.get_args(out_t)
    if in_args and out_args and len(in_args) == len(out_args) and Ellipsis not in in_args + out_args:
        return all(fits(o, i) for o, i in zip(out_args, in_args))
    return True


def _event_type(out_t: Any) -> Any:
    """The type of the events an output port emits: ``Optional[X]`` emits X (None is no event)."""
    if typing.get_origin(out_t) in (typing.Union, types.UnionType):
        arms = [a for a in typing.get_args(out_t) if a is not type(None)]
        return arms[0] if len(arms) == 1 else typing.Union[tuple(arms)]
    return out_t


def _distinctive(out_t: Any, in_t: Any) -> bool:
    """Whether a match of two ports by type alone is as telling as one by name: both are one
    value type of the program's own (a dataclass, Optional or not), not an array, a number, a
    container or Any, which ports of any meaning share (the paper's Appendix D-D wires by it)."""
    def own(tp: Any) -> Any:
        args = [a for a in typing.get_args(tp) if a is not type(None)]
        tp = args[0] if typing.get_origin(tp) in (typing.Union, types.UnionType) and len(args) == 1 else tp
        return tp if isinstance(tp, type) and dataclasses.is_dataclass(tp) else None

    return own(out_t) is not None and own(out_t) is own(in_t)


def _fits_through(out_t: Any, in_t: Any, sync: SyncPolicy) -> bool:
    out_t = _event_type(out_t)
    if isinstance(sync, ActionChunking):
        return True  # a chunk of rows arrives as one row; row types are not declared
    if sync.delivers_list:
        if _opaque(in_t):
            return True
        origin = typing.get_origin(in_t) or in_t
        if isinstance(origin, type) and issubclass(list, origin) and origin is not object:
            args = typing.get_args(in_t)
            return not args or fits(out_t, args[0])
        if typing.get_origin(in_t) in (typing.Union, types.UnionType):
            return any(_fits_through(out_t, arm, sync) for arm in typing.get_args(in_t))
        return False
    return fits(out_t, in_t)


# ---------------------------------------------------------------------------------------------
# Constructor parameters (for rebuilding a flow from the IR alone)
# ---------------------------------------------------------------------------------------------
def constructor_params(flow: Flow) -> tuple[dict[str, Any], str | None, bool]:
    """The flow's constructor arguments by name, why it cannot be rebuilt from them (or None),
    and whether that is only because its class lives in ``__main__`` (Node.rebuild_needs_main)."""
    params, problem = _params(flow)
    cls = type(flow)
    if "<locals>" in cls.__qualname__:
        problem = f"class {cls.__qualname__} is defined inside a function, so it cannot be imported"
    elif cls.__module__ == "__main__" and problem is None:
        script = getattr(sys.modules.get("__main__"), "__file__", None)
        script = os.path.basename(script) if script and not script.endswith("__main__.py") else "SCRIPT.py"
        return params, (f"class {cls.__qualname__} lives in __main__; write the IR with "
                        f"`retriever ir {script} --out FILE.json` (it imports the script as a module), "
                        "or move the class to an importable module"), True
    return params, problem, False


def _params(flow: Flow) -> tuple[dict[str, Any], str | None]:
    cls = type(flow)
    settings = settings_of(flow)
    problem = None
    if cls.__init__ is object.__init__:
        if settings.args or settings.kwargs:
            return {}, problem or "constructor arguments given but __init__ takes none"
        return {}, problem
    try:
        bound = inspect.signature(cls.__init__).bind(None, *settings.args, **settings.kwargs)
    except TypeError as e:
        return {}, problem or f"constructor arguments do not match __init__: {e}"
    params = dict(list(bound.arguments.items())[1:])
    shown = {}
    for name, value in params.items():
        try:
            shown[name] = param_to_ir(value)
        except CodecError:
            shown[name] = {"$unserializable": f"{type(value).__module__}.{type(value).__qualname__}"}
            path, bad = _uncarried(value, name)
            what = f"is a {type(bad).__qualname__}" if path == name else f"holds a {type(bad).__qualname__} at {path}"
            problem = problem or (
                f"argument '{name}' {what}, which the IR cannot carry (only msgpack "
                "values: numbers, str, bytes, lists, tuples, dicts, numpy arrays, @io dataclasses)")
    return json.loads(json.dumps(shown)), problem


def _uncarried(value: Any, path: str) -> tuple[str, Any]:
    """The path into ``value`` (``kwargs['render_mode']``, ``args[2]``) of the first part the IR
    cannot carry, and that part: a list's, tuple's or dict's innermost, or the value itself."""
    parts = (value.items() if isinstance(value, dict) else enumerate(value) if isinstance(value, (list, tuple))
             else ())
    for key, inner in parts:
        try:
            param_to_ir(inner)
        except CodecError:
            return _uncarried(inner, f"{path}[{key!r}]")
    return path, value


# ---------------------------------------------------------------------------------------------
# Cycles
# ---------------------------------------------------------------------------------------------
def elementary_cycles(succ: dict[str, list[str]], order: list[str], limit: int = MAX_CYCLES_LISTED) -> list[list[str]]:
    """Simple cycles, each listed once starting from its first node in ``order``."""
    rank = {n: i for i, n in enumerate(order)}
    found: list[list[str]] = []
    for start in order:
        stack = [(start, iter(sorted(set(succ.get(start, ())), key=rank.__getitem__)))]
        path = [start]
        on_path = {start}
        while stack and len(found) < limit:
            node, it = stack[-1]
            nxt = next(it, None)
            if nxt is None:
                stack.pop()
                on_path.discard(path.pop())
                continue
            if nxt == start:
                found.append(list(path))
            elif nxt not in on_path and rank[nxt] > rank[start]:
                path.append(nxt)
                on_path.add(nxt)
                stack.append((nxt, iter(sorted(set(succ.get(nxt, ())), key=rank.__getitem__))))
    return found


# ---------------------------------------------------------------------------------------------
# The compiler
# ---------------------------------------------------------------------------------------------
def _assign_ids(flows: list[Flow], problems: list[Problem]) -> dict[int, str]:
    ids: dict[int, str] = {}
    taken: dict[str, Flow] = {}
    for f in flows:
        name = settings_of(f).name
        if name is None:
            continue
        if name in taken:
            problems.append(Problem(
                f"node id '{name}' is used by two flows ({type(taken[name]).__qualname__} and "
                f"{type(f).__qualname__})", "give each flow its own name with flow.configure(name=...)"))
        taken[name] = f
        ids[id(f)] = name
    for f in flows:
        if id(f) in ids:
            continue
        base = snake_case(type(f).__name__)
        if base.endswith("_flow") and base != "_flow":
            base = base[: -len("_flow")]
        base = base or "flow"
        name, n = base[:NAME_MAX], 1  # a long class name cut to a node id's length
        while name in taken:
            n += 1
            name = f"{base[:NAME_MAX - len(str(n)) - 1]}_{n}"
        taken[name] = f
        ids[id(f)] = name
    return ids


def compile_graph(name: str, flows: list[Flow], declared: list["DeclaredEdge"], max_microsteps: int = 1000,
                  realtime: str = "soft", deadline: float = 0.1) -> Graph:
    problems: list[Problem] = []
    warnings: list[str] = []
    declaration_warnings: list[str] = []
    ids = _assign_ids(flows, problems)

    nodes: dict[str, Node] = {}
    for f in flows:
        spec = flow_spec(type(f))
        node_id = ids[id(f)]
        if node_id in nodes:
            continue  # a duplicate name, already reported
        params, rebuild_problem, needs_main = constructor_params(f)
        nodes[node_id] = Node(node_id, f, spec, dict(spec.inputs),
                              dict(spec.outputs) if spec.outputs is not None else {}, params, rebuild_problem,
                              needs_main)
        where = f"flow '{node_id}' ({type_path(type(f))})"
        if not spec.has_step:
            problems.append(Problem(f"{where} has no step() method",
                                    "define step(self, inp) (typed) or step(self, port, ...) (untyped)"))
        for p in spec.problems:
            problems.append(Problem(f"{where}: {p}"))

    edges: list[Edge] = []
    for decl in declared:
        src, dst = nodes[ids[id(decl.src)]], nodes[ids[id(decl.dst)]]
        if src.flow is decl.src and dst.flow is decl.dst:  # else an endpoint's name is duplicated
            edges.extend(_resolve_edge(decl, src, dst, problems, declaration_warnings))

    # Untyped producers' output ports are the ones their edges name.
    for e in edges:
        src = nodes[e.src]
        if src.spec.outputs is None and e.src_port not in src.outputs:
            src.outputs[e.src_port] = PortSpec(e.src_port)

    _check_port_names(nodes, problems)
    _check_fan_in_and_duplicates(edges, problems)
    _check_clocks(nodes, edges, problems)
    edges = [_bind_policy(e, nodes[e.dst]) for e in edges]

    warnings.extend(_chunks_seen_a_microstep_late(nodes, edges))
    fed = {(e.dst, e.dst_port) for e in edges}
    for node in nodes.values():
        for port, spec in node.inputs.items():
            if spec.required and (node.id, port) not in fed:
                warnings.append(f"input port {node.id}.{port} has no incoming edge and no default: "
                                f"every tick of '{node.id}' will be skipped (connect it, or give it a default)")
        clock = node.settings.clock
        if clock is not None and clock.triggered and clock.hz is None and node.inputs:
            watched = clock.trigger_ports or tuple(node.inputs)
            if not any((node.id, p) in fed for p in watched):
                warnings.append(f"'{node.id}' is clocked by {clock!r} but nothing feeds "
                                f"{'its inputs' if not clock.trigger_ports else ', '.join(node.id + '.' + p for p in watched)}, "
                                "so it never ticks (connect a trigger port, or clock it with Rate/Hybrid)")

    if problems:
        raise GraphError(name, problems)

    order = list(nodes)
    succ: dict[str, list[str]] = {n: [] for n in order}
    inst: dict[str, list[str]] = {n: [] for n in order}
    for e in edges:
        succ[e.src].append(e.dst)
        if e.delay_ns == 0 and nodes[e.src].settings.latency_ns == 0 and nodes[e.dst].triggers_on(e.dst_port):
            inst[e.src].append(e.dst)
    cycles = elementary_cycles(succ, order)
    instantaneous = elementary_cycles(inst, order)
    for c in instantaneous:
        loop = " → ".join(c + c[:1])
        warnings.append(
            f"instantaneous cycle {loop}: every link is a zero-latency, undelayed edge into a trigger port, "
            f"so it runs in microsteps within one instant and stops with an error past "
            f"max_microsteps={max_microsteps} (fix: latency=, delay=, or a Rate clock on the cycle)")
    return Graph(name, nodes, edges, max_microsteps, realtime, deadline, cycles, instantaneous, warnings,
                 declaration_warnings)


def _check_port_names(nodes: dict[str, Node], problems: list[Problem]) -> None:
    """Every port name one segment (ir.PORT_NAME): an untyped flow's outputs are the keys its step()
    returns and its edges' ``map=`` names, any str; one holding '/' was lost from the log's views.
    No input port named as a step record's detail key (trace.DETAIL_KEYS)."""
    for node in nodes.values():
        returned = node.spec.returned_keys or frozenset()
        for kind, ports in (("input", set(node.inputs)), ("output", set(node.outputs) | returned)):
            for port in sorted(ports, key=str):
                problem = port_name_problem(port)
                if problem is not None:
                    fix = re.sub(r"[^A-Za-z0-9_\-]", "_", str(port))
                    fix = fix if re.match(r"[A-Za-z_]", fix) else f"p_{fix}"
                    problems.append(Problem(f"flow '{node.id}' ({type_path(type(node.flow))}): {kind} port {problem}",
                                            f"rename it, e.g. {fix!r}, in its step() and in the edges' map="))
                elif kind == "input" and port in DETAIL_KEYS:
                    problems.append(Problem(
                        f"flow '{node.id}' ({type_path(type(node.flow))}): input port '{port}' has the name of a "
                        f"step record's detail key (a Queue's drop count is logged under its input port's name, "
                        f"where it would take the place of the record's own '{port}')",
                        f"rename it, e.g. '{port}_in', in its step() and in the edges' map="))


def _ports_list(ports: dict[str, PortSpec]) -> str:
    return ", ".join(sorted(ports)) or "(none)"


def _resolve_edge(decl: "DeclaredEdge", src: Node, dst: Node, problems: list[Problem],
                  warnings: list[str]) -> list[Edge]:
    label = f"edge {src.id} → {dst.id}" + (f" ({decl.where})" if decl.where else "")
    if dst.spec.is_source:
        problems.append(Problem(f"{label}: '{dst.id}' is a source (it has no input ports)",
                                "connect into a flow whose step() takes inputs"))
        return []
    if decl.map is not None:
        pairs = _mapped_pairs(decl.map, src, dst, label, problems)
    elif src.spec.outputs is None:
        pairs = _untyped_pairs(src, dst, label, problems, warnings)
    else:
        pairs = _typed_pairs(src, dst, decl.sync, label, problems, warnings)
    return _checked_edges(decl, src, dst, pairs, label, problems)


def _mapped_pairs(port_map: dict[str, str], src: Node, dst: Node, label: str,
                  problems: list[Problem]) -> list[tuple[str, str]]:
    """The (output, input) pairs an edge's ``map=`` names, those that name ports that exist (for
    an untyped producer: a key its step() returns, where those are known)."""
    typed_src = src.spec.outputs is not None
    pairs: list[tuple[str, str]] = []
    for out_port, in_port in port_map.items():
        ok = True
        if typed_src and out_port not in src.outputs:
            problems.append(Problem(
                f"{label}: map names output port '{out_port}', but {src.id} has no such output "
                f"(outputs: {_ports_list(src.outputs)})", "map goes {output_port: input_port}"))
            ok = False
        elif not typed_src and src.spec.returned_keys is not None and out_port not in src.spec.returned_keys:
            returned = ", ".join(f"'{k}'" for k in sorted(src.spec.returned_keys)) or "no port"
            problems.append(Problem(
                f"{label}: map names output port '{out_port}', but {src.id} is untyped and its step() "
                f"returns {returned}, never '{out_port}': {dst.id}.{in_port} would never get an event",
                "map goes {output_port: input_port}; name a key its step() returns"))
            ok = False
        if in_port not in dst.inputs:
            problems.append(Problem(
                f"{label}: map names input port '{in_port}', but {dst.id} has no such input "
                f"(inputs: {_ports_list(dst.inputs)})", "map goes {output_port: input_port}"))
            ok = False
        if ok:
            pairs.append((out_port, in_port))
    return pairs


def _untyped_pairs(src: Node, dst: Node, label: str, problems: list[Problem],
                   warnings: list[str]) -> list[tuple[str, str]]:
    """The pairs an edge from an untyped producer without ``map=`` feeds: the consumer's one
    input, or the inputs named as keys its step() returns; none where that is ambiguous or a
    required input would never get an event."""
    pairs: list[tuple[str, str]] = []
    if len(dst.inputs) == 1:
        (port,) = dst.inputs
        returned = src.spec.returned_keys
        if returned is not None and port not in returned:  # its step never returns that key
            shown = ", ".join(f"'{k}'" for k in sorted(returned)) or "no port"
            fix = (f"{src.id}.then({dst.id}, map={{'{sorted(returned)[0]}': '{port}'}})" if len(returned) == 1
                   else f"map={{'<one of its keys>': '{port}'}}")
            text = (f"{label}: {src.id} is untyped and its step() returns {shown}, never '{port}', the port "
                    f"of {dst.id} this edge feeds by name: {dst.id}.{port} would never get an event")
            if dst.inputs[port].required:
                problems.append(Problem(text, f"say which output feeds it: {fix}"))
                return []
            warnings.append(f"{text} (it is optional: {dst.id} steps without it)\n    hint: {fix}")
        pairs.append((port, port))
    elif src.spec.returned_keys is not None and src.spec.returned_keys & set(dst.inputs):
        # its step's keys are known (dict literals): matched by name, as a typed producer's ports
        pairs = [(p, p) for p in dst.inputs if p in src.spec.returned_keys]
    else:
        known = src.spec.returned_keys is not None
        problems.append(Problem(
            f"{label}: {src.id} is untyped, so its outputs cannot be matched by name to "
            f"{dst.id}'s inputs ({_ports_list(dst.inputs)}); the match is ambiguous"
            + (f" (its step() returns {', '.join(repr(k) for k in sorted(src.spec.returned_keys)) or 'nothing'}, "
               "none of them an input's name)" if known else ""),
            f"pass map={{'<output>': '<input>'}} to say which port of {dst.id} it feeds"))
    return pairs


def _typed_pairs(src: Node, dst: Node, sync: SyncPolicy, label: str, problems: list[Problem],
                 warnings: list[str]) -> list[tuple[str, str]]:
    """The pairs an edge between typed ports without ``map=`` feeds: the ports named alike, else
    the one pair whose types fit (with a warning where the type says little)."""
    pairs: list[tuple[str, str]] = []
    common = [p for p in src.outputs if p in dst.inputs]
    if common:
        pairs = [(p, p) for p in common]
    else:
        candidates = [(o, i) for o, os in src.outputs.items() for i, is_ in dst.inputs.items()
                      if _fits_through(os.type, is_.type, sync)]
        if len(candidates) == 1:
            pairs = candidates
            (o, i), = candidates
            if not _distinctive(src.outputs[o].type, dst.inputs[i].type):
                # an image would feed an action port because both are arrays: say so
                warnings.append(
                    f"{label}: no port names in common, so {src.id}.{o} feeds {dst.id}.{i} because they are "
                    f"the only pair whose types fit ({src.outputs[o].type_name} → {dst.inputs[i].type_name}), "
                    f"a type that says little about what a port means\n"
                    f"    hint: if that is meant, say so: map={{'{o}': '{i}'}}; else name the ports alike")
        elif not candidates:
            problems.append(Problem(
                f"{label}: no output of {src.id} ({_ports_list(src.outputs)}) matches an input of "
                f"{dst.id} ({_ports_list(dst.inputs)}) by name or type",
                "pass map={'<output>': '<input>'}"))
        else:
            shown = ", ".join(f"{o}→{i}" for o, i in candidates)
            problems.append(Problem(
                f"{label}: ambiguous port matching: no names in common and several type-compatible "
                f"pairs ({shown})", "pass map={'<output>': '<input>'} to choose"))
    return pairs


def _checked_edges(decl: "DeclaredEdge", src: Node, dst: Node, pairs: list[tuple[str, str]], label: str,
                   problems: list[Problem]) -> list[Edge]:
    """An edge per pair whose output type fits its input through the edge's sync policy."""
    sync = decl.sync
    edges = []
    for out_port, in_port in pairs:
        out_spec = src.outputs.get(out_port)
        in_spec = dst.inputs[in_port]
        if out_spec is not None and not _fits_through(out_spec.type, in_spec.type, sync):
            expected = in_spec.type_name
            what = f"list of {out_spec.type_name}" if sync.delivers_list else out_spec.type_name
            problems.append(Problem(
                f"{label}: type mismatch on {src.id}.{out_port} → {dst.id}.{in_port}: the input expects "
                f"{expected}, the edge delivers {what}",
                "Window and Queue deliver lists" if sync.delivers_list else
                "fix one of the annotations, or route the port elsewhere with map="))
            continue
        edges.append(Edge(src.id, out_port, dst.id, in_port, sync, decl.delay, decl.qsize, decl.deadline))
    return edges


def _check_fan_in_and_duplicates(edges: list[Edge], problems: list[Problem]) -> None:
    by_port: dict[tuple[str, str], Edge] = {}
    seen: set[tuple[str, str, str, str]] = set()
    for e in edges:
        key = (e.src, e.src_port, e.dst, e.dst_port)
        if key in seen:
            problems.append(Problem(f"edge {e} is declared twice", "remove the duplicate connect/then"))
            continue
        seen.add(key)
        first = by_port.setdefault((e.dst, e.dst_port), e)
        if first is not e and first.sync != e.sync:
            problems.append(Problem(
                f"fan-in into {e.dst}.{e.dst_port} mixes sync policies: {first} uses {first.sync!r}, "
                f"{e} uses {e.sync!r}", "several producers into one port are merged by tag and "
                "sampled by one policy: give every edge into the port the same sync="))


def _check_clocks(nodes: dict[str, Node], edges: list[Edge], problems: list[Problem]) -> None:
    for node in nodes.values():
        clock = node.settings.clock
        if clock is None:
            problems.append(Problem(f"flow '{node.id}' has no clock",
                                    f"bind one: {type(node.flow).__name__}(...) @ Rate(hz=...) or @ Trigger(\"port\")"))
            continue
        for port in clock.trigger_ports:
            if port not in node.inputs:
                problems.append(Problem(
                    f"{clock!r} on '{node.id}': '{node.id}' has no input port '{port}' "
                    f"(inputs: {_ports_list(node.inputs)})", "trigger on one of the flow's input ports"))
        if clock.triggered and clock.hz is None and not node.inputs:
            problems.append(Problem(f"'{node.id}' is a source clocked by {clock!r}, so it never ticks",
                                    "clock a source with Rate(hz=...)"))
    for e in edges:
        if isinstance(e.sync, ActionChunking) and e.sync.control_hz is None and nodes[e.dst].clock is not None \
                and nodes[e.dst].clock.hz is None:
            problems.append(Problem(f"edge {e}: ActionChunking needs control_hz= because '{e.dst}' has no rate",
                                    "ActionChunking(control_hz=200, chunk_steps=...)"))


#: how many of a chunk producer's ticks are looked at for one that falls on a consumer's tick
CHUNK_PHASE_TICKS = 64


def _chunks_seen_a_microstep_late(nodes: dict[str, Node], edges: list[Edge]) -> list[str]:
    """ActionChunking edges whose chunks start at an instant the consumer ticks, a microstep too
    early to see them, and whose row 0 is then never taken. A zero-latency producer ticking at
    (t, 0) emits at (t, 1); the consumer's tick at (t, 0) still holds the previous chunk, and its
    next tick, at t', takes row floor((t' − t) · control_hz): 1 or more when control_hz is its
    own rate. It follows from the sampling rule (docs/semantics.md) and keeps each row at the time
    it was planned for, so it is warned of, not redefined."""
    found = []
    for e in edges:
        src, dst = nodes[e.src], nodes[e.dst]
        if not isinstance(e.sync, ActionChunking) or e.sync.control_hz is None or src.settings.latency_ns or e.delay_ns:
            continue
        hz = exact_rational(e.sync.control_hz)  # bound to the consumer's rate by now, or given
        made, taken = src.settings.clock, dst.settings.clock
        if not hasattr(made, "tick_time") or not hasattr(taken, "tick_time"):
            continue
        for k in range(CHUNK_PHASE_TICKS):
            t = made.tick_time(k)
            j = taken.first_tick_at_or_after(t)
            if taken.tick_time(j) == t and (taken.tick_time(j + 1) - t) * hz.numerator >= NS_PER_S * hz.denominator:
                found.append(
                    f"edge {e}: {e.src} has no latency and ticks when {e.dst} ticks (first at {t / 1e9:g} s): a "
                    f"chunk made at such a tick is emitted a microstep after the {e.dst} tick at its start, which "
                    f"still takes the previous chunk, and the next tick takes row 1; row 0 of those chunks is never "
                    f"executed\n"
                    f"    hint: give {e.src} a latency of one control period or more ({e.src}.configure("
                    f"latency=...)): its chunks then start at a tick of {e.dst} that sees them")
                break
    return found


def _bind_policy(edge: Edge, dst: Node) -> Edge:
    if isinstance(edge.sync, ActionChunking) and edge.sync.control_hz is None and dst.clock is not None:
        hz = getattr(dst.clock, "hz_value", None)
        edge.sync = edge.sync.bound_to_rate(hz)
    return edge


# ---------------------------------------------------------------------------------------------
# The graph as an IR document
# ---------------------------------------------------------------------------------------------
def graph_to_doc(graph: Graph) -> dict:
    """The IR document of a compiled graph (``Graph.to_ir``; ``retriever.ir`` validates and reads it)."""
    nodes = []
    for node in graph.nodes.values():
        s = node.settings
        doc = {
            "id": node.id,
            "type": f"{type(node.flow).__module__}:{type(node.flow).__qualname__}",
            "params": node.params,
            "config": {
                "clock": s.clock.to_ir(),
                "latency": s.latency,
                "on_error": s.on_error,
                "on_overrun": s.on_overrun,
                "on_deadline_miss": s.on_deadline_miss,
                # the restart budget, where it applies
                **({"max_restarts": s.max_restarts, "restart_window": s.restart_window}
                   if s.on_error == "restart" else {}),
                **({"replay": s.replay} if s.replay != "rerun" else {}),
                **({"spin": s.spin} if s.spin else {}),
                **({"process": s.process} if s.process else {}),
            },
            "inputs": {p: spec.type_name for p, spec in node.inputs.items()},
            "outputs": {p: spec.type_name for p, spec in node.outputs.items()},
            "rebuildable": node.rebuild_problem is None,
        }
        if node.rebuild_problem is not None:
            doc["rebuild_problem"] = node.rebuild_problem
        if node.rebuild_needs_main:
            doc["rebuild_needs_main"] = True
        nodes.append(doc)
    edges = [
        {
            "source": {"node": e.src, "port": e.src_port},
            "destination": {"node": e.dst, "port": e.dst_port},
            "adapter": e.sync.to_ir(),
            "qsize": e.qsize,
            "delay": e.delay,
            "deadline": e.deadline,
        }
        for e in graph.edges
    ]
    metadata = {
        "name": graph.name,
        "validated": True,
        "optimized": False,
        "max_microsteps": graph.max_microsteps,
        "realtime": graph.realtime,
        "deadline": graph.deadline,
        "warnings": list(graph.warnings),
    }
    modules = [type(node.flow).__module__ for node in graph.nodes.values()]
    folders = _script_folders(modules)
    if folders:
        metadata["module_folders"] = folders
    metadata["code_sha256"] = code_hashes(modules)
    return {
        "version": IR_VERSION,
        "metadata": metadata,
        "nodes": nodes,
        "edges": edges,
        "topology": {
            "node_count": len(graph.nodes),
            "edge_count": len(graph.edges),
            "has_cycle": bool(graph.cycles),
            "cycles": graph.cycles,
            "instantaneous_cycles": graph.instantaneous_cycles,
        },
    }


def _script_folders(modules) -> dict[str, str]:
    """``{module: folder}`` for the modules Retriever imported from script files: a module that the
    import path does not hold by itself (``retriever run q.json`` adds the folder back)."""
    folders = {}
    for name in modules:
        folder = getattr(sys.modules.get(name), SCRIPT_FOLDER_ATTR, None)
        if isinstance(folder, str):
            folders[name] = folder
    return dict(sorted(folders.items()))
