"""What the coordinator knows of a run: one record, in parts, that its handlers read and write.

No Zenoh and no process here: the statuses, reports, process supervision and waits of the
coordinator's other modules all keep their findings in one :class:`RunBook`, so that each of them
is a few functions over it (and benchmarks/fuzz.py feeds forged reports to it with no run around).
The book holds what is run-wide (the graph, the counters, T0, the end, whether values come: set by
core.py at the start) and one part per concern, each with the modules that write it:

    book.processes  Processes: each node's host, process and state     processes.py, statuses.py
    book.grants     Grants: virtual time granted, and reached by whom  waiting.py, statuses.py
    book.intake     Intake: what the reports brought, nodes' counters  reports.py (statuses.py, processes.py add to it)
    book.faults     Faults: restart budgets, lost processes' faults    processes.py (budgets: statuses.py too)
    book.ending     Ending: a failure, a step's sys.exit(0), a stop    statuses.py, processes.py, reports.py, waiting.py

core.py also sets the hosts the hosting placed and the live views it opened. A hosting reads the
book through a :class:`BookView` and writes nothing to it (hosting.HostedRun).
"""

from __future__ import annotations

import sys
import time
from collections import Counter
from collections.abc import Mapping
from dataclasses import dataclass, field
from types import MappingProxyType

from ....errors import RestartLimitError
from ....graph import Graph
from ....starved import StarvationWatch
from ....tick import RestartBudget
from ...base import NodeStats
from ..host import Host, WorkerProcess
from ..origin import Senders
from ..protocol import NodeState, State
from ..seen import EventIds, RecentTicks
from ..wire import WireError
from .faults import Fault, RunFailure

#: how many dropped messages are said on stderr (all are counted, as ``garbage``)
GARBAGE_SAID = 3


@dataclass(slots=True, eq=False)
class Processes:
    """The run's processes: where each node runs, its process, and what each process said.
    Written by the supervisor (processes.py: spawns, restarts afresh, reaps) and the status
    machine (statuses.py: each state a process says, its restarts and hand-overs)."""

    hosts: dict[str, Host] = field(default_factory=dict)  # where each node's processes run
    workers: dict[str, WorkerProcess] = field(default_factory=dict)  # each node's process
    #: a restarting node's old process, until it hands over
    retiring: dict[str, WorkerProcess] = field(default_factory=dict)
    retired: list[WorkerProcess] = field(default_factory=list)  # old processes that handed over, to reap
    #: nodes whose last restart's old process handed over: it waits for its reports to be in
    #: (the `finished` answer's handed_over), then exits; a new restart of the node clears it
    handed_over: set[str] = field(default_factory=set)
    #: each process's last state (statuses.PROCESS_STAGES) for each node it serves (a group's serves several)
    said: dict[tuple[WorkerProcess, str], State] = field(default_factory=dict)
    #: each node's state (as `retriever status` shows it): NodeState.STARTING, then what its process said
    state: dict[str, NodeState | State] = field(default_factory=dict)
    exited: dict[int, float] = field(default_factory=dict)  # pid -> when that worker process was first seen gone
    #: nodes whose process is a restarted flow's, not yet in the run (before resume or restarted)
    joining: set[str] = field(default_factory=set)
    #: a node started afresh: its seqs, till its next status
    restarted: dict[str, dict[str, int]] = field(default_factory=dict)
    #: who sent what (origin.py): the keys of each node's processes, and what was refused as forged
    senders: Senders = field(default_factory=Senders)
    #: the nodes whose process is a group's (spawn_group), a hosting's group of one among them
    grouped: set[str] = field(default_factory=set)
    #: the keys of nodes' first processes, made ahead (a dora run's, in its spec): taken at their spawn
    first_keys: dict[str, bytes] = field(default_factory=dict)

    def started(self) -> list[WorkerProcess]:
        """Every worker process this run started (a group's once)."""
        return list({id(p): p for p in [*self.workers.values(), *self.retiring.values(), *self.retired]}.values())

    def in_group(self, node: str) -> bool:
        """Whether ``node``'s process is a group's, its members' one (a hosting's group of one too:
        dora's), which none of them survives: none starts afresh on its own."""
        return node in self.grouped

    def nodes_of(self, host: Host) -> list[str]:
        """The nodes whose processes run on ``host``."""
        return sorted(n for n, h in self.hosts.items() if h is host)

    def expect_keys(self, keys: dict[str, bytes]) -> None:
        """The keys the first processes of these nodes will sign with, made by the hosting (a
        dora run's, in its spec) instead of at their spawn."""
        self.first_keys.update(keys)


