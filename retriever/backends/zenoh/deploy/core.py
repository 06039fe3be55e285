"""Deployment: the Hosting of worker daemons, which wires the parts of deploy/ (its __init__ maps them)."""

from __future__ import annotations

import json
import os
import sys
from collections.abc import Callable
from pathlib import Path

from ....errors import BackendError, PlacementError
from ....graph import Graph
from ....log.format import package_versions
from ....placement import Placement, load_placement, place
from ..access import WATCH_USER, AccessError, RunAccess, TlsFiles, secret_bytes, watch_user
from ..daemon import DaemonInfo, WorkerError, check_security
from ..hub import weak_callback
from ..protocol import StatusReply
from ..remote import RemoteHost
from ..coordinator import Coordinator, Hosting
from ..coordinator.faults import Fault
from ..coordinator.hosting import HostedRun, HostLoss
from .book import WorkerBook, placement_target
from .discovery import CLOCK_REFUSE_NS, discover, package_differences
from .links import Links, phase
from .loss import WORKER_LOSS, LossPolicy
from .status import DeploymentQueryable
from .usage import UsagePoller

#: the steps of a deployment's start that ``on_phase`` times, in their order: open the hub and link
#: to the --connect endpoints; find the workers and ask each for its info; prepare each chosen worker
PHASES = ("join", "discover", "prepare")


def open_deployment(graph: Graph, *, connect: list[str] = (), listen: list[str] = (), router: list[str] = (),
                    namespace: str = "default",
                    placement: Placement | str | None = None, secret=None, insecure: bool = False,
                    startup_timeout: float = 60.0, start_margin: float = 0.5, quiet: bool = False,
                    max_clock_offset: float = CLOCK_REFUSE_NS / 1e9, on_worker_loss: str = "replace",
                    lease: float | None = None, tls: TlsFiles | None = None, virtual_time: bool = False,
                    keep: str = "trace", foxglove: int | None = None, rerun: str | os.PathLike | None = None,
                    on_phase: Callable[[str, float], None] | None = None, same_host_links: bool = True) -> Coordinator:
    """A run of ``graph`` on the worker daemons of a namespace: the coordinator, hosted by a
    :class:`Deployment` (``on_phase``: its timing hook). ``same_host_links``: taken, and without
    effect (yet): a deployment's edges all go over Zenoh, those within one daemon's host too."""
    hosting = Deployment(connect=connect, listen=listen, router=router, placement=placement, secret=secret,
                         insecure=insecure, max_clock_offset=max_clock_offset, on_worker_loss=on_worker_loss,
                         lease=lease, tls=tls, on_phase=on_phase)
    return Coordinator(graph, hosting=hosting, namespace=namespace, startup_timeout=startup_timeout,
                       start_margin=start_margin, quiet=quiet, secret=secret, virtual_time=virtual_time, keep=keep,
                       foxglove=foxglove, rerun=rerun)


