"""A pipeline's IR compiled to a dora dataflow descriptor: one dora node per process (a flow's,
or a group's: ``configure(process=NAME)``).

    nodes:
      - id: camera                       # the flow's node id (ids dora refuses are renamed n0, n1, ...)
        path: /…/python                  # the coordinator's interpreter
        args: -m retriever.backends.dora.node /dev/shm/retriever-run-…/spec.json camera
        outputs: [image, progress, warm] # one output per output port, its progress (frontiers), and
                                         # its warm-up messages (WARM)
      - id: policy
        …
        inputs:
          camera__image: {source: camera/image, queue_size: 100000, queue_policy: backpressure}
          camera__progress: {source: camera/progress, queue_size: 100000, queue_policy: backpressure}
          camera__warm: {source: camera/warm, queue_size: 100000, queue_policy: backpressure}

Each node is a Retriever worker process (the flow rebuilt from the IR), as on the zenoh backend,
started through node.py;
its events and its progress messages go to its consumers over dora. A group's dora node (its id
the group's name) is its members' one process: its outputs are ``MEMBER__PORT`` for the ports a
node outside the group consumes, and ``MEMBER__progress``; its inputs, the streams its members
consume from outside (one input for a stream two members consume). What goes between members
is no dora route: it stays in the process (backends/zenoh/node/group.py). A dropped event would leave
a gap in its stream that no frontier crosses, so every input is ``queue_policy: backpressure``
with a long queue. Dora's default route (straight between the nodes, drop-oldest) can lose
messages of a fast stream with no warning, the last progress message of a producer among them,
so that its consumer would wait out its deadline. A backpressure input goes through dora's
daemon and loses none, with blocking or timed-out ``next()`` alike. Dora still drops at ten
times the queue (a million events here), with an error in its log.

:class:`DoraNames` is the mapping both sides use: the descriptor's ids, and, in the worker,
which dora output carries which port and which input brings which stream.
"""

from __future__ import annotations

import json
import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

from ..zenoh.command import DORA_NODE_MODULE, worker_command
from ..zenoh.protocol import DoraPart

#: the output each node's progress messages go on (a port of that name is renamed)
PROGRESS = "progress"
#: the output a node whose events are heard puts an empty message on before a moment it foresees
#: (node/timing.py: Warmup); each consumer takes it on an input of its own, over the route its events
#: take, and rehearses their arrival at it (DoraNames.warm_inputs; link.py); renamed ``warm_1``, …
#: past its dora node's other outputs
WARM = "warm"
#: an input's queue (dora drops past ten times that with backpressure: see the module docstring)
QUEUE_SIZE = 100_000

_DORA_ID = re.compile(r"^[A-Za-z][A-Za-z0-9_-]{0,63}$")


