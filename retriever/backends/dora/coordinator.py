"""The coordinator of a run on dora: the zenoh backend's, whose workers dora starts and connects.

    pipe.run(duration=10, backend="dora")
        │ open the run's private Zenoh hub (the control plane), write spec.json and dataflow.yml
        │ `dora run dataflow.yml` ──▶ one worker per flow, each a dora node, says `ready`
        │ put `start` {T0, end}; the workers' events and progress go to each other over dora
        │ collect their reports (step records, events) into the trace and the log
        ▼ every worker says `done` → dora run ends; the hub closes

What dora cannot do here is refused before anything starts: a flow that restarts in a new
process (on_error="restart": dora started the dataflow's processes once) and lockstep virtual
time (use inproc or zenoh's ``virtual_time=True``).
"""

from __future__ import annotations

import json
import os
import sys
from pathlib import Path

from ...errors import BackendError
from ...graph import Graph
from ..zenoh.access import write_private
from ..zenoh.coordinator import Coordinator
from ..zenoh.host import Host
from .dataflow import DoraNames, dataflow_yaml
from .host import DoraHost, dora_command


class DoraCoordinator(Coordinator):
    backend_name = "dora"

    def __init__(self, graph: Graph, **options):
        restarting = sorted(nid for nid, node in graph.nodes.items() if node.settings.on_error == "restart")
        if restarting:
            raise BackendError(f"the dora backend cannot restart a flow in a new process (on_error='restart' on "
                               f"{', '.join(restarting)}): dora starts the dataflow's processes once\n"
                               "    hint: use on_error='skip_tick' or 'stop', or run on backend='zenoh'")
        dora_command()  # installed? (before any process starts)
        self._dora: DoraHost | None = None
        super().__init__(graph, **options)

    def _where(self) -> str:
        return f"dora dataflow {self._dir / 'dataflow.yml'}, control on the Zenoh hub at {self.endpoint}"

    def _how_to_watch(self) -> str:
        return ("its events go between the flows over dora, not Zenoh: watch it live with foxglove=PORT, "
                "or read its log")

    def _place(self) -> dict[str, Host]:
        names = DoraNames.of(self._spec["ir"])
        self._spec["dora"] = {**names.to_spec(), "cwd": os.getcwd()}
        spec_path = write_private(self._dir / "spec.json", json.dumps(self._spec))  # it holds the run's password
        package_root = str(Path(__file__).resolve().parents[3])  # the workers run this copy of retriever
        dataflow = self._dir / "dataflow.yml"
        dataflow.write_text(dataflow_yaml(self.graph.name, names, sys.executable, str(spec_path), package_root))
        self._dora = DoraHost(dataflow, names.nodes)
        return {nid: self._dora for nid in self.graph.nodes}

    def _release_hosts(self) -> None:
        if self._dora is not None:
            self._dora.stop()

    def _stderr_tail(self, nid: str, lines: int = 15) -> str:
        tail = super()._stderr_tail(nid, lines)
        if not tail.strip() and self._dora is not None and self._dora.tail:  # it never started: dora says why
            tail = "\n".join("        " + line for line in list(self._dora.tail)[-lines:])
        return tail

