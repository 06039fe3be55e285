"""The one seam every backend implements: open a session on a compiled graph, advance it.

A backend turns a :class:`~retriever.graph.Graph` into a :class:`Session`. Sessions keep their
own notion of ``now`` and a :class:`~retriever.trace.Trace`; the conformance suite in
``tests/backends`` holds every backend to the traces of the in-process reference.
"""

from __future__ import annotations

import time
from abc import ABC, abstractmethod
from collections import Counter
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

from ..errors import BackendError
from ..graph import Graph
from ..trace import KEEP, Trace

if TYPE_CHECKING:
    from ..log.writer import LogWriter


#: the counters of a real-time run (``pipe.counts()``, ``pipe.stats()[node].counts``, the log's end
#: record), what each counts, and what to do about it
COUNTERS = {
    "late": "events that arrived after the tick that could have used them (never applied to it)",
    "incomplete": "ticks that ran with an edge not complete up to their tag (its deadline passed)",
    "overrun": "ticks skipped because a step outlasted its period (on_overrun)",
    "restart_skipped": "Rate ticks skipped while a flow's process restarted (on_error='restart')",
    "deadline_miss": "LET outputs whose step finished after tick + latency (on_deadline_miss)",
    "unrun_ticks": "ticks triggered before the end whose inputs never completed in time",
    "unfinished_inputs": "input streams whose producer was done but whose last messages had not reached the "
                         "node seconds past the run's end: events of them it never took were lost",
    "garbage": "messages on the run's key space that were not the run's, dropped",
    "forged": "statuses and reports no process of their node signed, and step records at no tick of their "
              "node's clock, refused (a process holding the run's secret put them)",
    "report_waits": "times a node's loop waited for its reporter (recording fell behind)",
    "report_wait_ns": "how long those waits lasted in all, ns",
    "log_waits": "times the run waited for the log's disk (more than 64 MiB not yet written)",
    "log_wait_ns": "how long those waits lasted in all, ns",
    "restarts": "times a flow was restarted (on_error='restart'), after its step raised or its process died",
    "crash_restarts": "of those, restarts after the flow's process died (its state could not be handed over)",
    "moves": "times a flow started afresh on another worker after its worker was lost (retriever deploy)",
    "spin_ns": "ns flows spent busy-waiting for their ticks (configure(spin=)): CPU paid to start them on time",
    "redeclared": "times a starting flow declared its subscriptions and queryable again: a neighbour linked "
                  "to it had not learned of them (worker/starts.py, REDECLARE_AFTER_S)",
}


@dataclass
class NodeStats:
    """Counters of one node over a run."""

    ticks: int = 0
    steps: int = 0
    skips: int = 0
    errors: int = 0
    step_ns: int = 0  # total wall time spent inside step()
    #: what a real-time backend counted for this node (see :data:`COUNTERS`); absent means none
    counts: dict[str, int] = field(default_factory=dict)

    @property
    def mean_step_s(self) -> float:
        return self.step_ns / self.steps / 1e9 if self.steps else 0.0


def output_ports(graph: Graph) -> dict[str, frozenset[str] | None]:
    """Each node's ports a run of ``graph`` may make events on: a typed flow's fields, an untyped
    flow's edges and returned keys, or None for an untyped step whose keys cannot be read before
    the run (any name may be one of its ports)."""
    ports: dict[str, frozenset[str] | None] = {}
    for node in graph.nodes.values():
        known = node.spec.returned_keys if node.spec.outputs is None else frozenset()
        ports[node.id] = None if known is None else frozenset(node.outputs) | known
    return ports


