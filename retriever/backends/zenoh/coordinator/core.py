"""The coordinator of a real-time run: its setup, its run, its close (the package's docstring
draws it). Its handlers live in the sibling modules; this one wires them to a hub and a hosting."""

from __future__ import annotations

import atexit
import os
import secrets
import shutil
import sys
import threading
import time
import warnings
import weakref
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import zenoh

from ....errors import BackendError, RetrieverWarning
from ....graph import Graph
from ....plan import plan_graph, tie_order
from ....trace import Trace
from ...base import NodeStats, Session
from ..hub import new_zid, weak_callback
from ..protocol import Finished, RunSpec, Start, State
from ..wire import KeySpace
from .book import BookView, RunBook
from .control import RunControl
from .diagnostics import Diagnostics
from .endchecks import (check_every_flow_ticked, check_exit_recorded, record_starved, warn_forged,
                        warn_starved_by_late_events)
from .exits import ExitCut
from .faults import Fault
from .hosting import HostedRun, Hosting, LocalHosting
from .inbox import Inbox
from .processes import STOP_GRACE_S, Supervisor
from .reports import ReportIngest
from .spec import main_file, process_groups, python_path, run_dir, shipped_plan
from .statuses import StatusMachine
from .waiting import Waits

#: after the run, how long the workers' last lines have to reach this process's stderr
OUTPUT_DRAIN_S = 1.0

#: coordinators not closed yet
_OPEN: weakref.WeakSet = weakref.WeakSet()


def _close_open_coordinators() -> None:
    """Close what a program left open (an error before its run, a forgotten pipe.reset()): its
    workers are stopped and its hub closed. At exit Python joins the threads Zenoh started before
    it runs atexit hooks, and an open session's threads never end: the process hung there."""
    for coordinator in list(_OPEN):
        coordinator.close()


try:  # threading's own exit hooks run before that join (concurrent.futures uses them too)
    threading._register_atexit(_close_open_coordinators)
except (AttributeError, RuntimeError):  # another Python: atexit, which may come too late
    atexit.register(_close_open_coordinators)


