"""Workers → coordinator: a worker process's statuses and its reports, each signed by its key.

    status/node/<node>    put   [2, node, state, {fields..., pid}]: one of the STATUS records
    status/report/<node>  put   [2, node, [step record, ...], [[wall_ns, data message], ...]]: a Report

Every one goes with the MAC of its process's key as the Zenoh attachment (origin.py); the
coordinator takes none that no process of the node signed. A status's fields are its map in the
record's order, its ``pid`` last (the process's, as every status says).
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import StrEnum
from typing import Any, NamedTuple

from ....errors import WireError
from ....trace import STEP_STATUSES, StepStatus
from ..wire import WIRE_VERSION, shown
from .schema import (MAX_ITEMS, MAX_MESSAGE_BYTES, MAX_NAME_CHARS, NS_MAX, PID_MAX, SEQ_MAX, Bool, Int, ListOf,
                     MapOf, Name, Nullable, Plain, Record, Row, Text, field, pack, port, unpack)


class State(StrEnum):
    """What a worker process says of itself on ``status/node/<node>``."""

    READY = "ready"
    DONE = "done"
    FAILED = "failed"
    RESTART = "restart"
    HANDED_OVER = "handed_over"
    REACHED = "reached"  # virtual time: every tick below the coordinator's grant has run (node/waiting.py)
    UNANSWERED = "unanswered"
    EXIT = "exit"


NS = Int(0, NS_MAX)
TAG = Row(NS, NS, expects="[t_ns, microstep] of two integers >= 0")
COUNTS = MapOf(Text(256, min_chars=1), Int(0, NS_MAX))


@dataclass(frozen=True, kw_only=True)
class Status(Record):
    """What every status carries: its node (in the envelope) and its process's pid (last)."""

    node: str
    pid: int = field(Int(1, PID_MAX))

    @classmethod
    def schema(cls):
        """The fields of the map: the status's own, then pid (as the worker appends it)."""
        if "_schema" not in cls.__dict__:
            own = tuple(entry for entry in super().schema() if entry[0] != "pid")
            cls._schema = (*own, ("pid", Status.__dataclass_fields__["pid"].metadata["kind"], False))
        return cls._schema


@dataclass(frozen=True, kw_only=True)
class Ready(Status):
    """Ready for the start (said again until it comes). A node's first process says whether
    it linked to the hub and each neighbour (``unlinked``: those it did not, by name) and how
    many peers its session has; a restarted one says nothing more."""

    NAME = State.READY
    linked: bool = field(Bool(), optional=True)
    unlinked: tuple[str, ...] = field(ListOf(Text(MAX_NAME_CHARS)), optional=True)
    peers: int = field(Int(0, MAX_ITEMS), optional=True)


@dataclass(frozen=True, kw_only=True)
class Done(Status):
    """The process is done: its counts; once it ran, how many reports it sent, when the start
    came (ns since T0: negative when before T0; nil for a restarted process), its ticks,
    whether it was told to stop, and the last seq it put on each port."""

    NAME = State.DONE
    counts: dict[str, int] = field(COUNTS)
    reports: int = field(Int(0, NS_MAX), optional=True)
    started_ns: int | None = field(Nullable(Int(-NS_MAX, NS_MAX)), optional=True)
    ticks: int = field(Int(0, NS_MAX), optional=True)
    stopped: bool = field(Bool(), optional=True)
    sent: dict[str, int] = field(MapOf(port(), Int(-1, SEQ_MAX)), optional=True)


@dataclass(frozen=True, kw_only=True)
class Failed(Status):
    """The process failed: why, where (the tick, if a step raised), and its traceback;
    ``raised``: what its step raised, when that failed it; ``out_of_restarts``: true when that
    step's restart in place (a group's member) was past the flow's budget."""

    NAME = State.FAILED
    error: str = field(Text())
    setup: bool = field(Bool(), optional=True)
    tag: tuple[int, int] | None = field(Nullable(TAG), optional=True)
    counts: dict[str, int] = field(COUNTS, optional=True)
    traceback: str | None = field(Nullable(Text()))
    zeno: bool = field(Bool(), optional=True)
    raised: str | None = field(Nullable(Text()), optional=True)
    out_of_restarts: bool = field(Bool(), optional=True)