class Deployment(Hosting):
    """Where a deployment's nodes run: on the worker daemons of a namespace, as placed.

    ``on_phase(name, seconds)``, if given, is called on the coordinator's thread as each step of
    the start (:data:`PHASES`) ends, with how long it took, also when it fails: where a deployment's
    start time goes (benchmarks/deploy.py), without reaching into how each step is done.

    ``router``: Zenoh routers (``retriever router``, or any) that every session of the
    deployment joins as a client, the coordinator's, each worker daemon's and each flow's
    (hub.client_config): no session listens, so a machine behind NAT takes part; without them,
    every session is a peer of the others, linked directly.

    Flows that share a process (``configure(process=NAME)``, or ``process = "NAME"`` in the
    placement file, which wins) are placed as one unit (placement.assign) and started as one
    process by their worker's daemon; a worker lost moves them together, each then starting
    afresh in a process of its own (as a flow whose process died does)."""

    shares_processes = True

    def __init__(self, *, connect: list[str] = (), listen: list[str] = (), router: list[str] = (),
                 placement: Placement | str | None = None,
                 secret=None, insecure: bool = False, max_clock_offset: float = CLOCK_REFUSE_NS / 1e9,
                 on_worker_loss: str = "replace", lease: float | None = None, tls: TlsFiles | None = None,
                 on_phase: Callable[[str, float], None] | None = None):
        try:
            check_security(secret, insecure, "retriever deploy")
        except WorkerError as e:
            raise BackendError(str(e)) from None
        if router and (connect or listen):
            raise BackendError("a deployment joined through a router (--router) listens nowhere and connects to the "
                               "router alone: leave out --connect and --listen")
        if not connect and not listen and not router:
            raise BackendError("a deployment needs --connect ENDPOINT (a worker's), --listen ENDPOINT, where its "
                               "workers are reached, or --router ENDPOINT, the router they joined through\n"
                               "    hint: retriever deploy app.py --connect tcp/HOST:7447")
        if on_worker_loss not in WORKER_LOSS:
            raise BackendError(f"on_worker_loss={on_worker_loss!r} is none of {', '.join(WORKER_LOSS)}")
        if tls is not None:
            try:
                tls.check_endpoints([*connect, *listen, *router])
            except AccessError as e:
                raise BackendError(str(e)) from None
        self._on_worker_loss, self._on_phase = on_worker_loss, on_phase
        self._links = Links(connect=connect, listen=listen, router=router, secret=secret, insecure=insecure,
                            lease=lease, tls=tls, on_phase=on_phase)
        self._insecure = insecure
        self._placement = load_placement(placement) if isinstance(placement, str) else placement
        self._max_offset_ns = round(max_clock_offset * 1e9)
        self._book = WorkerBook()
        self._token = None
        # the parts that read the run, made once it is attached
        self._usage: UsagePoller | None = None
        self._queryable: DeploymentQueryable | None = None
        self._loss: LossPolicy | None = None

    def attach(self, run: HostedRun) -> None:
        super().attach(run)
        self._usage = UsagePoller(run, self._book)
        self._queryable = DeploymentQueryable(run, self._book, self._usage)
        self._loss = LossPolicy(run, self._links, self._book, self._placement, self._on_worker_loss)

    @property
    def placed(self) -> dict[str, str]:
        """Where each node runs: worker name by node."""
        return self._book.placed

    @property
    def daemons(self) -> dict[str, DaemonInfo]:
        """Each worker daemon as the deployment found it: its info reply, its clock offset, its session."""
        return self._book.daemons

    @property
    def ran_other_code(self) -> dict[str, list[str]]:
        """What each worker said of the code it runs anyway (--code-mismatch warn): into the log."""
        return self._book.ran_other_code

    # -- the coordinator's steps, for workers elsewhere ----------------------------------------
    def check_deployable(self, graph: Graph) -> None:
        super().check_deployable(graph)
        in_main = sorted(nid for nid, node in graph.nodes.items() if type(node.flow).__module__ == "__main__")
        if in_main:
            raise BackendError(f"flow(s) {', '.join(in_main)} are classes of the script being run (__main__), which "
                               "a worker cannot import\n    hint: move them to a module on the workers' --path, "
                               "or deploy the script as FILE:ATTR so that it is imported as a module")

    def run_access(self, namespace: str, secret) -> RunAccess | None:
        """The hub's credentials: those of this run alone (its run id), which each worker daemon
        derives for the run's flows from the secret it holds; through routers, the namespace's."""
        if self._insecure:
            return None
        if self._links.router:
            return super().run_access(namespace, secret)
        try:
            return RunAccess.create(namespace, secret_bytes(secret), run=self._book.run_id)
        except AccessError as e:
            raise BackendError(str(e)) from None

    def hub_dictionary(self, access: RunAccess, run_dir: Path) -> Path:
        # no process of this machine but this one reads it: in memory (Links.hub_dictionary)
        return self._links.hub_dictionary(access, run_dir)

    def open_hub(self, port: int, access: dict[str, str] | None):
        return self._links.open_hub(self.run, access)

    def watcher_user(self) -> str:
        # a router admits the watchers of several namespaces, each under a name of its own
        return watch_user(self.run.namespace) if self._links.router else WATCH_USER

    def where(self) -> str:
        return self._links.where()

    def process_names(self) -> dict[str, str]:
        """The process names of the placement file (``process = "NAME"``)."""
        return dict(self._placement.processes) if self._placement is not None else {}

    def place(self) -> dict[str, RemoteHost]:
        run, book, links = self.run, self._book, self._links
        with phase(self._on_phase, "discover"):
            book.daemons = found = discover(links, run, self._max_offset_ns)
        candidates = [placement_target(name, daemon.info, len(daemon.info.nodes))
                      for name, daemon in sorted(found.items())]
        try:
            book.placed = place(sorted(run.graph.nodes), self._placement, candidates, run.spec.groups)
        except PlacementError as e:
            raise BackendError(str(e)) from None
        # the token first: a worker prepares a run only while its coordinator's token is there
        control = links.control
        self._token = control.liveliness().declare_token(run.keys.deployment())
        with phase(self._on_phase, "prepare"):
            for name in sorted(set(book.placed.values())):
                differences = package_differences(package_versions(), book.daemons[name].info.packages)
                if differences:
                    print(f"retriever: warning: worker '{name}' has other versions of the run's packages than this "
                          f"machine: {'; '.join(differences)}", file=sys.stderr, flush=True)
                host = book.host_of(name, control, run.keys, self._links.secret)
                book.say_warnings(name, host.prepare(links.spec_for(run, name, book.daemons),
                                                     sorted(n for n, w in book.placed.items() if w == name)))
        self._usage.start()
        links.control_keep.append(control.declare_queryable(run.keys.deployment(),
                                                            weak_callback(self._queryable.answer)))
        links.control_keep.append(control.liveliness().declare_subscriber(run.keys.workers(),
                                                                          weak_callback(self._loss.worker_token)))
        return {nid: book.remotes[name] for nid, name in book.placed.items()}

    # -- while the run goes ----------------------------------------------------------------------
    def status_reply(self) -> StatusReply:
        """What ``retriever status`` shows (DeploymentQueryable.status_reply)."""
        return self._queryable.status_reply()

    def status(self) -> dict:
        """:meth:`status_reply`'s fields, as the live table of ``retriever deploy`` shows them
        (cli.status_table, which shows ``retriever status``'s answer too)."""
        return self.status_reply().to_fields()

    def check(self) -> None:
        self._loss.check()

    def host_lost(self, host, nodes: list[str]) -> HostLoss:
        """As ``on_worker_loss`` says (LossPolicy.host_lost); else the run stops, naming the worker."""
        decision = self._loss.host_lost(host, nodes)
        return decision if decision is not None else super().host_lost(host, nodes)

    # -- the run's end ---------------------------------------------------------------------------
    def faults_left(self) -> list[Fault]:
        return self._loss.faults_left()

    def log_metadata(self) -> dict[str, str]:
        """``deployment``: which worker ran each node, and what each worker said of itself."""
        workers = {name: {"host": daemon.info.host, "pid": daemon.info.pid, "labels": list(daemon.info.labels),
                          "python": daemon.info.python, "packages": daemon.info.packages, "offset_ns": daemon.offset_ns}
                   for name, daemon in self.daemons.items()}
        return {"deployment": json.dumps({"namespace": self.run.namespace, "placed": self.placed,
                                          "workers": workers, "ran_other_code": self.ran_other_code},
                                         sort_keys=True)}

    def release(self) -> None:
        self._usage.stop()
        for host in self._book.remotes.values():
            host.end()
            host.close()
        if self._token is not None:
            self._token.undeclare()
            self._token = None
        self._links.close(self.run.hub)
