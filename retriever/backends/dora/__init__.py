"""The dora backend (the seed paper's ``pipe.run(backend="dora")``): the pipeline compiled to a
dora dataflow, run by dora's own runtime (the ``dora-rs`` and ``dora-rs-cli`` packages).

    dataflow.py     the IR as a dora dataflow descriptor (YAML): one node per flow, or group of flows
    link.py         a worker's events and progress over dora (one DoraLink per process)
    node.py         a dora node's process: the zenoh worker's phases (a group's too), on that link
    host.py         ``dora run`` starting the workers, and what they print
    coordinator.py  the zenoh backend's coordinator, handed a hosting (DoraHosting) whose workers
                    ``dora run`` starts: T0, reports, the trace, the log as on zenoh

Each flow runs in its own process, rebuilt from the IR, with the same loop as on the zenoh
backend (clocks, sync policies, deadlines, LET, step records: the same trace and the same log);
only the events between flows travel over dora. Flows given one ``configure(process=NAME)``
share one process, one dora node, served by the zenoh backend's group worker (their events
between them by reference, in the process). A flow with ``on_error="restart"`` restarts in
place, in its process (dora starts them once): a group's member in its group's, a flow alone as
a group of one (coordinator.py). The run's control plane (start, stop, reports,
frontier queries) stays on its private Zenoh hub.
"""

from __future__ import annotations

from ...errors import BackendError
from ...graph import Graph
from ..base import Backend


class DoraBackend(Backend):
    name = "dora"
    OPTIONS = ("namespace", "startup_timeout", "start_margin", "hub_port", "quiet", "secret", "keep", "foxglove",
               "rerun")

    def open(self, graph: Graph, **options: object):
        unknown = sorted(set(options) - set(self.OPTIONS))
        if unknown:
            hint = (" (lockstep virtual time is the zenoh backend's: backend='zenoh', virtual_time=True)"
                    if "virtual_time" in unknown else "")
            raise BackendError(f"the dora backend takes no options {unknown} (it accepts "
                               f"{', '.join(self.OPTIONS)}){hint}")
        from .coordinator import open_coordinator

        return open_coordinator(graph, **options)