@dataclass(frozen=True, kw_only=True)
class Restart(Status):
    """A step raised with on_error="restart" at ``tag``: start a new process for the node."""

    NAME = State.RESTART
    tag: tuple[int, int] = field(TAG)
    error: str = field(Text())


@dataclass(frozen=True, kw_only=True)
class HandedOver(Status):
    """The restarting process wrote its state for the new one and ends."""

    NAME = State.HANDED_OVER
    counts: dict[str, int] = field(COUNTS)
    reports: int = field(Int(0, NS_MAX))


@dataclass(frozen=True, kw_only=True)
class Reached(Status):
    """Virtual time: the node ran every tick below ``until``."""

    NAME = State.REACHED
    until: int = field(NS)


@dataclass(frozen=True, kw_only=True)
class Unanswered(Status):
    """Before the start: ``nodes`` never answered this one's question (REDECLARE_AFTER_S)."""

    NAME = State.UNANSWERED
    nodes: tuple[str, ...] = field(ListOf(Name(), min_items=1))


@dataclass(frozen=True, kw_only=True)
class Exit(Status):
    """A step called sys.exit(0) at ``tag``: the run ends there."""

    NAME = State.EXIT
    tag: tuple[int, int] = field(TAG)


#: how a worker process ends, beside 0 (done) and a signal: its exit code, which its parent reads
#: when its last status may not have come
EXIT_FAILED = 1
EXIT_HANDED_OVER = 3
EXIT_ABANDONED = 4  # its parent (a coordinator, a worker daemon) died: it ended without a word

STATUSES = {record.NAME: record for record in (Ready, Done, Failed, Restart, HandedOver, Reached, Unanswered, Exit)}
#: a report may carry big frames inline (a spill directory on another host is no use): no bound
#: but the one its transport has
MAX_REPORT_BYTES = 1 << 62


class StatusChannel:
    """``status/node/<node>``: ``[2, node, state, {fields..., pid}]``."""

    what = "status/node"

    def encode(self, record: Status) -> bytes:
        if STATUSES.get(record.NAME) is not type(record):
            raise TypeError(f"{type(record).__name__} is no status")
        return pack([WIRE_VERSION, record.node, str(record.NAME), record.to_fields()])

    def decode(self, data: Any, node: str | None = None) -> Status:
        """A status; ``node``: the one its key names (a status must be of that node)."""
        _, said, state, info = unpack(data, 4, "a status message", MAX_MESSAGE_BYTES)
        said = Name().read(said, "a status message: its node")
        if node is not None and said != node:
            raise WireError(f"a status of {said} arrived on the key of {node}")
        record = STATUSES.get(state) if type(state) is str else None
        if record is None:
            raise WireError(f"a status message of state {shown(state, 20)}; a worker's states are "
                            f"{', '.join(STATUSES)}")
        return record.from_fields(info, f"a '{state}' status of {said}", node=said)


STATUS = StatusChannel()
for _record in STATUSES.values():
    _record.CHANNEL = STATUS


class ReportedStep(NamedTuple):
    """A step record as a report carries it (trace.StepRecord's fields but the node)."""

    tag: tuple[int, int]
    consumed: dict[str, tuple[tuple[str, str, int], ...]]
    produced: tuple[tuple[str, str, int], ...]
    status: StepStatus
    detail: dict | None
    wall_start_ns: int
    wall_ns: int


class ReportedEvent(NamedTuple):
    """A data message the node published (wire.decode_events reads it), or the name of the file
    of the run directory that holds it (on the coordinator's host), and when it was published."""

    wall_ns: int
    message: bytes | str


CHUNK = Name()
PORT = port()
WALL = Int(-NS_MAX - 1, NS_MAX)  # Unix ns, as the worker's clock says (it may step back)
DETAIL = Nullable(Plain())
#: a file name a report may give for a message: the node's own, in the run directory
MAX_FILE_NAME = 255