@dataclass(slots=True, eq=False)
class Grants:
    """Lockstep virtual time: the ticks below ``granted`` (ns since T0) may run. Granted by the
    waits (waiting.py); what each node reached, as the status machine heard it (statuses.py)."""

    granted: int = 0
    #: per node, the last grant it said it reached
    reached: dict[str, int] = field(default_factory=dict)
    #: (when granted, when put last), monotonic s
    last_grant: tuple[float, float] = (0.0, 0.0)

    def reach(self, node: str, until: int) -> None:
        """``node`` ran every tick below ``until``: past the grant (one it was told by someone
        else), it reached this one on the way."""
        self.reached[node] = max(self.reached.get(node, -1), min(until, self.granted))


@dataclass(slots=True, eq=False)
class Intake:
    """What the workers' reports brought: the events and step records seen, each node's counters.
    Written by the report ingest (reports.py); the status machine adds what a process says of
    itself (its counters, the reports it sent, its ``done``: statuses.py), the supervisor a
    restart's counters, ``have`` and the ``unseen`` a lost process's fault claims (processes.py)."""

    stats: dict[str, NodeStats]
    #: (producer, port, consumer) of every edge: a consumer may report the events it got there
    feeds: set[tuple[str, str, str]]
    # reports handled, and reports sent as the node's processes said when they ended: Zenoh
    # orders messages per key only, so a last report may come after the `done` status
    reports: dict[str, int]
    reports_sent: dict[str, int]
    streams: set[tuple[str, str]]  # (node, port) of every output port
    #: nodes whose flows may emit on ports no edge names (untyped: a dict step's extra keys)
    open_outputs: set[str]
    #: inputs that had no event for long while their producers made events (starved.py)
    starvation: StarvationWatch
    event_ids: EventIds = field(default_factory=EventIds)  # every event id seen (as runs of seqs: bounded memory)
    # events a consumer's report carried for its producer (node/reports.py, HOLD_RECORDS_NS), and
    # per stream the last seq the coordinator has, told to the consumers (control `have`)
    carried: set[tuple[str, str, int]] = field(default_factory=set)
    have: dict[tuple[str, str], int] = field(default_factory=dict)
    have_told: dict[tuple[str, str], int] = field(default_factory=dict)
    #: (node, tag) of the step records seen (the recent ones, then a floor)
    ticks: RecentTicks = field(default_factory=RecentTicks)
    #: per stream, the highest seq known (events and records)
    max_seq: dict[tuple[str, str], int] = field(default_factory=dict)
    #: event ids that records produced and no report carried yet
    unseen: set[tuple[str, str, int]] = field(default_factory=set)
    done_info: dict[str, dict] = field(default_factory=dict)  # what each node's worker said of its run when done
    #: bytes of the workers' reports (step records and events) received, spilled ones included
    reported_bytes: int = 0
    live: object = None  # the live views (log/live.py), fed with what the reports bring (set by the core)

    @classmethod
    def of(cls, graph: Graph) -> Intake:
        return cls(stats={nid: NodeStats() for nid in graph.nodes},
                   feeds={(e.src, e.src_port, e.dst) for e in graph.edges},
                   reports={nid: 0 for nid in graph.nodes}, reports_sent={nid: 0 for nid in graph.nodes},
                   streams={(nid, port) for nid, node in graph.nodes.items() for port in node.outputs},
                   open_outputs={nid for nid, node in graph.nodes.items() if node.spec.out_mode == "dict"},
                   starvation=StarvationWatch(graph))


@dataclass(slots=True, eq=False)
class Faults:
    """Restarts and lost processes (node/handover.py): each node's restart budget (a restart the
    flow asks for takes from it too: statuses.py), the nodes starting afresh, and the faults of the
    run's processes. Written by the supervisor (processes.py)."""

    restarts: dict[str, RestartBudget]
    #: the nodes starting afresh, by what became of the old process
    fresh: dict[str, Fault] = field(default_factory=dict)
    #: faults of processes not started afresh, logged once their last reports are in
    unrecovered: list[Fault] = field(default_factory=list)
    #: what went wrong with the run's processes (each a fault record of the log)
    logged: list[Fault] = field(default_factory=list)

    @classmethod
    def of(cls, graph: Graph) -> Faults:
        return cls({nid: RestartBudget(node.settings.max_restarts, node.settings.restart_window)
                    for nid, node in graph.nodes.items()})