@dataclass(frozen=True)
class DoraNames:
    """The dora ids of a run: per node, its dora node's id, its outputs by port, its progress
    output, and its inputs by stream. A group's members (``configure(process=)``) share one dora
    node: each has outputs only for the ports a node outside the group consumes, and inputs only
    from nodes outside it (what goes between members stays in their process: node/group.py). A
    group of one (a flow alone with on_error="restart": DoraHosting.groups_of_one) is named as
    the lone flow it is: its outputs ``PORT`` and ``progress``."""

    nodes: dict[str, str]                       # node id -> dora node id
    outputs: dict[str, dict[str, str]]          # node id -> {port: dora output id}
    progress: dict[str, str]                    # node id -> its progress's dora output id (if heard over dora)
    inputs: dict[str, dict[str, list]]          # node id -> {dora input id: [producer, port or None]}

    @classmethod
    def of(cls, ir_doc: dict, groups: Mapping[str, Sequence[str]] | None = None) -> "DoraNames":
        """The ids of the IR ``ir_doc``'s nodes, ``groups`` (the run spec's: name -> members)
        each one dora node."""
        group_of = {nid: name for name, members in (groups or {}).items() for nid in members}
        nodes, by_group, used = {}, {}, set()
        for i, node in enumerate(ir_doc["nodes"]):
            nid = node["id"]
            group = group_of.get(nid)
            if group in by_group:
                nodes[nid] = by_group[group]
                continue
            name = nid if group is None else group
            nodes[nid] = _unique(name if name != "dora" else "", used, f"n{i}")
            if group is not None:
                by_group[group] = nodes[nid]
        crossing = [e for e in ir_doc["edges"]
                    if e["source"]["node"] not in group_of
                    or group_of[e["source"]["node"]] != group_of.get(e["destination"]["node"])]
        heard = {e["source"]["node"] for e in crossing}
        outputs, progress, taken = {}, {}, {}
        for i, node in enumerate(ir_doc["nodes"]):
            nid = node["id"]
            own: set[str] = set()
            ports = {port: _unique(port if port != PROGRESS else "", own, f"o{j}")
                     for j, port in enumerate(sorted(node["outputs"]))}
            if nid not in group_of or len(groups[group_of[nid]]) == 1:  # (a group of one's, as a lone node's)
                outputs[nid] = ports
                if nid in heard:
                    progress[nid] = PROGRESS
                continue
            # a member's outputs in its group's dora node: named by member and port, unique there
            used = taken.setdefault(nodes[nid], set())
            member = nid if _DORA_ID.match(nid) else f"n{i}"
            remote = {e["source"]["port"] for e in crossing if e["source"]["node"] == nid}
            outputs[nid] = {port: _unique(f"{member}__{ports[port]}", used, f"o{i}_{j}")
                            for j, port in enumerate(sorted(node["outputs"])) if port in remote}
            if nid in heard:
                progress[nid] = _unique(f"{member}__{PROGRESS}", used, f"p{i}")
        inputs: dict[str, dict[str, list]] = {nid: {} for nid in nodes}
        # per dora node, its input per stream: PRODUCER__OUTPUT, which two streams may both be named
        # (node a's output b__c and node a__b's c): the second is i0, i1, … (no '__': no clash)
        input_ids: dict[str, dict[tuple, str]] = {}
        for e in crossing:
            src, port, dst = e["source"]["node"], e["source"]["port"], e["destination"]["node"]
            if port not in outputs[src]:  # an untyped flow's port: the IR lists every port an edge names
                raise ValueError(f"edge from {src}.{port}: no such output port in the IR")
            ids = input_ids.setdefault(nodes[dst], {})
            for stream, output in (((src, port), outputs[src][port]), ((src, None), progress[src])):
                if stream not in ids:
                    wanted = f"{nodes[src]}__{output}"
                    ids[stream] = wanted if wanted not in ids.values() else f"i{len(ids)}"
                inputs[dst][ids[stream]] = list(stream)
        return cls(nodes, outputs, progress, inputs)

    def warm(self, dora_id: str) -> str | None:
        """The dora node ``dora_id``'s warm-up output (WARM), if one of its nodes is heard over
        dora (it has a progress output); else None. Derived from the other ids, by both sides."""
        members = self.members(dora_id)
        if not any(nid in self.progress for nid in members):
            return None
        taken = {o for nid in members for o in (*self.outputs[nid].values(), self.progress.get(nid))}
        return _unique(WARM, taken, WARM)

    def warm_inputs(self, dora_id: str) -> dict[str, list[str]]:
        """The dora node ``dora_id``'s warm-up inputs: per producing dora node it hears events of
        (through a progress input) that has a warm-up output (:meth:`warm`), one input taking
        that output, and the producers whose warm-ups it brings (the members of that node this
        one hears). Named ``PRODUCER__WARM``, or ``w0``, ``w1``, … past this node's other inputs.
        Derived from the other ids, by both sides."""
        members = self.members(dora_id)
        heard: dict[str, list[str]] = {}  # producing dora node -> its members heard here
        for nid in members:
            for src, port in self.inputs[nid].values():
                if port is None and src not in heard.setdefault(self.nodes[src], []):
                    heard[self.nodes[src]].append(src)
        taken = {input_id for nid in members for input_id in self.inputs[nid]}
        warm_inputs = {}
        for k, producer in enumerate(sorted(heard)):
            warm = self.warm(producer)
            if warm is not None:
                warm_inputs[_unique(f"{producer}__{warm}", taken, f"w{k}")] = sorted(heard[producer])
        return warm_inputs

    def processes(self, groups: Mapping[str, Sequence[str]]) -> dict[str, str]:
        """Each process's dora node id: a node's own by its id, a group's by its name."""
        grouped = {nid for members in groups.values() for nid in members}
        return {**{nid: did for nid, did in self.nodes.items() if nid not in grouped},
                **{name: self.nodes[members[0]] for name, members in groups.items()}}

    def members(self, dora_id: str) -> list[str]:
        """The node ids whose dora node is ``dora_id`` (a worker's argument): one, or a group's."""
        return [nid for nid, did in self.nodes.items() if did == dora_id]

    def part(self, *, cwd: str, coordinator: int, dir: str, keys: dict[str, bytes]) -> DoraPart:
        """The run's spec's dora part (protocol.DoraPart): these ids, and what a node's process
        is told of the coordinator (its working directory, its pid, dora's directory, the keys)."""
        return DoraPart(nodes=dict(self.nodes), outputs={nid: dict(ports) for nid, ports in self.outputs.items()},
                        inputs={nid: {input_id: tuple(stream) for input_id, stream in inputs.items()}
                                for nid, inputs in self.inputs.items()},
                        progress=dict(self.progress), cwd=cwd, coordinator=coordinator, dir=dir, keys=dict(keys))

    @classmethod
    def of_part(cls, part: DoraPart) -> "DoraNames":
        """The ids a run's spec's dora part holds (:meth:`part`)."""
        return cls(dict(part.nodes), {nid: dict(ports) for nid, ports in part.outputs.items()}, dict(part.progress),
                   {nid: {input_id: list(stream) for input_id, stream in inputs.items()}
                    for nid, inputs in part.inputs.items()})