class Session(ABC):
    """One run of one graph on one backend."""

    backend_name: str = ""
    #: whether ``pipe.step(dt)`` may drive this session (virtual time)
    steppable: bool = False
    #: whether the run holds other processes and shared memory: SIGTERM then stops it like Ctrl-C
    #: (its default would end this process at once, and leave what Zenoh put in /dev/shm)
    holds_processes: bool = False

    #: most steps between two hand-overs of the trace to the log writer, and the wall time
    #: aimed for between them (slow steps mean smaller batches, so a kill loses little)
    LOG_BATCH = 4096
    LOG_HANDOVER_S = 0.02
    #: and the bytes of events aimed for between two hand-overs (big values mean smaller batches:
    #: a batch is encoded whole before it is written)
    LOG_BATCH_BYTES = 8 << 20

    def __init__(self, graph: Graph, keep: str = "trace"):
        if keep not in KEEP:
            raise BackendError(f"keep={keep!r} is none of {', '.join(map(repr, KEEP))}\n"
                               "    hint: keep='trace' keeps every value in pipe.trace; keep='records' only the "
                               "events' ids and tags and the step records (the values are in the log); "
                               "keep='counters' nothing but the counters (the log has the rest)")
        self.graph = graph
        self.keep = keep
        self.trace = Trace(keep=keep)
        self.trace.ports = output_ports(graph)
        self.now_ns = 0
        self.log: LogWriter | None = None
        self.logged_to = None  # the path of this run's finished log, if it had one
        self._log_mark = (time.monotonic(), 0)  # wall time and step count at the last hand-over
        self.stop_requested = False  # set by Ctrl-C / SIGTERM during a logged run
        self.stop_signal: int | None = None  # and which of the two it was
        self.ending_log = False  # the log's end is being written: a second stop signal waits for it
        self.signal_ignored = False  # and one did (the command's clean-up then ends at the next)
        #: what the run counted that no node owns (COUNTERS; a coordinator's dropped garbage)
        self.own_counts: Counter = Counter()
        #: the most records (events and steps) the trace held at a hand-over to the log (or, with
        #: keep="counters" and no log, when it dropped them): bounded under keep="counters"
        self.retained_peak = 0

    @property
    def starved(self) -> list[dict]:
        """Each span of the run in which an input had no event while its producers made some
        (:class:`~retriever.starved.StarvationWatch`; a real-time coordinator watches for them)."""
        return []

    @property
    def counts(self) -> Counter:
        """The run's counters (COUNTERS): every node's, plus the session's own."""
        total = Counter(self.own_counts)
        for s in self.stats().values():
            total.update(s.counts)
        return total

    def seeds(self) -> dict:
        """The seeds this run depends on, recorded in the log's run metadata."""
        return {}

    def log_metadata(self) -> dict[str, str]:
        """More of the log's run metadata (text values): a deployment's workers and placement."""
        return {}

    def write_log(self) -> int:
        """Hand the trace to the log writer; return how many steps to run before the next
        hand-over, sized from the recent step rate to come back every ``LOG_HANDOVER_S``.
        Between two ticks the trace is whole: a requested stop happens here."""
        assert self.log is not None
        self.log.write(self.trace)
        if self.log.disk_waits[0]:
            self.own_counts["log_waits"], self.own_counts["log_wait_ns"] = self.log.disk_waits
        self._note_retained()
        if self.keep == "counters":
            self.log.release(self.trace)  # the log has them: memory stays bounded
        else:
            self.trace.forget_values(self.log.events_written)  # keep="records": freed once written
        if self.stop_requested:
            raise KeyboardInterrupt
        now, done = time.monotonic(), self.log.steps_total
        last_time, last_done = self._log_mark
        self._log_mark = (now, done)
        if now <= last_time or done <= last_done:
            return 1
        rate = (done - last_done) / (now - last_time)
        per_step = self.log.last_bytes / (done - last_done)
        by_bytes = int(self.LOG_BATCH_BYTES / per_step) if per_step else self.LOG_BATCH
        return max(1, min(self.LOG_BATCH, by_bytes, int(rate * self.LOG_HANDOVER_S)))

    def drop_records(self) -> None:
        """``keep="counters"`` with no log: nothing is to keep the records, drop them."""
        if self.keep == "counters" and self.log is None:
            self._note_retained()
            self.trace.discard(len(self.trace.raw_events), len(self.trace.raw_steps))

    def look_between_ticks(self) -> None:
        """Have the run look at ``stop_requested`` at its next chance (a backend whose loop
        looks only now and then says so here)."""

    def _note_retained(self) -> None:
        self.retained_peak = max(self.retained_peak, len(self.trace.raw_events) + len(self.trace.raw_steps))

    @abstractmethod
    def advance(self, until_ns: int) -> None:
        """Execute every tick with ``t < until_ns``; afterwards ``now_ns == until_ns``."""

    def run_to_end(self) -> None:
        raise BackendError(f"backend '{self.backend_name}' needs a duration: pipe.run(duration=seconds)")

    @abstractmethod
    def stats(self) -> dict[str, NodeStats]:
        """Per-node counters so far."""

    def produced_counts(self) -> dict[tuple[str, str], int] | None:
        """How many events each ``(node, port)`` produced so far (None: this backend cannot say)."""
        return None

    def close(self) -> None:
        """Release resources (processes, sessions, files). Idempotent."""


class Backend(ABC):
    """Factory of sessions; registered by name in :mod:`retriever.backends`."""

    name: str = ""

    @abstractmethod
    def open(self, graph: Graph, **options: object) -> Session:
        ...