@dataclass(frozen=True, kw_only=True)
class Report(Record):
    """A batch of a node's step records and the data messages it published (node/reporter.py)."""

    NAME = "report"
    node: str
    records: tuple[ReportedStep, ...]
    events: tuple[ReportedEvent, ...]

    def encode(self) -> bytes:
        return pack([WIRE_VERSION, self.node, list(self.records), list(self.events)])

    @classmethod
    def decode(cls, data: Any, node: str | None = None) -> Report:
        """A report (exact); ``node``: the one its key names. Event ids come back as tuples, as
        in the trace; the data messages are left encoded."""
        # without the check of keys named twice, which doubled the time of a report of small
        # records: its process signed it, and a key twice could only hide part of its own claim
        _, said, records, events = unpack(data, 4, "a report", MAX_REPORT_BYTES, exact_maps=False)
        said = CHUNK.read(said, "a report: its node")
        if node is not None and said != node:
            raise WireError(f"a report of {said} arrived on the key of {node}")
        where = f"a report of {said}"
        if type(records) is not list or type(events) is not list:
            raise WireError(f"{where} must carry a list of records and a list of events")
        return cls(node=said, records=tuple([_step(r, where, i) for i, r in enumerate(records)]),
                   events=tuple([_event(e, where, i) for i, e in enumerate(events)]))


#: a step record's status as the wire spells it → its StepStatus
_STEP_STATUS = {status.value: status for status in StepStatus}


def _step(raw: Any, report: str, i: int) -> ReportedStep:
    """A step record, read on a fast path (reports come by the thousand): each field checked
    inline, and only a bad one read again by its kind, for the error that names it."""
    if type(raw) is not list or len(raw) != 7:
        raise WireError(f"{report}: record {i} must be [tag, consumed, produced, status, detail, wall_start_ns, "
                        "wall_ns]")
    tag, consumed, produced, status, detail, start, wall = raw
    if not (type(tag) is list and len(tag) == 2 and type(tag[0]) is int and type(tag[1]) is int
            and 0 <= tag[0] <= NS_MAX and 0 <= tag[1] <= NS_MAX):
        TAG.read(tag, f"{report}: record {i}: field 'tag'")
    if type(consumed) is not dict:
        raise WireError(f"{report}: record {i}: field 'consumed' must be a map of port to event ids, "
                        f"got {type(consumed).__name__}")
    ids = {}
    for name, events in consumed.items():
        if type(name) is not str or not 0 < len(name) <= MAX_NAME_CHARS:
            PORT.read(name, f"{report}: record {i}: field 'consumed' key")
        ids[name] = _ids(events, report, i, "consumed")
    said = _STEP_STATUS.get(status) if type(status) is str else None
    if said is None:
        raise WireError(f"{report}: record {i}: field 'status' must be one of {', '.join(STEP_STATUSES)}, "
                        f"got {shown(status, 30)}")
    if detail is not None:
        if type(detail) is not dict:
            raise WireError(f"{report}: record {i}: field 'detail' must be nil or a map, got {type(detail).__name__}")
        DETAIL.read(detail, f"{report}: record {i}: field 'detail'")
    if not (type(start) is int and type(wall) is int and -NS_MAX - 1 <= start <= NS_MAX
            and -NS_MAX - 1 <= wall <= NS_MAX):
        WALL.read(start, f"{report}: record {i}: field 'wall_start_ns'")
        WALL.read(wall, f"{report}: record {i}: field 'wall_ns'")
    # tuple.__new__: a NamedTuple's own constructor is Python code, run once per record
    return tuple.__new__(ReportedStep, ((tag[0], tag[1]), ids, _ids(produced, report, i, "produced"), said, detail,
                                        start, wall))


def _ids(raw: Any, report: str, i: int, name: str) -> tuple[tuple[str, str, int], ...]:
    """``[[node, port, seq], …]`` → a tuple of event ids."""
    if type(raw) is not list or not all(type(e) is list and len(e) == 3 and type(e[0]) is str and type(e[1]) is str
                                        and type(e[2]) is int and 0 <= e[2] <= SEQ_MAX for e in raw):
        raise WireError(f"{report}: record {i}: field '{name}' must hold event ids: [node, port, seq] triples (seq "
                        f"from 0), got {shown(raw, 60)}")
    return tuple(map(tuple, raw))


def _event(raw: Any, report: str, i: int) -> ReportedEvent:
    if (type(raw) is not list or len(raw) != 2 or type(raw[0]) is not int or not -NS_MAX - 1 <= raw[0] <= NS_MAX
            or not (type(raw[1]) is bytes or (type(raw[1]) is str and 0 < len(raw[1]) <= MAX_FILE_NAME))):
        raise WireError(f"{report}: event {i} must be [wall_ns, data message or file name], got {shown(raw, 60)}")
    return tuple.__new__(ReportedEvent, raw)