def _unique(name: str, used: set[str], fallback: str) -> str:
    """``name`` if dora takes it and it is not ``used`` yet, else ``fallback`` (``fallback_1``, …
    if a name taken before is ``fallback`` already); marked used."""
    chosen = name if _DORA_ID.match(name) and name not in used else fallback
    k = 0
    while chosen in used:
        k += 1
        chosen = f"{fallback}_{k}"
    used.add(chosen)
    return chosen


def dataflow_yaml(name: str, names: DoraNames, python: str, spec_path: str, pythonpath: str) -> str:
    """The dataflow descriptor (YAML; scalars written as JSON strings, which YAML reads alike)."""
    q = json.dumps
    lines = [f"# Retriever pipeline {q(name)} as a dora dataflow: one node per process (a flow's, or a group's),",
             "# each a Retriever worker (its flows rebuilt from the IR in spec.json); events and progress go over "
             "dora.", "nodes:"]
    for dora_id in dict.fromkeys(names.nodes.values()):
        members = names.members(dora_id)
        outputs = []
        for nid in members:
            outputs += [*names.outputs[nid].values(), *([names.progress[nid]] if nid in names.progress else [])]
        warm = names.warm(dora_id)
        outputs += [warm] if warm is not None else []
        # a group's members consuming one stream: one input of their dora node
        inputs = {input_id: stream for nid in members for input_id, stream in names.inputs[nid].items()}
        path, *args = worker_command(spec_path, dora_id, module=DORA_NODE_MODULE, python=python)
        lines += [f"  - id: {q(dora_id)}",
                  f"    path: {q(path)}",
                  f"    args: {q(' '.join(args))}",
                  "    env:",
                  f"      PYTHONPATH: {q(pythonpath)}",
                  f"    outputs: [{', '.join(q(o) for o in outputs)}]"]
        if inputs:
            lines.append("    inputs:")
            for input_id, (src, port) in inputs.items():
                output = names.progress[src] if port is None else names.outputs[src][port]
                lines.append(f"      {q(input_id)}: {{source: {q(names.nodes[src] + '/' + output)}, "
                             f"queue_size: {QUEUE_SIZE}, queue_policy: backpressure}}")
            # each producer's warm-up messages, on the route its events take (link.py: warmed)
            for input_id, producers in names.warm_inputs(dora_id).items():
                source = names.nodes[producers[0]]
                lines.append(f"      {q(input_id)}: {{source: {q(source + '/' + names.warm(source))}, "
                             f"queue_size: {QUEUE_SIZE}, queue_policy: backpressure}}")
    return "\n".join(lines) + "\n"