class Coordinator(Session):
    """A run of ``graph`` in worker processes, one per node, wherever ``hosting`` puts them
    (this machine by default: :class:`LocalHosting`)."""

    holds_processes = True

    def __init__(self, graph: Graph, *, hosting: Hosting | None = None, namespace: str | None = None,
                 startup_timeout: float = 60.0, start_margin: float = 0.3, hub_port: int = 0, quiet: bool = False,
                 secret: str | os.PathLike | bytes | None = None, virtual_time: bool = False, keep: str = "trace",
                 foxglove: int | None = None, rerun: str | os.PathLike | None = None, same_host_links: bool = True):
        if rerun is not None:  # a target that cannot be one is said before anything starts
            from ....log.rerun_live import check_target

            check_target(rerun)
        super().__init__(graph, keep)
        self.hosting = hosting if hosting is not None else LocalHosting()
        self.backend_name = self.hosting.backend_name
        #: the port of a Foxglove live view (its WebSocket server, in this process), if asked for
        self.foxglove_port = foxglove
        #: where a Rerun live view streams (a viewer's gRPC URL or an .rrd path), if asked for
        self.rerun_target = rerun
        self.quiet = quiet
        #: lockstep virtual time (node/waiting.py): the trace is the in-process backend's, however long it takes
        self.virtual_time = bool(virtual_time)
        if self.virtual_time and graph.instantaneous_cycles:
            cycle = graph.instantaneous_cycles[0]
            raise BackendError(
                f"zenoh in virtual time cannot run the instantaneous cycle {' → '.join([*cycle, cycle[0]])} (yet): "
                "each of its flows waits for the other's promise of what comes next, one microstep at a time\n"
                "    hint: give an edge of the cycle a delay= or a flow on it a latency=, or run it on inproc "
                "(virtual time too) or on zenoh in real time")
        refuse_in_a_worker(graph)
        self.hosting.check_deployable(graph)
        self.namespace = namespace or f"run-{os.getpid()}-{secrets.token_hex(3)}"
        self.keys = KeySpace(self.namespace)
        self.access = self.hosting.run_access(self.namespace, secret)
        self.startup_timeout = startup_timeout
        #: whether the edges between its processes go over same-host links where the hosting puts every
        #: process on this host (LocalHosting): ``same_host_links=False`` keeps them all on Zenoh
        self.same_host_links = bool(same_host_links) and self.hosting.one_host
        self.start_margin_ns = round(start_margin * 1e9)
        self.book = RunBook(graph, self.own_counts)
        self.ran = self.closed = False
        self.run_dir = run_dir()
        self.hub = None
        self.subscribers: list = []
        self.hosted = HostedRun(graph, self.namespace, self.keys, self.access, self.run_dir, BookView(self.book),
                                keep=self.subscribers.append, stop=self._stop_asked, closed=lambda: self.closed,
                                expect_keys=self.book.processes.expect_keys)
        self.hosting.attach(self.hosted)
        _OPEN.add(self)  # closed at the interpreter's exit at the latest (see _close_open_coordinators)
        try:
            self._open(hub_port)
        except BaseException:
            self.close()
            raise

    def _open(self, hub_port: int) -> None:
        """Open the hub, listen, place the nodes and start their workers."""
        access, graph = self.access, self.graph
        dictionary = self.hosting.hub_dictionary(access, self.run_dir) if access else None
        self.hub, self.endpoint = self.hosting.open_hub(hub_port, access.session_config(dictionary) if access else None)
        #: a Zenoh config file with which a client joins the run as a read-only watcher
        self.watch_config = (access.write_watcher_config(self.run_dir / "watch.json5", self.endpoint,
                                                         self.hosting.watcher_user()) if access else None)
        self.hosted.hub, self.hosted.endpoint, self.hosted.watch_config = self.hub, self.endpoint, self.watch_config
        if not self.quiet:
            print(f"retriever: {self.hosting.where()} (namespace '{self.namespace}'); {self.hosting.how_to_watch()}",
                  file=sys.stderr, flush=True)
        self._assemble(RunControl(self.hub, self.keys))
        self._listen()
        groups = self._groups()
        zids = {nid: new_zid() for nid in graph.nodes}
        for members in groups.values():  # one session for a group: its members' id
            zids.update(dict.fromkeys(members, zids[members[0]]))
        # (each field held as its decoder reads it, tuples and floats: a field at its default is
        # left out of the file and of the prepare request alike)
        self.hosted.spec = RunSpec(
            ir=graph.to_ir().doc, namespace=self.namespace, hub=self.endpoint,
            plan=shipped_plan(graph),  # the run's wiring, made once: retriever.plan
            python_path=tuple(python_path()), main_file=main_file(graph), argv=tuple(sys.argv),
            spill_dir=str(self.run_dir), access=access.to_spec(dictionary) if access else None,
            startup_timeout=float(self.startup_timeout),
            # each first process's session id, and the hub's: a worker says ready once
            # linked to its neighbours and the hub, whatever other peers it has
            zids=zids, hub_zid=str(self.hub.zid()),
            virtual_time=self.virtual_time, groups={name: tuple(members) for name, members in groups.items()},
            links=self.same_host_links)
        self.book.processes.hosts = self.hosting.place()
        grouped = {nid for members in groups.values() for nid in members}
        for name, members in groups.items():
            self.supervisor.spawn_group(name, members)
        for nid in graph.nodes:
            if nid not in grouped:
                self.supervisor.spawn(nid)

    def _groups(self) -> dict[str, list[str]]:
        """The groups of flows that share a process, where the hosting starts them so."""
        named = self.hosting.process_names()
        groups = process_groups(self.graph, named)
        if groups and not self.hosting.shares_processes:
            warnings.warn(f"the {self.backend_name} backend {self.hosting.where()} starts each flow in a process of "
                          f"its own: configure(process=) ({', '.join(sorted(groups))}) is not taken here (yet)",
                          RetrieverWarning, stacklevel=4)
            return {}
        alone = set(self.hosting.groups_of_one(self.graph, groups))
        if alone:  # (in the graph's order, as the others)
            groups = {**groups, **{nid: [nid] for nid in self.graph.nodes if nid in alone}}
        return groups

    def _assemble(self, control: RunControl) -> None:
        """The coordinator's parts, each with one job, over one record of the run (``book``)."""
        parts = assemble(self.book, self.trace, self.run_dir, control, self.hosting, backend_name=self.backend_name,
                         on_fault=self._log_fault, virtual_time=self.virtual_time,
                         startup_timeout=self.startup_timeout)
        self.control, self.diagnostics, self.supervisor = parts.control, parts.diagnostics, parts.supervisor
        self.statuses, self.inbox = parts.statuses, parts.inbox
        self.waits = Waits(self, self.book, self.inbox, control, self.supervisor, self.diagnostics, parts.exits)

    def _listen(self) -> None:
        """Take the workers' statuses and reports, answer their questions (what is finished, the start)."""
        put, senders = self.inbox.put, self.book.processes.senders

        def take(sample) -> None:  # on Zenoh's thread: what no process of the node signed is held nowhere
            key, data, mac = str(sample.key_expr), sample.payload.to_bytes(), sample.attachment
            sender = senders.sender(key.rsplit("/", 1)[1], key, data, None if mac is None else mac.to_bytes())
            if sender is not None:
                put((key, data, sender))

        self.subscribers += [
            self.hub.declare_subscriber(self.keys.status("**"), take),
            self.hub.declare_queryable(self.keys.finished(), weak_callback(self._answer_finished)),
            self.hub.declare_queryable(self.keys.start(), weak_callback(self._answer_start))]

    def _answer_finished(self, query) -> None:
        """Which nodes are done, which of them have every report in, which start afresh after
        their process died (a restarted flow's process waits for answers from the others, but
        from these), and whose old process that handed over has every report in (it may exit)."""
        procs, intake = self.book.processes, self.book.intake
        states = list(procs.state.items())
        done = tuple(sorted(node for node, state in states if state == State.DONE))
        # and whose every report is in: their processes may now close their sessions (worker/waits.py,
        # REPORTS_TAKEN_S)
        def all_in(node: str) -> bool:
            return intake.reports.get(node, 0) >= intake.reports_sent.get(node, 0)

        complete = tuple(sorted(node for node, state in states if state in (State.DONE, State.HANDED_OVER)
                                and all_in(node)))
        handed_over = tuple(sorted(node for node in procs.handed_over if all_in(node)))
        self.control.reply(query, self.keys.finished(), Finished(nodes=done, complete=complete,
                                                                 restarting=tuple(sorted(self.book.faults.fresh)),
                                                                 handed_over=handed_over))

    def _answer_start(self, query) -> None:
        """T0 and the end, to a worker that said ready and has not seen ``start`` (a put it may
        have missed: see START_ASK_S in worker/waits.py); nothing before the run has a start."""
        t0 = self.book.t0
        if t0 is not None:
            self.control.reply(query, self.keys.start(), Start(t0=t0, end=self.book.end_ns, values=self.book.values))

    def _stop_asked(self) -> None:
        """End the run at the next look, as Ctrl-C here would (a hosting told ``retriever stop``)."""
        self.stop_requested = True

    def _log_fault(self, fault: Fault) -> None:
        if self.log is not None:
            self.log.add_fault(fault.log_fields())

    # ---------------------------------------------------------------------------------------
    # The run
    # ---------------------------------------------------------------------------------------
    def advance(self, until_ns: int) -> None:
        if self.ran:
            raise BackendError("a real-time run on the zenoh backend cannot be continued: wall time went on\n"
                               "    hint: give the whole duration to one pipe.run(duration=...), or pipe.reset()")
        self.ran = True
        book = self.book
        try:
            self.waits.until_ready(self.startup_timeout)
            self._start_live_views()  # before T0: reaching a viewer may take seconds
            book.t0 = self.hub.new_timestamp().get_time_as_ntp64().as_nanos() + self.start_margin_ns
            book.end_ns = until_ns
            # values come to the coordinator only for the trace (keep="trace"), the log, or a live view
            book.values = self.keep == "trace" or self.log is not None or book.intake.live is not None
            self.waits.until_finished(Start(t0=book.t0, end=until_ns, values=book.values), self.virtual_time)
        except BaseException:
            self.stop_workers()  # their last reports, then: which outputs died with a process
            book.tell_forged()
            self.supervisor.record_faults_left()
            record_starved(book, self.log)
            self.close()
            raise
        # in virtual time, a step's sys.exit(0) ended the run at its tick, as in-process
        ended_by = book.ending.ended_by
        self.now_ns = book.ending.exit_said[ended_by][0][0] if self.virtual_time and ended_by else until_ns
        self.supervisor.record_faults_left()
        record_starved(book, self.log)
        self.close()  # a real-time run is over when its time is: workers reaped, hub closed
        warn_forged(book)
        check_exit_recorded(book, self.backend_name)
        check_every_flow_ticked(book, self.backend_name, self.start_margin_ns)
        warn_starved_by_late_events(book, self.trace)

    def _start_live_views(self) -> None:
        from ....log.live import open_live_views

        def say(text: str) -> None:
            if not self.quiet:
                print(f"retriever: {text}", file=sys.stderr, flush=True)

        self.book.intake.live = open_live_views(self.graph.to_ir(), foxglove=self.foxglove_port,
                                                rerun=self.rerun_target, say=say)

    def stop_workers(self, grace: float = STOP_GRACE_S) -> None:
        """Stop every worker (processes.Supervisor.stop); nothing before the hub is open."""
        if self.hub is not None:
            self.supervisor.stop(grace)

    def close(self) -> None:
        if self.closed:
            return
        self.closed = True
        book = self.book
        if any(p.poll() is None for p in book.processes.started()):
            self.stop_workers()
        if book.intake.live is not None:
            book.intake.live.close()
        give_up = time.monotonic() + OUTPUT_DRAIN_S  # their last lines, before the run returns
        for output in {id(o): o for host in book.processes.hosts.values() for o in host.outputs()}.values():
            output.drain(max(0.0, give_up - time.monotonic()))
        if self.hub is not None:
            self.hosting.release()
            for sub in self.subscribers:
                sub.undeclare()
            try:
                self.hub.close()
            except zenoh.ZError as e:
                # a link whose peer stopped reading (a watcher suspended with SIGSTOP, its socket
                # full) holds the close 10 s: Zenoh sets SO_LINGER 10 s on its TCP sockets, and
                # close() waits that long for unsent bytes, as long as the session's close timeout
                # (10 s). The run is over and recorded all the same; the hub's session goes with
                # this process
                print(f"retriever: the run's hub did not close in time: a peer connected to it stopped reading "
                      f"(a suspended watcher?) ({e})", file=sys.stderr, flush=True)
            self.hub = None
        shutil.rmtree(self.run_dir, ignore_errors=True)
        _OPEN.discard(self)

    # ---------------------------------------------------------------------------------------
    # What the run says of itself
    # ---------------------------------------------------------------------------------------
    def stats(self) -> dict[str, NodeStats]:
        return self.book.intake.stats

    def produced_counts(self) -> dict[tuple[str, str], int]:
        # from the step records' produced ids, which every run reports whatever it keeps
        return {key: seq + 1 for key, seq in self.book.intake.max_seq.items()}

    def worker_pids(self) -> dict[str, int]:
        """PIDs of the worker processes, by node (for tests and tools)."""
        return {nid: p.pid for nid, p in self.book.processes.workers.items()}

    def log_metadata(self) -> dict[str, str]:
        """``time``: a run in lockstep virtual time says so (its wall times mean nothing); and
        what the hosting says of where it ran (a deployment's workers)."""
        return {**({"time": "virtual"} if self.virtual_time else {}), **self.hosting.log_metadata()}

    @property
    def starved(self) -> list[dict]:
        """Each span in which an input had no event while its producers made some (starved.py)."""
        return self.book.intake.starvation.episodes

    @property
    def t0(self) -> int | None:
        """HLC Unix ns of the run's start (None before it)."""
        return self.book.t0

    @property
    def end_ns(self) -> int:
        return self.book.end_ns

    @property
    def ended_by(self) -> str | None:
        """The node whose step called sys.exit(0), ending the run."""
        return self.book.ending.ended_by

    @property
    def faults(self) -> list[dict]:
        """What went wrong with the run's processes, as the log's fault records have it."""
        return [fault.log_fields() for fault in self.book.faults.logged]

    @property
    def reported_bytes(self) -> int:
        """Bytes of the workers' reports (step records and events) received, spilled ones included."""
        return self.book.intake.reported_bytes

    @property
    def live(self):
        """The live views fed with what the reports bring (log/live.py), if any were asked for."""
        return self.book.intake.live


