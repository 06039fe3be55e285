"""The real-time backend over Eclipse Zenoh (docs/realtime.md): one OS process per flow.

    protocol/       every control and status message as a typed record with an exact decoder, one file
                    per direction (its __init__ maps it); protocol/seal.py: the coordinator's control,
                    sealed for each process
    wire.py         the key space; the data plane's events and progress; bounded reprs for errors
    access.py       who may join a run (Zenoh authentication, TLS) and what a watcher may do (access control)
    origin.py       which process sent a status or report: each worker process's own key, and the MAC it puts on them
    hub.py          peer sessions: the run's hub and the workers joining it
    router.py       retriever router: a Zenoh router that deployments join as clients (hub.client_config)
    routing.py      a router-mode session's access control and config (router.py's, a daemon's run router)
    reach.py        why an endpoint admitted no session (nothing listens, refused, wrong credentials)
    folders.py      private folders named by their process's PID, and the reaping of a dead one's
    link/           same-host links: a producer's messages to its consumers on its host over a Unix socket and
                    a sealed memfd ring instead of Zenoh (its __init__ maps it); node/linked.py wires them in
    node/           one node's real-time loop, split by concern (its docstring draws it); its
                    reporter sends step records and events to the coordinator
    worker/         the worker process around a loop, in phases (its docstring maps the modules each
                    phase's work is in); worker/group.py: around a group's loops (configure(process=))
    command.py      a worker's command line, built and read in one place
    output.py       what workers print, on the coordinator's streams, prefixed with the node
    host.py         where worker processes run (this machine: LocalHost), and how they are started
    coordinator/    the coordinator: starts workers on hosts, agrees on T0, collects the trace and the log;
                    where the hosts are is a Hosting handed to it (this machine, a deployment, dora)
    seen.py         what the coordinator has seen of a run (event ids, recent ticks), in bounded memory
    stopping.py     the stop a daemon or router waits on, asked for by a signal wherever it lands
    remote.py       worker processes on a worker daemon (RemoteHost), as the coordinator sees them
    deploy/         a deployment: the coordinator hosted on worker daemons, its nodes placed there;
                    Deployment wires its parts (discovery, links, status, usage, the loss policy)
    daemon/         a long-lived worker daemon (retriever-worker), what it runs for a coordinator
                    (daemon/runs.py), and listing them (retriever workers); its docstring draws it
"""

from __future__ import annotations

from ...errors import BackendError
from ...graph import Graph
from ..base import Backend


class ZenohBackend(Backend):
    name = "zenoh"
    OPTIONS = ("namespace", "startup_timeout", "start_margin", "hub_port", "quiet", "secret", "virtual_time", "keep",
               "foxglove", "rerun", "same_host_links")
    #: options of a deployment on worker daemons (deploy/): given any of the first three, the
    #: run's nodes go to the workers reached there instead of processes of this machine
    DEPLOY_OPTIONS = ("connect", "listen", "router", "placement", "insecure", "max_clock_offset", "on_worker_loss",
                      "lease", "tls", "on_phase")

    def open(self, graph: Graph, **options: object):
        deploy = any(options.get(key) is not None for key in ("connect", "listen", "router"))
        accepted = [*self.OPTIONS, *self.DEPLOY_OPTIONS] if deploy else [*self.OPTIONS, "connect", "listen", "router"]
        if deploy:
            accepted.remove("hub_port")
        unknown = sorted(set(options) - set(accepted))
        if unknown:
            raise BackendError(f"the zenoh backend takes no options {unknown} "
                               f"{'in a deployment (connect= or listen= given) ' if deploy else ''}"
                               f"(it accepts {', '.join(accepted)})")
        if deploy:
            from .deploy import open_deployment

            return open_deployment(graph, **options)
        from .coordinator import Coordinator

        options.pop("connect", None), options.pop("listen", None), options.pop("router", None)
        return Coordinator(graph, **options)