@dataclass(slots=True, eq=False)
class Ending:
    """How the run ends: a failure, a step's sys.exit(0), a stop this coordinator sent. Written by
    the status machine (statuses.py), the supervisor (processes.py), the report ingest (an exit's
    record: reports.py) and, in virtual time, the waits (the earliest exit: waiting.py)."""

    failure: RunFailure | None = None  # the node that failed the run, and why
    limit: RestartLimitError | None = None  # a flow ran out of restarts (on_error="restart")
    # a step's sys.exit(0): its `exit` status ends the run once its process's record of
    # that step (status ok, detail {"exit": 0}) is in; per node, the (tag, process) of each
    exit_said: dict[str, tuple[tuple[int, int], object]] = field(default_factory=dict)
    exit_recorded: dict[str, tuple[tuple[int, int], object]] = field(default_factory=dict)
    stop_sent: bool = False  # whether this coordinator told the workers to stop
    ended_by: str | None = None  # the node whose step called sys.exit(0), ending the run


class RunBook:
    """The coordinator's record of one run: its nodes' processes and states (``processes``),
    virtual time's grants (``grants``), what their reports brought (``intake``), their faults
    (``faults``) and how the run ends (``ending``). ``counts``: the session's own counters
    (``garbage``, ``forged``)."""

    __slots__ = ("graph", "counts", "t0", "end_ns", "values", "forged_told",
                 "processes", "grants", "intake", "faults", "ending")

    def __init__(self, graph: Graph, counts: Counter):
        self.graph = graph
        self.counts = counts
        self.t0: int | None = None  # HLC Unix ns of the run's start
        self.end_ns = 0  # the run's end, ns since T0
        self.values = True  # whether the workers report their events' values (set at the start)
        self.forged_told = 0  # how many refused as forged were told (tell_forged)
        self.processes = Processes()
        self.grants = Grants()
        self.intake = Intake.of(graph)
        self.faults = Faults.of(graph)
        self.ending = Ending()

    def run_time(self) -> int:
        """Now, in ns since T0 (0 before the start)."""
        return max(0, time.time_ns() - self.t0) if self.t0 is not None else 0

    def finished(self) -> bool:
        """Every node done, and every report it sent in."""
        intake = self.intake
        return (all(s == State.DONE for s in self.processes.state.values())
                and all(intake.reports[n] >= intake.reports_sent[n] for n in intake.reports))

    def garbage(self, key: str, error: WireError) -> None:
        """Drop a message that is no message of the run: counted, the first few said."""
        self.counts["garbage"] += 1
        if self.counts["garbage"] <= GARBAGE_SAID:
            print(f"retriever: dropped a message on {key}: {error}", file=sys.stderr, flush=True)

    def tell_forged(self) -> None:
        """Count what was refused as forged (``forged``), and say so on stderr when more came."""
        senders = self.processes.senders
        refused = senders.refused
        if refused == self.forged_told:
            return
        self.counts["forged"] = refused
        if self.forged_told == 0:
            print(f"retriever: refused a message or record that no process of the run's node made: "
                  f"{senders.reasons[0]} (counted as 'forged'; a process holding the run's secret?)",
                  file=sys.stderr, flush=True)
        self.forged_told = refused


class BookView:
    """What a hosting reads of the run's book (hosting.HostedRun): the run's time, and each node's
    host, process, state and counters, as they are when asked. It writes nothing: what a hosting
    changes in the run goes through HostedRun's callables and the decisions it returns."""

    __slots__ = ("_book",)

    def __init__(self, book: RunBook):
        self._book = book

    @property
    def t0(self) -> int | None:
        return self._book.t0

    @property
    def end_ns(self) -> int:
        return self._book.end_ns

    def run_time(self) -> int:
        return self._book.run_time()

    @property
    def hosts(self) -> Mapping[str, Host]:
        return MappingProxyType(self._book.processes.hosts)

    @property
    def workers(self) -> Mapping[str, WorkerProcess]:
        return MappingProxyType(self._book.processes.workers)

    @property
    def state(self) -> Mapping[str, NodeState | State]:
        return MappingProxyType(self._book.processes.state)

    @property
    def stats(self) -> Mapping[str, NodeStats]:
        return MappingProxyType(self._book.intake.stats)

    def processes(self) -> list[WorkerProcess]:
        """Every worker process the run started (a group's once)."""
        return self._book.processes.started()