@dataclass(frozen=True)
class Parts:
    """What handles a run's messages and processes, wired to one RunBook (see :func:`assemble`)."""

    control: RunControl
    diagnostics: Diagnostics
    supervisor: Supervisor
    statuses: StatusMachine
    inbox: Inbox
    #: virtual time: the records held until no step's sys.exit(0) can cut them off
    exits: ExitCut | None = None


def assemble(book: RunBook, trace: Trace, spill_dir: Path, control: RunControl, hosting: Hosting, *,
             backend_name: str = "zenoh", on_fault: Callable[[Fault], None] = lambda fault: None,
             virtual_time: bool = False, startup_timeout: float = 60.0) -> Parts:
    """The coordinator's parts over ``book``: what a Coordinator runs on, and what a test or
    benchmarks/fuzz.py feeds messages to with no hub and no process (``control`` over a stand-in)."""
    diagnostics = Diagnostics(book, hosting)
    supervisor = Supervisor(book, control, hosting, diagnostics, backend_name=backend_name, on_fault=on_fault)
    exits = ExitCut(tie_order(plan_graph(book.graph))) if virtual_time else None
    statuses = StatusMachine(book, control, supervisor, exits=exits, startup_timeout=startup_timeout)
    reports = ReportIngest(book, trace, spill_dir, statuses.end_by_exit, exits)
    inbox = supervisor.inbox = Inbox(control.keys, reports, statuses)
    return Parts(control, diagnostics, supervisor, statuses, inbox, exits)


def refuse_in_a_worker(graph: Graph) -> None:
    from .. import worker

    if worker.serving is not None:
        raise BackendError(f"pipeline '{graph.name}' was started in the worker process of node '{worker.serving}', "
                           "while it imported its flow: a module of the run starts a pipeline when it is imported "
                           "(workers import the modules of their flows, the main script as __mp_main__)\n"
                           "    hint: start the run under `if __name__ == \"__main__\":`")
