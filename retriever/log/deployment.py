"""Where the nodes of a deployment ran (``retriever deploy``), as its log records it.

The run record's ``deployment`` entry is written as the run starts: the namespace, the worker
each node started on (``placed``) and what each worker said of itself (host, pid, labels, ...).
A node that started afresh on a worker after its own was lost (``on_worker_loss``) has a fault
record naming the worker it went to (``moved_to``): the moves are read from those, in order, so
that each names the worker the node left. A log's text is a hostile file's: every field is
checked for its shape, and only ever shown as text.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from typing import Any

from ..errors import LogError

#: the furthest ahead of the coordinator's clock a run's stamps are taken to be (clock_ahead_ns):
#: the skew Zenoh's HLC tolerates between sessions, past which a node's progress is refused as
#: garbage (backends/zenoh/node/frontiers.py, CLOCK_AHEAD_MAX_NS): a worker said further ahead
#: could not have run its flows with the others (a log claiming more is bounded by it)
CLOCK_AHEAD_MAX_NS = 500_000_000
#: what ``log info`` shows of each worker's word on itself, in this order
WORKER_FIELDS = ("host", "pid", "labels")


@dataclass(frozen=True)
class Move:
    """``node`` started afresh on worker ``to`` at ``at_ns`` (run time) after ``left``, the
    worker it ran on, was lost (``left == to``: it waited for that worker to come back)."""

    node: str
    left: str
    to: str
    at_ns: int


@dataclass(frozen=True)
class Span:
    """``node`` ran on ``worker`` from ``from_ns`` (None: the run's start) until ``until_ns``
    (None: the run's end), in run time."""

    node: str
    worker: str
    from_ns: int | None
    until_ns: int | None


@dataclass(frozen=True)
class LoggedDeployment:
    """The workers of a deployment's run, the worker each node started on, and its moves."""

    namespace: str
    placed: dict[str, str]
    workers: dict[str, dict[str, Any]]
    moves: tuple[Move, ...]

    def spans_on(self, worker: str) -> list[Span]:
        """What ran on ``worker``: each node placed there or moved there, from when (None: the
        start) until when (None: the end), by node and time."""
        return sorted((span for span in self.spans() if span.worker == worker),
                      key=lambda s: (s.node, s.from_ns or 0))

    def spans(self) -> list[Span]:
        """Where each node ran, span by span: a move to another worker ends one and begins the next."""
        ended, running = [], {node: Span(node, worker, None, None) for node, worker in self.placed.items()}
        for move in self.moves:
            if move.to == move.left:  # back on the worker it waited for: the same worker ran it
                continue
            if move.node in running:
                left = running[move.node]
                ended.append(Span(left.node, left.worker, left.from_ns, move.at_ns))
            running[move.node] = Span(move.node, move.to, move.at_ns, None)
        return [*ended, *running.values()]

    def clock_ahead_ns(self) -> int:
        """How far ahead of the coordinator's clock the run's stamps can be: the furthest ahead a
        worker said its clock ran when the run began (``offset_ns``, NTP-style), or 0, at most
        CLOCK_AHEAD_MAX_NS. A node's tags are its HLC's, which runs at its worker's clock or at a
        faster one it heard from."""
        offsets = [worker.get("offset_ns") for worker in self.workers.values()]
        return min(max([0, *(offset for offset in offsets if type(offset) is int)]), CLOCK_AHEAD_MAX_NS)


def read_deployment(path, text: str | None, faults: list[dict[str, Any]]) -> LoggedDeployment | None:
    """The deployment that the run metadata's ``text`` (its ``deployment`` entry; None: the run
    was not a deployment) and the log's ``faults`` (``RunLog.faults``) record; a LogError naming
    ``path`` when the entry is not of the shape a deployment writes."""
    if text is None:
        return None
    try:
        doc = json.loads(text)
    except (ValueError, RecursionError):
        doc = None
    if (type(doc) is not dict or type(doc.get("namespace")) is not str
            or not _maps(doc.get("placed"), str) or not _maps(doc.get("workers"), dict)):
        raise LogError(f"{path}: its metadata 'deployment' is not a JSON object of a deployment's namespace, "
                       f"placement and workers ({str(text)[:60]!r})", "the file was changed after it was written")
    return LoggedDeployment(doc["namespace"], doc["placed"], doc["workers"], _moves(doc["placed"], faults))


def _maps(value: object, kind: type) -> bool:
    """Whether ``value`` is a JSON object of names to values of ``kind``."""
    return type(value) is dict and all(type(v) is kind for v in value.values())


def _moves(placed: dict[str, str], faults: list[dict[str, Any]]) -> tuple[Move, ...]:
    """The fault records of nodes that moved, each as the move from where the node last ran."""
    where, moves = dict(placed), []
    for fault in faults:
        to = fault.get("moved_to")
        if type(to) is str:
            node = fault["node"]
            moves.append(Move(node, where.get(node, "?"), to, int(fault.get("at_ns", "0"))))
            where[node] = to
    return tuple(moves)
