"""The real-time backend over Eclipse Zenoh (DESIGN.md §5, §7): one OS process per flow.

    wire.py     key space and msgpack envelopes
    access.py   who may join a run (Zenoh authentication) and what a watcher may do (access control)
    hub.py      peer sessions: the run's hub and the workers joining it
    loop.py     one node's real-time loop (frontiers, deadlines, LET, overruns, restarts)
    worker.py   the worker process around a loop
    session.py  the coordinator: starts workers, agrees on T0, collects the trace and the log
    output.py   what workers print, on the coordinator's streams, prefixed with the node
    daemon.py   a long-lived worker daemon (retriever-worker) and listing them (retriever workers)
"""

from __future__ import annotations

from ...errors import BackendError
from ...graph import Graph
from ..base import Backend


class ZenohBackend(Backend):
    name = "zenoh"
    OPTIONS = ("namespace", "startup_timeout", "start_margin", "hub_port", "quiet", "secret")

    def open(self, graph: Graph, **options: object):
        unknown = sorted(set(options) - set(self.OPTIONS))
        if unknown:
            raise BackendError(f"the zenoh backend takes no options {unknown} (it accepts {', '.join(self.OPTIONS)})")
        from .session import ZenohSession

        return ZenohSession(graph, **options)
