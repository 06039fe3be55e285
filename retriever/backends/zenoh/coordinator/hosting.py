"""Where a run's processes run, handed to the coordinator: this machine, worker daemons, or dora.

    Hosting                   the coordinator's questions about where its run is
    ├── LocalHosting          every node a child process of this one (the embedded default)
    ├── deploy.Deployment     the nodes on worker daemons of a namespace, placed (placement.py)
    └── dora.DoraHosting      `dora run` starting every node (or group) as a dora node

The coordinator's logic (readiness, T0, reports, the log, restarts, lost processes) is the same
on each; a hosting answers what differs: how the hub opens and who may join it, where the nodes
go (:meth:`place`), what a host lost means, how the processes stop, what a run's log says of it.
A hosting serves one run, which :meth:`attach` hands it before the hub opens: a :class:`HostedRun`,
what it may read of the run and the three things it may do to it (keep a subscription, stop it,
give nodes the keys their first processes sign with).
What a host lost means is a decision it returns (:class:`FailRun`, :class:`Relocate`,
:class:`AwaitHost`), which the coordinator's Supervisor carries out (processes.py).
"""

from __future__ import annotations

import sys
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from ....errors import BackendError
from ....graph import Graph
from ..access import WATCH_USER, AccessError, RunAccess, secret_bytes
from ..host import Host, LocalHost
from ..hub import open_hub
from ..protocol import RunSpec
from ..wire import KeySpace
from .book import BookView
from .faults import Fault


@dataclass
class HostedRun:
    """The run a hosting serves: what it reads of it, filled in as the coordinator opens it
    (``hub``, ``endpoint``, ``watch_config`` once the hub is open; ``spec`` before :meth:`Hosting.place`,
    which may replace it with one that has a part of its own: dora's). ``book`` is a read-only
    view of the coordinator's record (states, counters, processes, run time): what a host lost
    changes in it goes through the decision :meth:`Hosting.host_lost` returns."""

    graph: Graph
    namespace: str
    keys: KeySpace
    access: RunAccess | None
    run_dir: Path
    book: BookView
    #: keep a subscription or queryable of the hub until the run closes
    keep: Callable[[Any], None]
    #: end the run now, as Ctrl-C here would (``retriever stop``)
    stop: Callable[[], None]
    #: whether the run has closed
    closed: Callable[[], bool]
    #: the keys some nodes' first processes sign with, made by the hosting (:meth:`Hosting.place`:
    #: dora's, in its spec) instead of at their spawn (book.Processes.expect_keys)
    expect_keys: Callable[[dict[str, bytes]], None]
    hub: Any = None
    endpoint: str | None = None
    watch_config: Path | None = None
    spec: RunSpec | None = None


@dataclass(frozen=True)
class FailRun:
    """A host lost stops the run: why (``reason``), and how each of its processes ended, as
    their faults say (``exit``)."""

    reason: str
    exit: str


@dataclass(frozen=True)
class Relocate:
    """A host lost: each of its nodes starts afresh on another host (``hosts``), named
    ``moved_to`` in its fault, which says its old process went at ``at_ns`` as ``exit`` says."""

    hosts: dict[str, Host]
    moved_to: dict[str, str]
    at_ns: int
    exit: str


@dataclass(frozen=True)
class AwaitHost:
    """A host lost: the run goes on without its nodes until it is back; ``lost``: the nodes
    lost just now, whose consumers are told (none when the loss was seen before)."""

    lost: tuple[str, ...] = ()


#: what a host lost means (Hosting.host_lost), for the Supervisor to carry out
HostLoss = FailRun | Relocate | AwaitHost


