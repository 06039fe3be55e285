"""The worker-loss policy: what a deployment does with the nodes of a worker it lost
(``on_worker_loss``): move them, wait for the worker, or stop the run; through a router, a lost
router loses every worker."""

from __future__ import annotations

import sys

import zenoh

from ....placement import Placement, move
from ..daemon import describe
from ..hub import router_linked
from ..coordinator.faults import Fault
from ..coordinator.hosting import AwaitHost, FailRun, HostedRun, HostLoss, Relocate
from .book import WorkerBook
from .links import Links

#: what a deployment does with the nodes of a worker it lost: start them afresh on another worker
#: that their placement allows (the least loaded), or on it once it is back, or stop
WORKER_LOSS = ("replace", "wait", "stop")


class LossPolicy:
    """A lost worker's nodes, as ``on_worker_loss`` says (one of WORKER_LOSS), for the
    deployment's run; the workers waited for, and those of them back."""

    def __init__(self, run: HostedRun, links: Links, book: WorkerBook, placement: Placement | None,
                 on_worker_loss: str):
        self.run, self._links, self._book = run, links, book
        self._placement, self._on_worker_loss = placement, on_worker_loss
        self._waiting: dict[str, dict] = {}  # lost workers waited for (on_worker_loss="wait"): nodes, when
        self._returned: set[str] = set()  # of those, the ones whose token came back

    def check(self) -> None:
        """Through a router: once the hub's link to it is gone, every worker is (_router_lost).
        Their tokens' ends are not told to a subscriber that came after the tokens, as the
        coordinator's did (Zenoh tells only those that asked for their history)."""
        if self._links.router and self._book.remotes and not router_linked(self.run.hub):
            for host in list(self._book.remotes.values()):
                host.lost()

    def host_lost(self, host, nodes: list[str]) -> HostLoss | None:
        """on_worker_loss="replace": each of its nodes starts afresh on a worker still up that its
        placement allows, by the rule of the first placement (placement.move; as a flow whose
        process died: node/handover.py); the log's fault record says where it went. Any node that has
        nowhere to go stops the run. "wait": they start afresh on it once a worker of its name is
        up again (see _await_return). None: the hosting's default (Hosting.host_lost: the run stops)."""
        run = self.run
        if self._links.router and not router_linked(run.hub):
            return self._router_lost(host, nodes)
        if self._on_worker_loss == "stop" or run.book.t0 is None:
            return None
        if self._on_worker_loss == "wait":
            return self._await_return(host, nodes)
        self._book.remotes.pop(host.name, None)
        self._book.daemons.pop(host.name, None)
        targets = move(nodes, self._placement, self._book.workers_up(), run.spec.groups)  # a group's together
        if targets is None:
            return None
        return self._move(host.name, targets, run.book.run_time())

    def _router_lost(self, host, nodes: list[str]) -> FailRun:
        """The coordinator's link to its router went, and with it every worker's token: the run
        stops, saying so (the workers' daemons lost the coordinator's token the same way, and
        stop its flows). Zenoh joins the router again by itself once it is back, but nothing
        of the run went through it meanwhile."""
        routers = ", ".join(self._links.router)
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
        daemon = describe(self._links.control, run.namespace, name)
        if daemon.info is None:
            return AwaitHost()  # not (yet) a worker that answers as one (of this protocol): wait on
        del self._waiting[name]
        self._book.daemons[name] = daemon  # a new daemon of that name: a session of its own
        self._book.remotes.pop(name).close()
        return self._move(name, {nid: name for nid in nodes}, waiting["at"])

    def _move(self, lost: str, targets: dict[str, str], at: int) -> Relocate:
        """Each node of ``targets`` (the lost worker's) to start afresh on its worker there,
        prepared for it."""
        run, book = self.run, self._book
        for name in sorted(set(targets.values())):
            remote = book.host_of(name, self._links.control, run.keys, self._links.secret)
            book.say_warnings(name, remote.prepare(self._links.spec_for(run, name, book.daemons),
                                                   sorted(n for n, w in targets.items() if w == name)))
        for nid, name in sorted(targets.items()):
            print(f"retriever: worker '{lost}' was lost; its node '{nid}' starts afresh on worker '{name}'",
                  file=sys.stderr, flush=True)
        book.placed.update(targets)
        return Relocate({nid: book.remotes[name] for nid, name in targets.items()}, dict(targets), at,
                        f"was lost with its worker '{lost}'")

    def worker_token(self, sample: zenoh.Sample) -> None:
        """A worker's liveliness: gone, its processes are as good as killed."""
        name = str(sample.key_expr).rsplit("/", 1)[-1]
        if sample.kind == zenoh.SampleKind.DELETE:
            host = self._book.remotes.get(name)
            if host is not None:
                host.lost()
        elif name in self._waiting:  # back (on_worker_loss="wait"): the main loop moves its nodes there
            self._returned.add(name)

    def faults_left(self) -> list[Fault]:
        """The nodes of the workers still waited for at the run's end: lost, and never back."""
        workers, faults = self.run.book.workers, []
        for waiting in self._waiting.values():
            faults += [Fault(nid, waiting["at"], workers[nid].pid, "was lost with its worker")
                       for nid in waiting["nodes"]]
        self._waiting.clear()
        return faults
