"""A deployment: the coordinator (coordinator/), hosted on worker daemons (docs/deploy.md).

    retriever deploy app.py --connect tcp/10.0.0.2:7447 --placement lab.toml --secret lab.key
        │ join the namespace (its control session: Zenoh peer, the namespace's credentials) and
        │ open the run's hub (the credentials of this run alone: access.py), find its workers
        │ (liveliness tokens workers/<name>) and ask each for its info: protocol, labels, load, clock offset
        │ place every node (placement.py: pins, labels, load), refuse what cannot be met, all at once
        │ prepare each chosen worker (remote.py: the spec; it checks every class it will import)
        │ declare the deployment's liveliness token: a worker stops its flows once it goes
        ▼ from here on as the embedded run: spawn, ready, T0, reports, the log, faults, stop

Two sessions, so that nothing of one run links to the daemons or to another run: the control
session links to the worker daemons alone (prepare, spawn, their events and tokens, ``retriever
status``/``stop``); the hub, whose dictionary holds this run's users alone, listens for the run's
flows, which each daemon points at it (the address it reached that daemon from, the hub's port)
with the run's passwords, derived there from the secret and the run id. With ``--router
ENDPOINT`` every session (the coordinator's, each daemon's, each flow's) is instead a client of
that Zenoh router (router.py), which routes between them: none listens, one coordinator session
does both, and every password is the namespace's (a router's dictionary is fixed when it starts).

A worker that is lost mid-run (its token went) takes its nodes' processes with it; with
``on_worker_loss="replace"`` (the default) each of them starts afresh on another worker that its
placement allows, as a flow whose process died does (node/handover.py); with "stop", or nowhere to go,
the run stops naming the worker.
"""

from __future__ import annotations

import dataclasses
import json
import os
import re
import secrets
import sys
import threading
import time
import tomllib
from collections import Counter
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path

import zenoh

from ...errors import BackendError, PlacementError
from ...graph import Graph
from ...log.format import package_versions
from ...placement import Placement, WorkerInfo, load_placement, move, place
from ...trace import KEEP
from .access import (CONTROL_DICTIONARY, WATCH_USER, AccessError, RunAccess, TlsFiles,
                     secret_bytes, watch_user)
from .daemon import (ENDPOINT, QUERY_S, DaemonInfo, WorkerError, check_security, credentials, describe, in_session,
                     no_router, open_access)
from .hub import (HUB_SHARED_MEMORY, client_config, forward_dropping, free_port, peer_config, raise_open_file_limit,
                  remove_orphaned_segments_at_exit, router_linked, wait_for_peers, weak_callback)
from .protocol import (ABSENT, DEPLOYMENT_QUERY, DEPLOYMENT_REPLY, PROTOCOL_VERSION, DaemonOp, DeploymentOp,
                       ErrorReply, InfoReply, InfoRequest, NodeStatus, StatusQuery, StatusReply, StopQuery, StopReply,
                       decode_reply, error_message)
from .reach import REFUSES_LINKS, why_no_session
from .remote import RemoteHost
from .wire import KeySpace, WireError, check_chunk
from .coordinator import Coordinator, Hosting
from .coordinator.faults import Fault
from .coordinator.hosting import AwaitHost, FailRun, HostLoss, Relocate