class Hosting:
    """What differs between the places a run's processes run; the defaults are this machine's."""

    #: the backend's name, in the run's errors and its log
    backend_name = "zenoh"
    #: whether it starts a group of flows in one process (configure(process=)); else each flow
    #: runs alone, and the run says so
    shares_processes = False
    #: whether every process of the run is on one host, this one: its edges between processes may
    #: then go over same-host links (the coordinator's ``same_host_links``, node/linked.py)
    one_host = False

    def attach(self, run: HostedRun) -> None:
        """The run this hosting serves."""
        self.run = run

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

    def hub_dictionary(self, access: RunAccess, run_dir: Path) -> Path:
        """The dictionary file the hub checks a joining peer against, in the run's folder (where
        this machine's workers read it too); :meth:`open_hub` opens the hub with it."""
        return access.write_dictionary(run_dir)

    def open_hub(self, port: int, access: dict[str, str] | None):
        """Open the run's own session, which the workers join: ``(session, endpoint)``."""
        return open_hub(port, access=access, keys=self.run.keys)

    def watcher_user(self) -> str:
        """The user name a watcher of the run proves where it joins (the run's own hub: WATCH_USER)."""
        return WATCH_USER

    def where(self) -> str:
        """Where the run's hub is, for the line that says how to watch it."""
        return f"Zenoh hub listening on {self.run.endpoint}"

    def how_to_watch(self) -> str:
        """How a plain Zenoh client sees the run's events, for the line that says where it is."""
        run = self.run
        if run.watch_config is None:
            return f"anyone on its network may join it (insecure); watch it with a subscriber on {run.keys.all_data()}"
        return (f"watch it read-only with zenoh.Config.from_file('{run.watch_config}') and a subscriber on "
                f"{run.keys.all_data()}")

    def process_names(self) -> dict[str, str]:
        """The process name the hosting gives some nodes, winning over their configure(process=)
        (a deployment's placement file): none by default."""
        return {}

    def groups_of_one(self, graph: Graph, groups: dict[str, list[str]]) -> list[str]:
        """The nodes outside ``groups`` whose process the hosting starts as a group of one (named
        as the node, served by the group worker): none by default."""
        return []

    def place(self) -> dict[str, Host]:
        """Each node's host, where its processes start (the run's ``spec`` is written, with its
        ``groups``: a group's nodes go to one host, which starts their one process)."""
        raise NotImplementedError

    # -- while the run goes --------------------------------------------------------------------
    def check(self) -> None:
        """Before the coordinator looks at its hosts and processes: mark a host known lost."""

    def host_lost(self, host: Host, nodes: list[str]) -> HostLoss:
        """A host went with the nodes on it: what that means (the default: the run stops; a
        deployment may move them instead). Asked again at each check while the host is gone."""
        return FailRun(f"worker '{host.name}' was lost (its liveliness token went): its node(s) {', '.join(nodes)} "
                       "stopped\n    hint: is the machine up, and on the network? `retriever workers` lists the "
                       "workers up", f"was lost with its worker '{host.name}'")

    def stderr_tail(self, nid: str, lines: int) -> str:
        """The last ``lines`` lines ``nid``'s processes printed on stderr."""
        host = self.run.book.hosts.get(nid)
        return host.output(nid).tail(lines) if host is not None else ""

    # -- the run's end -------------------------------------------------------------------------
    def before_stop(self) -> None:
        """Before the coordinator stops the workers (at the run's end, or on an error)."""

    def faults_left(self) -> list[Fault]:
        """Faults of processes the hosting still expected back when the run ended, for the log."""
        return []

    def release(self) -> None:
        """Let go of the hosts, the run over (a worker daemon forgets it); on this machine, nothing."""

    def log_metadata(self) -> dict[str, str]:
        """What the run's log says of where it ran."""
        return {}


class LocalHosting(Hosting):
    """Every node on this machine: the spec in the run directory, the workers its children."""

    shares_processes = True
    one_host = True

    def place(self) -> dict[str, Host]:
        run = self.run
        host = LocalHost(run.spec.write_file(run.run_dir / "spec.json"))
        return {nid: host for nid in run.graph.nodes}


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


