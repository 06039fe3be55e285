"""Where a run's processes run, handed to the coordinator: this machine, worker daemons, or dora.

    Hosting                   the coordinator's questions about where its run is
    ├── LocalHosting          every node a child process of this one (the embedded default)
    ├── deploy.Deployment     the nodes on worker daemons of a namespace, placed (placement.py)
    └── dora.DoraHosting      `dora run` starting every node as a dora node

The coordinator's logic (readiness, T0, reports, the log, restarts, lost processes) is the same
on each; a hosting answers what differs: how the hub opens and who may join it, where the nodes
go (:meth:`place`), what a host lost means, how the processes stop, what a run's log says of it.
A hosting serves one coordinator, which :meth:`attach` hands it before anything else.
"""

from __future__ import annotations

import json
import sys

from ....errors import BackendError
from ....graph import Graph
from ..access import AccessError, RunAccess, secret_bytes, write_private
from ..host import Host, LocalHost
from ..hub import open_hub


class Hosting:
    """What differs between the places a run's processes run; the defaults are this machine's."""

    #: the backend's name, in the run's errors and its log
    backend_name = "zenoh"

    def attach(self, coordinator) -> None:
        """The coordinator this hosting serves (its ``book``, ``supervisor``, ``control``, ``spec``...)."""
        self.coordinator = coordinator

    # -- before anything starts ----------------------------------------------------------------
    def check_deployable(self, graph: Graph) -> None:
        """Refuse, before anything starts, a graph that cannot run here (the default: every flow
        must be rebuildable from the IR in another process)."""
        check_rebuildable(graph)

    def run_access(self, namespace: str, secret) -> RunAccess | None:
        """The run's credentials: random, or derived from the deployment secret (access.py)."""
        try:
            return RunAccess.create(namespace, secret_bytes(secret))
        except AccessError as e:
            raise BackendError(str(e)) from None

    def open_hub(self, port: int, access: dict[str, str] | None):
        """Open the run's own session, which the workers join: ``(session, endpoint)``."""
        return open_hub(port, access=access, keys=self.coordinator.keys)

    def where(self) -> str:
        """Where the run's hub is, for the line that says how to watch it."""
        return f"Zenoh hub listening on {self.coordinator.endpoint}"

    def how_to_watch(self) -> str:
        """How a plain Zenoh client sees the run's events, for the line that says where it is."""
        coordinator = self.coordinator
        if coordinator.watch_config is None:
            return ("anyone on its network may join it (insecure); watch it with a subscriber on "
                    f"{coordinator.keys.all_data()}")
        return (f"watch it read-only with zenoh.Config.from_file('{coordinator.watch_config}') and a subscriber on "
                f"{coordinator.keys.all_data()}")

    def place(self) -> dict[str, Host]:
        """Each node's host, where its processes start (the coordinator's ``spec`` is written)."""
        raise NotImplementedError

    # -- while the run goes --------------------------------------------------------------------
    def check(self) -> None:
        """Before the coordinator looks at its hosts and processes: mark a host known lost."""

    def host_lost(self, host: Host, nodes: list[str]) -> None:
        """A host went with the nodes on it: the run stops (a deployment may move them instead),
        and the log says which processes went with it (their faults, once their last reports are in)."""
        book = self.coordinator.book
        if book.t0 is not None:
            book.unrecovered += [{"node": nid, "at_ns": book.run_time(), "pid": book.workers[nid].pid,
                                  "exit": f"was lost with its worker '{host.name}'"} for nid in nodes]
        book.failure = (nodes[0], {"error": f"worker '{host.name}' was lost (its liveliness token went): its node(s) "
                                            f"{', '.join(nodes)} stopped\n    hint: is the machine up, and on the "
                                            "network? `retriever workers` lists the workers up"})

    def stderr_tail(self, nid: str, lines: int) -> str:
        """The last ``lines`` lines ``nid``'s processes printed on stderr."""
        host = self.coordinator.book.hosts.get(nid)
        return host.output(nid).tail(lines) if host is not None else ""

    # -- the run's end -------------------------------------------------------------------------
    def before_stop(self) -> None:
        """Before the coordinator stops the workers (at the run's end, or on an error)."""

    def faults_left(self) -> list[dict]:
        """Faults of processes the hosting still expected back when the run ended, for the log."""
        return []

    def release(self) -> None:
        """Let go of the hosts, the run over (a worker daemon forgets it); on this machine, nothing."""

    def log_metadata(self) -> dict[str, str]:
        """What the run's log says of where it ran."""
        return {}


class LocalHosting(Hosting):
    """Every node on this machine: the spec in the run directory, the workers its children."""

    def place(self) -> dict[str, Host]:
        coordinator = self.coordinator
        path = coordinator.run_dir / "spec.json"
        write_private(path, json.dumps(coordinator.spec))  # it holds the run's password
        host = LocalHost(path)
        return {nid: host for nid in coordinator.graph.nodes}


def check_rebuildable(graph: Graph) -> None:
    """Every flow must be rebuildable from the IR; a class in ``__main__`` is, when the main
    script is a file (workers import it as ``__mp_main__``, like multiprocessing)."""
    main_file = getattr(sys.modules.get("__main__"), "__file__", None)
    problems = [f"  {nid}: {node.rebuild_problem}" for nid, node in graph.nodes.items()
                if node.rebuild_problem is not None and not (main_file and node.rebuild_needs_main)]
    if problems:
        raise BackendError("the zenoh backend runs each flow in its own process, rebuilt from the IR (type + "
                           "params), and these flows cannot be rebuilt that way:\n" + "\n".join(problems)
                           + "\n    hint: define flow classes at a module's top level and give them "
                           "msgpack-serializable constructor arguments, or run in-process: backend=\"inproc\"")