#: how often the coordinator asks its workers for their flows' CPU time (retriever status, the live table)
USAGE_EVERY_S = 1.0
#: how long the coordinator waits for links to its --connect endpoints before it looks for workers
JOIN_S = 5.0
#: what a deployment does with the nodes of a worker it lost: start them afresh on another worker
#: that their placement allows (the least loaded), or on it once it is back, or stop
WORKER_LOSS = ("replace", "wait", "stop")
#: where a coordinator told only --connect listens: every address of its machine, a port the OS picks
ANY_ADDRESS = "tcp/0.0.0.0:0"
#: how long a liveliness get for the namespace's workers waits for answers
DISCOVER_S = 2.0
#: clock offsets between the coordinator and a worker: past the first a warning, past the second
#: (by default) the deployment is refused: Rate ticks and T0 come from each worker's clock
CLOCK_WARN_NS = 1_000_000
CLOCK_REFUSE_NS = 10_000_000
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
                    on_phase: Callable[[str, float], None] | None = None) -> Coordinator:
    """A run of ``graph`` on the worker daemons of a namespace: the coordinator, hosted by a
    :class:`Deployment` (``on_phase``: its timing hook)."""
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
    every session is a peer of the others, linked directly."""

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
        self._on_worker_loss, self._lease, self._tls, self._on_phase = on_worker_loss, lease, tls, on_phase
        if tls is not None:
            try:
                tls.check_endpoints([*connect, *listen, *router])
            except AccessError as e:
                raise BackendError(str(e)) from None
        self._connect, self._listen_at, self._insecure = list(connect), list(listen), insecure
        self._router = list(router)
        self._secret = secret
        #: the session that links to the worker daemons, with the namespace's credentials (the hub
        #: itself when joined through routers); ``_control_keep``: what is declared on it
        self._control: zenoh.Session | None = None
        self._control_keep: list = []
        self._hub_port: int | None = None  # where the hub listens, on every address of its host
        self._hub_proto, self._hub_host = "tcp", "0.0.0.0"
        self._placement = load_placement(placement) if isinstance(placement, str) else placement
        self._run_id = secrets.token_hex(6)
        self._max_offset_ns = round(max_clock_offset * 1e9)
        self._remotes: dict[str, RemoteHost] = {}
        self._token = None
        self._linked = False  # whether the hub has a link to each --connect endpoint
        self._cpu: dict[str, float] = {}  # node -> CPU seconds of its process, last read (_watch_usage)
        self._waiting: dict[str, dict] = {}  # lost workers waited for (on_worker_loss="wait"): nodes, when
        self._returned: set[str] = set()  # of those, the ones whose token came back
        self._usage_stop = threading.Event()
        #: where each node runs: worker name by node
        self.placed: dict[str, str] = {}
        #: what each worker said of the code it runs anyway (--code-mismatch warn): into the log
        self.ran_other_code: dict[str, list[str]] = {}
        #: each worker daemon as the deployment found it: its info reply, its clock offset, its
        #: session (RemoteHost takes only that session's answers)
        self.daemons: dict[str, DaemonInfo] = {}

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
        if self._router:
            return super().run_access(namespace, secret)
        try:
            return RunAccess.create(namespace, secret_bytes(secret), run=self._run_id)
        except AccessError as e:
            raise BackendError(str(e)) from None

    def open_hub(self, port: int, access: dict[str, str] | None):
        if self._router:
            return self._open_client()
        links = self._tls.session_config() if self._tls is not None else {}
        raise_open_file_limit()  # it listens where strangers may connect too (hub.accept_pending)
        remove_orphaned_segments_at_exit()
        with self._phase("join"):
            try:
                self._control = self._open_control(links)
                try:
                    hub = self._open_run_hub({**(access or {}), **links})
                except BaseException:
                    self._close_control()
                    raise
            finally:  # Zenoh read the run's dictionary as the hub opened; no process of this machine reads it after
                self._drop_hub_dictionary()
        host = "127.0.0.1" if self._hub_host in ("0.0.0.0", "[::]") else self._hub_host
        return hub, f"{self._hub_proto}/{host}:{self._hub_port}"

    def hub_dictionary(self, access: RunAccess, run_dir) -> Path:
        """The hub's dictionary, in memory (access.SessionDictionary: no file on disk, on Linux);
        no process but this one reads it, and open_hub drops it once the hub opened."""
        self._hub_dictionary = access.session_dictionary(run_dir)
        return self._hub_dictionary.path

    def _drop_hub_dictionary(self) -> None:
        dictionary, self._hub_dictionary = getattr(self, "_hub_dictionary", None), None
        if dictionary is not None:
            dictionary.close()

    def _open_control(self, links: dict[str, str]) -> zenoh.Session:
        """The session that links to the worker daemons, with the namespace's credentials. It
        listens even when told only where to connect (as the daemons do: a daemon it learns of
        by gossip may open the link). Zenoh reads the namespace's dictionary as it opens: it is given
        in memory (access.SessionDictionary), closed then: on disk at no time, on Linux."""
        listen = self._listen_at or [ANY_ADDRESS.replace("tcp/", "tls/") if self._tls else ANY_ADDRESS]
        access = dict(links)
        dictionary = None
        if not self._insecure:
            try:
                namespace_access = RunAccess.create(self.run.namespace, secret_bytes(self._secret))
            except AccessError as e:
                raise BackendError(str(e)) from None
            dictionary = namespace_access.session_dictionary(self.run.run_dir, CONTROL_DICTIONARY)
            access.update(namespace_access.session_config(dictionary.path))
        try:
            control = zenoh.open(peer_config(listen=listen, connect=self._connect, access=access or None,
                                             lease=self._lease, shared_memory=False))
        finally:
            if dictionary is not None:
                dictionary.close()
        try:
            self._linked = wait_for_peers(control, len(self._connect), JOIN_S)
        except BaseException:
            control.close()
            raise
        return control

    def _open_run_hub(self, access: dict[str, str]) -> zenoh.Session:
        """The run's hub: it checks the run's flows (and watchers) against this run's dictionary
        alone, listening on a free port of every address of its host (or of the --listen one's
        host), which each daemon's flows connect to (:meth:`_hub_for`). It connects nowhere."""
        proto, host = "tls" if self._tls else "tcp", "0.0.0.0"
        if self._listen_at:
            proto, _, address = self._listen_at[0].partition("/")
            host = address.split("#")[0].rpartition(":")[0] or host
        self._hub_proto, self._hub_host = proto, host
        access = {**access, **forward_dropping(self.run.keys)}  # a watcher's link never holds the hub
        last: Exception | None = None
        for _ in range(5):
            port = free_port(host) if ":" not in host else free_port()  # (an IPv6 host: one free on loopback)
            try:
                hub = zenoh.open(peer_config(listen=[f"{proto}/{host}:{port}"], access=access, lease=self._lease,
                                             shared_memory=HUB_SHARED_MEMORY))
            except zenoh.ZError as e:  # taken between the check and the bind: try another
                last = e
                continue
            self._hub_port = port
            return hub
        raise BackendError(f"could not open the run's hub on {proto}/{host}: {last}")

    def _hub_for(self, name: str) -> str:
        """The hub's endpoint as worker ``name``'s host reaches it: the address of this machine
        on the control session's link to that daemon (peers do not route for each other: a
        daemon the coordinator asks has a direct link), the hub's port."""
        if self._router:
            return self.run.endpoint
        replier = self.daemons[name].zid or ""  # the replier's id: "EntityGlobalId { zid: <hex>, eid: N }"
        found = re.search(r"zid: ([0-9a-f]+)", replier)
        zid = found.group(1) if found else replier
        for link in self._control.info.links():
            if zid and str(link.zid) == zid:
                _, _, address = str(link.src).partition("/")
                host = address.split("#")[0].rpartition(":")[0]
                if host:
                    return f"{self._hub_proto}/{host}:{self._hub_port}"
        if self._hub_host not in ("0.0.0.0", "[::]"):
            return f"{self._hub_proto}/{self._hub_host}:{self._hub_port}"
        raise BackendError(f"the coordinator has no link to worker '{name}' to tell it where the run's hub is\n"
                           "    hint: pass --connect with each worker's endpoint")

    def _close_control(self) -> None:
        """Undeclare what the control session holds and close it (not the hub: the coordinator's)."""
        for declared in self._control_keep:
            try:
                declared.undeclare()
            except zenoh.ZError:
                pass
        self._control_keep.clear()
        control, self._control = self._control, None
        if control is not None and control is not self.run.hub:
            try:
                control.close()
            except zenoh.ZError:
                pass

    def _open_client(self):
        """open_hub through the routers: a client of theirs, with the namespace's password for
        them (RunAccess.client_config). It opens only once a router admitted it: joined."""
        run = self.run
        access = {**(run.access.client_config(run.namespace) if run.access is not None else {}),
                  **(self._tls.session_config() if self._tls is not None else {})}
        remove_orphaned_segments_at_exit()
        with self._phase("join"):
            self._drop_hub_dictionary()  # a client has none (see open_hub)
            try:
                hub = zenoh.open(client_config(connect=self._router, access=access or None, lease=self._lease,
                                               shared_memory=HUB_SHARED_MEMORY))
            except zenoh.ZError:
                raise BackendError(no_router("the deployment", self._router, self._tls, run.namespace)) from None
        self._linked = True
        self._control = hub  # one session does both, with the namespace's credentials
        return hub, self._router[0]

    def watcher_user(self) -> str:
        # a router admits the watchers of several namespaces, each under a name of its own
        return watch_user(self.run.namespace) if self._router else WATCH_USER

    def where(self) -> str:
        if self._router:
            return f"deployment joined through router {', '.join(self._router)}"
        if not self._connect:
            return f"deployment listening on {', '.join(self._listen_at)}"
        # a peer's session opens without a link: "joined" only once it has one to each endpoint
        return f"deployment {'joined through' if self._linked else 'connecting to'} {', '.join(self._connect)}"

    def place(self) -> dict:
        run = self.run
        with self._phase("discover"):
            found = self._discover()
        candidates = [placement_target(name, daemon.info, len(daemon.info.nodes))
                      for name, daemon in sorted(found.items())]
        try:
            self.placed = place(sorted(run.graph.nodes), self._placement, candidates)
        except PlacementError as e:
            raise BackendError(str(e)) from None
        # the token first: a worker prepares a run only while its coordinator's token is there
        control = self._control
        self._token = control.liveliness().declare_token(run.keys.deployment())
        with self._phase("prepare"):
            for name in sorted(set(self.placed.values())):
                differences = package_differences(package_versions(), self.daemons[name].info.packages)
                if differences:
                    print(f"retriever: warning: worker '{name}' has other versions of the run's packages than this "
                          f"machine: {'; '.join(differences)}", file=sys.stderr, flush=True)
                host = self._remotes[name] = RemoteHost(control, run.keys, name, self._run_id, self.daemons[name].zid,
                                                              self._secret)
                self._say_warnings(name, host.prepare(self._spec_for(name),
                                                      sorted(n for n, w in self.placed.items() if w == name)))
        threading.Thread(target=self._watch_usage, name="retriever-usage", daemon=True).start()
        self._control_keep.append(control.declare_queryable(run.keys.deployment(), weak_callback(self._answer)))
        self._control_keep.append(control.liveliness().declare_subscriber(run.keys.workers(),
                                                                          weak_callback(self._worker_token)))
        return {nid: self._remotes[name] for nid, name in self.placed.items()}

    def _spec_for(self, name: str):
        """The run's spec as worker ``name`` gets it: the hub where its host reaches it."""
        return dataclasses.replace(self.run.spec.for_remote(), hub=self._hub_for(name))

    @contextmanager
    def _phase(self, name: str) -> Iterator[None]:
        """Time step ``name`` of the start for ``on_phase``, whether it ends or raises."""
        begin = time.perf_counter()
        try:
            yield
        finally:
            if self._on_phase is not None:
                self._on_phase(name, time.perf_counter() - begin)

    def _say_warnings(self, name: str, warnings: list[str]) -> None:
        for warning in warnings:
            print(f"retriever: warning: worker '{name}' runs {warning}", file=sys.stderr, flush=True)
            self.ran_other_code.setdefault(name, []).append(warning.partition("\n")[0])

    def _discover(self) -> dict[str, DaemonInfo]:
        """The namespace's live workers and their info; every problem with them at once."""
        hub, keys, namespace = self._control, self.run.keys, self.run.namespace
        names = sorted({str(r.ok.key_expr).rsplit("/", 1)[-1]
                        for r in hub.liveliness().get(keys.workers(), timeout=DISCOVER_S) if r.ok})
        # tokens of one key are one to Zenoh: ask each name who answers, every reply kept
        twice = [name for name in names if self._answering(name) > 1]
        if twice:  # workers that never linked to each other, so neither refused to start
            raise BackendError(f"several workers are named {', '.join(map(repr, twice))} in namespace "
                               f"'{namespace}': a node placed on that name could run twice\n    hint: give each "
                               "worker a name of its own (retriever workers --connect ... lists them), then deploy")
        if not names:
            self._none_found()
        problems, found = [], {}
        for name in names:
            daemon = describe(hub, namespace, name)
            info = daemon.info
            if daemon.other_protocol is not None:
                protocol, retriever = daemon.other_protocol
                problems.append(f"worker '{name}' speaks protocol {protocol}, this coordinator {PROTOCOL_VERSION}"
                                "\n    hint: install the same Retriever version on both machines "
                                f"(the worker has {retriever or '?'!r:.30})")
            elif info is None:
                problems.append(f"worker '{name}' did not say what it is: {daemon.error}")
            elif daemon.offset_ns is not None and abs(daemon.offset_ns) > self._max_offset_ns:
                problems.append(f"worker '{name}' (host {info.host}) has a clock {daemon.offset_ns / 1e6:+.3f} ms "
                                f"off this machine's, past {self._max_offset_ns / 1e6:g} ms\n    hint: sync both "
                                "clocks (chrony or ntpd, or PTP on a robot's LAN), then deploy again")
            else:
                if daemon.offset_ns is not None and abs(daemon.offset_ns) > CLOCK_WARN_NS:
                    print(f"retriever: warning: worker '{name}' has a clock {daemon.offset_ns / 1e6:+.3f} ms off "
                          "this machine's", file=sys.stderr, flush=True)
                found[name] = daemon
        if problems:
            raise BackendError("the deployment cannot start:\n" + "\n".join(f"  - {p}" for p in problems))
        self.daemons = found
        return found

    def _none_found(self) -> None:
        """No worker answered: say why that may be."""
        namespace = self.run.namespace
        refusing = [e for e in self._connect if why_no_session(e, credentials(self._tls)) == REFUSES_LINKS]
        if refusing:  # a stranger's idle connections, not the secret (hub.ACCEPT_TIMEOUT_S)
            raise BackendError(f"no worker found in namespace '{namespace}': {', '.join(refusing)}: "
                               f"{REFUSES_LINKS}\n    hint: see who holds connections to it (ss -tn state "
                               "established on the worker), and keep strangers off the workers' ports: a "
                               "firewall, or TLS (docs/security.md)")
        reached = self._router or self._connect or self._listen_at
        raise BackendError(f"no worker is up in namespace '{namespace}' (reached through "
                           f"{', '.join(reached)}), or none holds this --secret"
                           f"{' and TLS certificate' if self._tls else ''}\n    hint: start one on each machine: "
                           f"retriever-worker --name NAME --namespace {namespace} --secret FILE"
                           + (f" --router {self._router[0]}" if self._router else ""))

    def _answering(self, name: str) -> int:
        """How many daemons answer as worker ``name`` (distinct pids and hosts)."""
        who = set()
        hub, keys = self._control, self.run.keys
        for reply in hub.get(keys.ctl(name), payload=InfoRequest().encode(), timeout=QUERY_S,
                             consolidation=zenoh.ConsolidationMode.NONE):
            try:
                info = decode_reply(reply.ok.payload.to_bytes(), DaemonOp.INFO)
            except (AttributeError, WireError):  # an error reply, garbage, or a daemon of another protocol
                continue
            who.add((info.host, info.pid))
        return len(who)

    def _worker_token(self, sample: zenoh.Sample) -> None:
        """A worker's liveliness: gone, its processes are as good as killed."""
        name = str(sample.key_expr).rsplit("/", 1)[-1]
        if sample.kind == zenoh.SampleKind.DELETE:
            host = self._remotes.get(name)
            if host is not None:
                host.lost()
        elif name in self._waiting:  # back (on_worker_loss="wait"): the main loop moves its nodes there
            self._returned.add(name)

    # -- retriever status / stop -------------------------------------------------------------------
    def _answer(self, query: zenoh.Query) -> None:
        """``status``: the deployment, node by node; ``stop``: end it now, as Ctrl-C here would."""
        run = self.run
        try:
            asked = DEPLOYMENT_QUERY.decode(query.payload.to_bytes() if query.payload is not None else b"",
                                            who="the deployment")
        except WireError as e:
            query.reply_err(ErrorReply(message=str(e)).encode())
            return
        if isinstance(asked, StopQuery):
            run.stop()
            query.reply(run.keys.deployment(), StopReply(pipeline=run.graph.name).encode())
            return
        for _ in range(3):  # read on Zenoh's thread while the run updates it: a copy may collide
            try:
                status = self.status_reply()
                break
            except RuntimeError:
                continue
        else:
            query.reply_err(ErrorReply(message="busy: ask again").encode())
            return
        query.reply(run.keys.deployment(), status.encode())

    def _watch_usage(self) -> None:
        """From a thread of its own, while the deployment runs: each node's CPU seconds so far, as
        its worker reads them, every USAGE_EVERY_S (a worker that does not answer is skipped)."""
        while not self.run.closed() and not self._usage_stop.wait(USAGE_EVERY_S):
            for remote in list(self._remotes.values()):
                try:
                    self._cpu.update(remote.usage())
                except BackendError:
                    continue

    def status_reply(self) -> StatusReply:
        """What ``retriever status`` shows: the run's time, and per node its worker, counters and
        the CPU seconds its process used so far (as last read)."""
        run, book = self.run, self.run.book
        used = dict(self._cpu)
        nodes = {nid: NodeStatus(worker=self.placed.get(nid), state=book.state.get(nid), ticks=s.ticks,
                                 steps=s.steps, skips=s.skips, errors=s.errors, counts=dict(s.counts),
                                 cpu_s=used.get(nid, ABSENT))
                 for nid, s in sorted(book.stats.items())}
        return StatusReply(pipeline=run.graph.name, run=self._run_id, t_ns=min(book.run_time(), book.end_ns),
                           end_ns=book.end_ns, started=book.t0 is not None, nodes=nodes)

    def status(self) -> dict:
        """:meth:`status_reply`'s fields, as the live table of ``retriever deploy`` shows them
        (cli.status_table, which shows ``retriever status``'s answer too)."""
        return self.status_reply().to_fields()

    # -- a worker lost -------------------------------------------------------------------------
    def check(self) -> None:
        """Through a router: once the hub's link to it is gone, every worker is (_router_lost).
        Their tokens' ends are not told to a subscriber that came after the tokens, as the
        coordinator's did (Zenoh tells only those that asked for their history)."""
        if self._router and self._remotes and not router_linked(self.run.hub):
            for host in list(self._remotes.values()):
                host.lost()

    def host_lost(self, host, nodes: list[str]) -> HostLoss:
        """on_worker_loss="replace": each of its nodes starts afresh on a worker still up that its
        placement allows, by the rule of the first placement (placement.move; as a flow whose
        process died: node/handover.py); the log's fault record says where it went. Any node that has
        nowhere to go stops the run. "wait": they start afresh on it once a worker of its name is
        up again (see _await_return)."""
        run = self.run
        if self._router and not router_linked(run.hub):
            return self._router_lost(host, nodes)
        if self._on_worker_loss == "stop" or run.book.t0 is None:
            return super().host_lost(host, nodes)
        if self._on_worker_loss == "wait":
            return self._await_return(host, nodes)
        self._remotes.pop(host.name, None)
        self.daemons.pop(host.name, None)
        targets = move(nodes, self._placement, self._workers_up())
        if targets is None:
            return super().host_lost(host, nodes)
        return self._move(host.name, targets, run.book.run_time())

    def _router_lost(self, host, nodes: list[str]) -> FailRun:
        """The coordinator's link to its router went, and with it every worker's token: the run
        stops, saying so (the workers' daemons lost the coordinator's token the same way, and
        stop its flows). Zenoh joins the router again by itself once it is back, but nothing
        of the run went through it meanwhile."""
        routers = ", ".join(self._router)
        return FailRun(f"the deployment lost its router {routers}: no worker is reached through it (worker "
                       f"'{host.name}' with node(s) {', '.join(nodes)} among them), and its workers stop the run's "
                       "flows\n    hint: is the router up? start it again (retriever router), then deploy again",
                       f"was cut off with the router {routers}")

    def _await_return(self, host, nodes: list[str]) -> HostLoss:
        """on_worker_loss="wait": the run goes on without the nodes (their consumers see a gap);
        once a worker of the lost one's name is up again (its token back), they start afresh there."""
        run, name = self.run, host.name
        waiting = self._waiting.get(name)
        if waiting is None:
            waiting = self._waiting[name] = {"nodes": nodes, "at": run.book.run_time()}
            print(f"retriever: worker '{name}' was lost with node(s) {', '.join(nodes)}; waiting for it to come "
                  "back (on_worker_loss='wait')", file=sys.stderr, flush=True)
            return AwaitHost(lost=tuple(nodes))
        if name not in self._returned:
            return AwaitHost()
        self._returned.discard(name)
        daemon = describe(self._control, run.namespace, name)
        if daemon.info is None:
            return AwaitHost()  # not (yet) a worker that answers as one (of this protocol): wait on
        del self._waiting[name]
        self.daemons[name] = daemon  # a new daemon of that name: a session of its own
        self._remotes.pop(name).close()
        return self._move(name, {nid: name for nid in nodes}, waiting["at"])

    def _move(self, lost: str, targets: dict[str, str], at: int) -> Relocate:
        """Each node of ``targets`` (the lost worker's) to start afresh on its worker there,
        prepared for it."""
        run = self.run
        for name in sorted(set(targets.values())):
            remote = self._remotes.get(name)
            if remote is None:
                remote = self._remotes[name] = RemoteHost(self._control, run.keys, name, self._run_id,
                                                          self.daemons[name].zid, self._secret)
            self._say_warnings(name, remote.prepare(self._spec_for(name),
                                                    sorted(n for n, w in targets.items() if w == name)))
        for nid, name in sorted(targets.items()):
            print(f"retriever: worker '{lost}' was lost; its node '{nid}' starts afresh on worker '{name}'",
                  file=sys.stderr, flush=True)
        self.placed.update(targets)
        return Relocate({nid: self._remotes[name] for nid, name in targets.items()}, dict(targets), at,
                        f"was lost with its worker '{lost}'")

    def _workers_up(self) -> list[WorkerInfo]:
        """The workers still up, each with the nodes placed on it as its load (a move's candidates)."""
        load = Counter(self.placed.values())
        return [placement_target(name, daemon.info, load[name]) for name, daemon in sorted(self.daemons.items())]

    def faults_left(self) -> list[Fault]:
        workers, faults = self.run.book.workers, []
        for waiting in self._waiting.values():  # lost, and never back in the run's time
            faults += [Fault(nid, waiting["at"], workers[nid].pid, "was lost with its worker")
                       for nid in waiting["nodes"]]
        self._waiting.clear()
        return faults

    def log_metadata(self) -> dict[str, str]:
        """``deployment``: which worker ran each node, and what each worker said of itself."""
        workers = {name: {"host": daemon.info.host, "pid": daemon.info.pid, "labels": list(daemon.info.labels),
                          "python": daemon.info.python, "packages": daemon.info.packages, "offset_ns": daemon.offset_ns}
                   for name, daemon in self.daemons.items()}
        return {"deployment": json.dumps({"namespace": self.run.namespace, "placed": self.placed,
                                          "workers": workers, "ran_other_code": self.ran_other_code},
                                         sort_keys=True)}

    def release(self) -> None:
        self._usage_stop.set()
        for host in self._remotes.values():
            host.end()
            host.close()
        if self._token is not None:
            self._token.undeclare()
            self._token = None
        self._close_control()


