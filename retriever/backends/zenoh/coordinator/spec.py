"""What a run's workers are told of it: the run's directory, the import path of its flows, and its wiring."""

from __future__ import annotations

import os
import sys
from collections.abc import Mapping
from pathlib import Path

from ....errors import BackendError
from ....graph import Graph
from ....plan import plan_graph
from ..folders import RUN_FOLDER, private_folder


def run_dir() -> Path:
    """The run's directory: the spec and big events on their way to the
    coordinator. In shared memory when the host has it (no disk I/O for those events)."""
    shm = Path("/dev/shm")
    base = str(shm) if shm.is_dir() and os.access(shm, os.W_OK | os.X_OK) else None
    return private_folder(RUN_FOLDER, base)  # named by pid: a SIGKILLed run's is reaped by the next


def python_path() -> list[str]:
    """The import path the flows came from, for the workers (absolute directories only)."""
    out = []
    for entry in sys.path:
        path = os.path.abspath(entry or ".")
        if os.path.isdir(path) and path not in out:
            out.append(path)
    return out


def main_file(graph: Graph) -> str | None:
    """The ``__main__`` script, when some flow class is defined in it."""
    if not any(type(n.flow).__module__ == "__main__" for n in graph.nodes.values()):
        return None
    path = getattr(sys.modules.get("__main__"), "__file__", None)
    if path is None:
        raise BackendError("a flow class is defined in an interactive __main__, which worker processes cannot "
                           "import\n    hint: move the flow classes to a module or a script file")
    return os.path.abspath(path)


def process_groups(graph: Graph, named: Mapping[str, str] | None = None) -> dict[str, list[str]]:
    """The groups of flows that share a worker process (``configure(process=NAME)``, or ``named``:
    a process name by node that wins over the flow's, a deployment's placement file): name -> its
    nodes, in the graph's order. A name only one flow has is no group (that flow runs alone). A
    member with ``on_error="restart"`` restarts in place, in the group's process
    (node/in_place.py). A group named as a node outside it is refused: what a process prints is
    told under its name (host.share_output), so its lines would show as that node's."""
    groups: dict[str, list[str]] = {}
    for nid, node in graph.nodes.items():
        process = (named or {}).get(nid, node.settings.process)
        if process is not None:
            groups.setdefault(process, []).append(nid)
    groups = {name: nodes for name, nodes in groups.items() if len(nodes) > 1}
    clashes = [f"process '{name}' (flows {', '.join(repr(n) for n in nodes)}) has the name of node '{name}', which "
               "is not one of them: what the process prints would show as that node's"
               for name, nodes in groups.items() if name in graph.nodes and name not in nodes]
    if clashes:
        raise BackendError("\n".join(clashes) + '\n    hint: give the process another name (configure(process=), '
                           'or process = "NAME" in a placement file)')
    return groups


def shipped_plan(graph: Graph) -> dict:
    """The run's wiring, node by node (retriever.plan), as JSON-safe data: made once here, the
    authority of the run, and wired by every worker as it says (each checks it against the IR)."""
    return plan_graph(graph).to_data()
