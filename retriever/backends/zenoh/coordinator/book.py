"""What the coordinator knows of a run: one record that its handlers read and write.

No Zenoh and no process here: the statuses, reports, process supervision and waits of the
coordinator's other modules all keep their findings in one :class:`RunBook`, so that each of them
is a few functions over it (and benchmarks/fuzz.py feeds forged reports to it with no run around).
"""

from __future__ import annotations

import sys
import time
from collections import Counter

from ....errors import RestartLimitError
from ....graph import Graph
from ....starved import StarvationWatch
from ...base import NodeStats, RestartBudget
from ..host import Host, WorkerProcess
from ..origin import Senders
from ..protocol import NodeState, State
from ..seen import EventIds, RecentTicks
from ..wire import WireError
from .faults import Fault, RunFailure

#: how many dropped messages are said on stderr (all are counted, as ``garbage``)
GARBAGE_SAID = 3


class RunBook:
    """The coordinator's record of one run: its nodes' processes and states, what their reports
    brought, and what went wrong. ``counts``: the session's own counters (``garbage``, ``forged``)."""

    def __init__(self, graph: Graph, counts: Counter):
        self.graph = graph
        self.counts = counts
        self.t0: int | None = None  # HLC Unix ns of the run's start
        self.end_ns = 0  # the run's end, ns since T0
        self.values = True  # whether the workers report their events' values (set at the start)
        self.live = None  # the live views (log/live.py), fed with what the reports bring
        #: bytes of the workers' reports (step records and events) received, spilled ones included
        self.reported_bytes = 0
        self._init_processes(graph)
        self._init_reports(graph)
        self._init_faults(graph)

    def _init_processes(self, graph: Graph) -> None:
        self.hosts: dict[str, Host] = {}  # where each node's processes run
        self.workers: dict[str, WorkerProcess] = {}  # each node's process
        self.retiring: dict[str, WorkerProcess] = {}  # a restarting node's old process, until it hands over
        self.retired: list[WorkerProcess] = []  # old processes that handed over, to reap
        #: nodes whose last restart's old process handed over: it waits for its reports to be in
        #: (the `finished` answer's handed_over), then exits; a new restart of the node clears it
        self.handed_over: set[str] = set()
        #: each process's last state (statuses.PROCESS_STAGES) for each node it serves (a group's serves several)
        self.said: dict[tuple[WorkerProcess, str], State] = {}
        #: each node's state (as `retriever status` shows it): NodeState.STARTING, then what its process said
        self.state: dict[str, NodeState | State] = {}
        self.exited: dict[int, float] = {}  # pid -> when that worker process was first seen gone
        #: nodes whose process is a restarted flow's, not yet in the run (before resume or restarted)
        self.joining: set[str] = set()
        self.restarted: dict[str, dict[str, int]] = {}  # a node started afresh: its seqs, till its next status
        # who sent what (origin.py): the keys of each node's processes, the first ones made
        # ahead (a dora run's, in its spec), and what was refused as forged
        self.senders = Senders()
        self.first_keys: dict[str, bytes] = {}
        self.forged_told = 0
        # virtual time: the ticks below ``granted`` (ns since T0) may run; per node, the last
        # grant it said it reached; (when granted, when put last), monotonic s
        self.granted = 0
        self.reached: dict[str, int] = {}
        self.last_grant = (0.0, 0.0)

    def _init_reports(self, graph: Graph) -> None:
        self.stats = {nid: NodeStats() for nid in graph.nodes}
        self.event_ids = EventIds()  # every event id seen (as runs of seqs: bounded memory)
        # events a consumer's report carried for its producer (node/reports.py, HOLD_RECORDS_NS), and per
        # stream the last seq the coordinator has, told to the consumers (control `have`)
        self.carried: set[tuple[str, str, int]] = set()
        self.have: dict[tuple[str, str], int] = {}
        self.have_told: dict[tuple[str, str], int] = {}
        self.feeds = {(e.src, e.src_port, e.dst) for e in graph.edges}
        # reports handled, and reports sent as the node's processes said when they ended: Zenoh
        # orders messages per key only, so a last report may come after the `done` status
        self.reports = {nid: 0 for nid in graph.nodes}
        self.reports_sent = {nid: 0 for nid in graph.nodes}
        self.ticks = RecentTicks()  # (node, tag) of the step records seen (the recent ones, then a floor)
        self.max_seq: dict[tuple[str, str], int] = {}  # per stream, the highest seq known (events and records)
        self.unseen: set[tuple[str, str, int]] = set()  # event ids that records produced and no report carried yet
        self.streams = {(nid, port) for nid, node in graph.nodes.items() for port in node.outputs}
        # untyped flows may emit on ports no edge names (a dict step's extra keys)
        self.open_outputs = {nid for nid, node in graph.nodes.items() if node.spec.out_mode == "dict"}
        self.done_info: dict[str, dict] = {}  # what each node's worker said of its run when done
        #: inputs that had no event for long while their producers made events (starved.py)
        self.starvation = StarvationWatch(graph)

    def _init_faults(self, graph: Graph) -> None:
        self.restarts = {nid: RestartBudget(node.settings.max_restarts, node.settings.restart_window)
                         for nid, node in graph.nodes.items()}
        self.failure: RunFailure | None = None  # the node that failed the run, and why
        self.limit: RestartLimitError | None = None  # a flow ran out of restarts (on_error="restart")
        # a step's sys.exit(0): its `exit` status ends the run once its process's record of
        # that step (status ok, detail {"exit": 0}) is in; per node, the (tag, process) of each
        self.exit_said: dict[str, tuple[tuple[int, int], object]] = {}
        self.exit_recorded: dict[str, tuple[tuple[int, int], object]] = {}
        self.stop_sent = False  # whether this coordinator told the workers to stop
        self.ended_by: str | None = None  # the node whose step called sys.exit(0), ending the run
        self.stackless: dict[str, float] = {}  # nodes asked for their stacks that printed none, and how long waited
        # a lost process (node/handover.py): the nodes starting
        # afresh, by what became of the old process; faults of processes not started afresh
        self.fresh: dict[str, Fault] = {}
        self.unrecovered: list[Fault] = []
        #: what went wrong with the run's processes (each a fault record of the log)
        self.faults: list[Fault] = []

    # ---------------------------------------------------------------------------------------
    def run_time(self) -> int:
        """Now, in ns since T0 (0 before the start)."""
        return max(0, time.time_ns() - self.t0) if self.t0 is not None else 0

    def processes(self) -> list[WorkerProcess]:
        """Every worker process this run started (a group's once)."""
        return list({id(p): p for p in [*self.workers.values(), *self.retiring.values(), *self.retired]}.values())

    def nodes_of(self, host: Host) -> list[str]:
        """The nodes whose processes run on ``host``."""
        return sorted(n for n, h in self.hosts.items() if h is host)

    def finished(self) -> bool:
        """Every node done, and every report it sent in."""
        return (all(s == State.DONE for s in self.state.values())
                and all(self.reports[n] >= self.reports_sent[n] for n in self.reports))

    def garbage(self, key: str, error: WireError) -> None:
        """Drop a message that is no message of the run: counted, the first few said."""
        self.counts["garbage"] += 1
        if self.counts["garbage"] <= GARBAGE_SAID:
            print(f"retriever: dropped a message on {key}: {error}", file=sys.stderr, flush=True)

    def tell_forged(self) -> None:
        """Count what was refused as forged (``forged``), and say so on stderr when more came."""
        refused = self.senders.refused
        if refused == self.forged_told:
            return
        self.counts["forged"] = refused
        if self.forged_told == 0:
            print(f"retriever: refused a message or record that no process of the run's node made: "
                  f"{self.senders.reasons[0]} (counted as 'forged'; a process holding the run's secret?)",
                  file=sys.stderr, flush=True)
        self.forged_told = refused