def placement_target(name: str, info: InfoReply, load: int) -> WorkerInfo:
    """Worker ``name`` as placement weighs it: the labels and host of its info reply, and ``load``
    nodes on it (at the start, those its info lists; when a lost worker's nodes move, those placed there)."""
    return WorkerInfo(name, frozenset(info.labels), load, info.host)


def package_differences(ours: dict[str, str], theirs: dict[str, str]) -> list[str]:
    """``numpy 2.4.6 here, 2.3.0 there`` for each package of ``ours`` that a worker's info
    (``theirs``, as it answered) has in another version."""
    return [f"{name} {version} here, {theirs[name]:.40} there" for name, version in sorted(ours.items())
            if isinstance(theirs.get(name), str) and theirs[name] != version]


def ask_deployment(connect: list[str], namespace: str, op: str, secret=None, insecure: bool = False,
                   tls: TlsFiles | None = None, router: bool = False) -> dict | None:
    """Ask the namespace's running deployment (``op``: a DeploymentOp, status or stop) through the
    peers at ``connect`` (its workers; ``router``: the routers it joined through): the fields of
    its reply (StatusReply or StopReply, exact), or None when no deployment runs there."""
    check_security(secret, insecure, f"retriever {op}")
    keys = KeySpace(namespace)
    request = {DeploymentOp.STATUS: StatusQuery, DeploymentOp.STOP: StopQuery}[DeploymentOp(op)]()
    found: list[dict] = []
    refusing: list[str] = []

    def ask(session: zenoh.Session) -> None:
        for reply in session.get(keys.deployment(), payload=request.encode(), timeout=QUERY_S):
            if reply.ok is None:
                data = reply.err.payload.to_bytes()
                message = error_message(data)
                raise WorkerError(f"the deployment refused {op}: {repr(data[:200]) if message is None else message}")
            try:
                answer = DEPLOYMENT_REPLY.decode(reply.ok.payload.to_bytes())
            except WireError as e:
                raise WorkerError(f"the deployment answered {op} with garbage: {e}") from None
            if answer.NAME != request.NAME:
                raise WorkerError(f"the deployment answered {op} with its '{answer.NAME}' reply")
            found.append(answer.to_fields())
            return

    with open_access(namespace, None if secret is None else str(secret), tls, client=router) as access:
        for endpoint in connect:
            config = peer_config(connect=[endpoint], access=access)
            config.insert_json5("mode", '"client"')
            try:
                in_session(config, ask)
            except zenoh.ZError:  # nothing listens there, it refuses new links, or it wants another secret
                if why_no_session(endpoint, credentials(tls)) == REFUSES_LINKS:
                    refusing.append(endpoint)
                continue
            if found:
                return found[0]
    if refusing:  # not the secret: a stranger's idle connections (hub.ACCEPT_TIMEOUT_S)
        raise WorkerError(f"no session at {', '.join(refusing)}: {REFUSES_LINKS}\n    hint: keep strangers off "
                          "the workers' ports: a firewall, or TLS (docs/security.md)")
    return None


