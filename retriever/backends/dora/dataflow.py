"""A pipeline's IR compiled to a dora dataflow descriptor: one dora node per flow.

    nodes:
      - id: camera                       # the flow's node id (ids dora refuses are renamed n0, n1, ...)
        path: /…/python                  # the coordinator's interpreter
        args: -m retriever.backends.dora.node /dev/shm/retriever-run-…/spec.json camera
        outputs: [image, progress]       # one output per output port, and its progress (frontiers)
      - id: policy
        …
        inputs:
          camera__image: {source: camera/image, queue_size: 100000, queue_policy: backpressure}
          camera__progress: {source: camera/progress, queue_size: 100000, queue_policy: backpressure}

Each node is a Retriever worker process (the flow rebuilt from the IR), as on the zenoh backend,
started through node.py;
its events and its progress messages go to its consumers over dora. A dropped event would leave
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
from dataclasses import dataclass

from ..zenoh.command import DORA_NODE_MODULE, worker_command
from ..zenoh.protocol import DoraPart

#: the output each node's progress messages go on (a port of that name is renamed)
PROGRESS = "progress"
#: an input's queue (dora drops past ten times that with backpressure: see the module docstring)
QUEUE_SIZE = 100_000

_DORA_ID = re.compile(r"^[A-Za-z][A-Za-z0-9_-]{0,63}$")


@dataclass(frozen=True)
class DoraNames:
    """The dora ids of a run: per node, its id, its outputs by port, and its inputs by stream."""

    nodes: dict[str, str]                       # node id -> dora node id
    outputs: dict[str, dict[str, str]]          # node id -> {port: dora output id}
    inputs: dict[str, dict[str, list]]          # node id -> {dora input id: [producer, port or None]}

    @classmethod
    def of(cls, ir_doc: dict) -> "DoraNames":
        nodes, outputs = {}, {}
        for i, node in enumerate(ir_doc["nodes"]):
            nid = node["id"]
            nodes[nid] = nid if _DORA_ID.match(nid) and nid != "dora" else f"n{i}"
            outputs[nid] = {port: port if _DORA_ID.match(port) and port != PROGRESS else f"o{j}"
                            for j, port in enumerate(sorted(node["outputs"]))}
        inputs: dict[str, dict[str, list]] = {nid: {} for nid in nodes}
        for e in ir_doc["edges"]:
            src, port, dst = e["source"]["node"], e["source"]["port"], e["destination"]["node"]
            if port not in outputs[src]:  # an untyped flow's port: the IR lists every port an edge names
                raise ValueError(f"edge from {src}.{port}: no such output port in the IR")
            inputs[dst][f"{nodes[src]}__{outputs[src][port]}"] = [src, port]
            inputs[dst][f"{nodes[src]}__{PROGRESS}"] = [src, None]
        return cls(nodes, outputs, inputs)

    def node_of(self, dora_id: str) -> str:
        """The node id whose dora node is ``dora_id`` (a worker's argument)."""
        return next(nid for nid, did in self.nodes.items() if did == dora_id)

    def part(self, *, cwd: str, coordinator: int, dir: str, keys: dict[str, bytes]) -> DoraPart:
        """The run's spec's dora part (protocol.DoraPart): these ids, and what a node's process
        is told of the coordinator (its working directory, its pid, dora's directory, the keys)."""
        return DoraPart(nodes=dict(self.nodes), outputs={nid: dict(ports) for nid, ports in self.outputs.items()},
                        inputs={nid: {input_id: tuple(stream) for input_id, stream in inputs.items()}
                                for nid, inputs in self.inputs.items()},
                        cwd=cwd, coordinator=coordinator, dir=dir, keys=dict(keys))

    @classmethod
    def of_part(cls, part: DoraPart) -> "DoraNames":
        """The ids a run's spec's dora part holds (:meth:`part`)."""
        return cls(dict(part.nodes), {nid: dict(ports) for nid, ports in part.outputs.items()},
                   {nid: {input_id: list(stream) for input_id, stream in inputs.items()}
                    for nid, inputs in part.inputs.items()})


def dataflow_yaml(name: str, names: DoraNames, python: str, spec_path: str, pythonpath: str) -> str:
    """The dataflow descriptor (YAML; scalars written as JSON strings, which YAML reads alike)."""
    q = json.dumps
    lines = [f"# Retriever pipeline {q(name)} as a dora dataflow: one node per flow, each a Retriever worker",
             "# (the flow rebuilt from the IR in spec.json); events and progress go over dora.", "nodes:"]
    for nid, dora_id in names.nodes.items():
        outputs = [*names.outputs[nid].values()]
        consumed = any(src == nid for node_inputs in names.inputs.values() for src, _ in node_inputs.values())
        if consumed:
            outputs.append(PROGRESS)
        path, *args = worker_command(spec_path, dora_id, module=DORA_NODE_MODULE, python=python)
        lines += [f"  - id: {q(dora_id)}",
                  f"    path: {q(path)}",
                  f"    args: {q(' '.join(args))}",
                  "    env:",
                  f"      PYTHONPATH: {q(pythonpath)}",
                  f"    outputs: [{', '.join(q(o) for o in outputs)}]"]
        node_inputs = names.inputs[nid]
        if node_inputs:
            lines.append("    inputs:")
            for input_id, (src, port) in node_inputs.items():
                output = PROGRESS if port is None else names.outputs[src][port]
                lines.append(f"      {q(input_id)}: {{source: {q(names.nodes[src] + '/' + output)}, "
                             f"queue_size: {QUEUE_SIZE}, queue_policy: backpressure}}")
    return "\n".join(lines) + "\n"