#: what a deploy.toml may hold, with the kind of each value: the flags of retriever deploy
DEPLOY_CONFIG = {"connect": "endpoints", "listen": "endpoints", "router": "endpoints", "namespace": "text", "placement": "path",
                 "duration": "seconds", "log": "path", "secret": "path", "insecure": "bool", "virtual_time": "bool",
                 "keep": "keep", "on_worker_loss": "text", "lease": "seconds", "max_clock_offset": "seconds",
                 "tls_ca": "path", "tls_cert": "path", "tls_key": "path"}


def load_deploy_config(path: str | os.PathLike) -> dict:
    """The settings of ``retriever deploy --config deploy.toml`` (DEPLOY_CONFIG; relative paths
    are relative to the file's folder); every problem at once, one a line."""
    path = Path(path)
    try:
        values = tomllib.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, tomllib.TOMLDecodeError, RecursionError) as e:
        raise BackendError(f"cannot read the deploy config {path}: {e}") from None
    problems = [f"'{key!s:.40}' is no setting of retriever deploy (it takes: {', '.join(DEPLOY_CONFIG)})"
                for key in values if key not in DEPLOY_CONFIG]
    settings = {}
    for key, kind in DEPLOY_CONFIG.items():
        if key not in values:
            continue
        value = values[key]
        if kind == "endpoints":
            value = [value] if isinstance(value, str) else value
            ok = isinstance(value, list) and all(isinstance(v, str) for v in value)
        elif kind == "seconds":
            ok = type(value) in (int, float) and 0 < value <= 1e9
        elif kind == "bool":
            ok = isinstance(value, bool)
        elif kind == "keep":
            ok = value in KEEP
        else:
            ok = isinstance(value, str)
            if ok and kind == "path":
                value = str(path.parent / value) if not os.path.isabs(value) else value
        if not ok:
            problems.append(f"'{key}' must be {DEPLOY_KINDS[kind]}, got {value!r:.60}")
        else:
            _check_deploy_value(key, kind, value, problems)
        settings[key] = value
    if problems:
        raise BackendError(f"the deploy config {path} has problems:\n" + "\n".join(f"  - {p}" for p in problems))
    return settings


def _check_deploy_value(key: str, kind: str, value, problems: list[str]) -> None:
    """A value of the right kind that the deployment would still refuse later, one problem per
    run: said now, with the others. The files it names are read, and judged, by their readers."""
    if kind == "endpoints":
        for endpoint in value:
            if not ENDPOINT.fullmatch(endpoint):
                problems.append(f"'{key}': {endpoint!r:.60} is no Zenoh endpoint: write PROTOCOL/ADDRESS, "
                                f"e.g. tcp/10.0.0.2:7447 (tls/... with TLS)")
    elif key == "namespace":
        try:
            check_chunk("'namespace'", value)
        except ValueError as e:
            problems.append(str(e))
    elif key == "on_worker_loss" and value not in WORKER_LOSS:
        problems.append(f"'on_worker_loss' must be one of {', '.join(WORKER_LOSS)}, got {value!r:.60}")


DEPLOY_KINDS = {"endpoints": "an endpoint or a list of them (\"tcp/HOST:PORT\")", "seconds": "a positive number of seconds (at most 1e9)",
                "bool": "true or false", "text": "a string", "path": "a file path (a string)",
                "keep": "\"records\" (values only in the log), \"trace\" (every value in memory) or \"counters\" "
                        "(nothing but counters)"}
