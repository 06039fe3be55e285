"""Coordinator → workers: the run's control (``ctl/run``) and the answers to a worker's questions.

    ctl/run          put, every worker subscribes   [2, op, {fields}]: one of RUN_CONTROL's records
    ctl/start        the coordinator's queryable    reply: a Start (without grant), once the run has one
    status/finished  the coordinator's queryable    reply: Finished

Each record is the op of the same name; its fields are the map, in this order (see __init__'s
table for who sends which, and what its receivers check beyond these fields).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property
from enum import StrEnum

from .schema import NS_MAX, SEQ_MAX, Bool, Channel, Int, ListOf, MapOf, Name, Record, Row, field, port


class Op(StrEnum):
    """The ops of ``ctl/run``, and of the answers on ``ctl/start`` and ``status/finished``."""

    START = "start"
    GRANT = "grant"
    REDECLARE = "redeclare"
    RESTARTED = "restarted"
    HANDOVER = "handover"
    RESUME = "resume"
    END = "end"
    HAVE = "have"
    LOST = "lost"
    STOP = "stop"
    FINISHED = "finished"


NS = Int(0, NS_MAX)

#: A flow whose process died (kill -9, a segfault) under on_error="restart" starts afresh in a
#: new process, its state lost (node/handover.py). Its streams go on from a seq past every one the
#: dead process may have used: the coordinator knows the seqs it reported; at most its
#: unreported seqs were published unknown to the coordinator: fewer than FLUSH_MAX_SEQS +
#: MAX_BURST in the node loop, at most MAX_PENDING_SEQS (or one report) in the reporter's queue,
#: 655,360 in all, far fewer than RESTART_SEQ_GAP. A consumer told that a producer was lost takes
#: its seqs up to that far ahead (node/frontiers.py's EARLY_SEQS_MAX is for running
#: streams). The coordinator's ``restarted`` puts each first seq that far past the last it knows.
RESTART_SEQ_GAP = 1 << 21


@dataclass(frozen=True, kw_only=True)
class Start(Record):
    """The run starts at ``t0`` (ns since the epoch, the hub's HLC) and ends ``end`` ns after it;
    ``values``: whether reports carry the events' values; ``grant``: in virtual time, the ticks
    below it may run (node/waiting.py)."""

    NAME = Op.START
    t0: int = field(NS)
    end: int = field(NS)
    values: bool = field(Bool())
    grant: int = field(NS, optional=True)


@dataclass(frozen=True, kw_only=True)
class Grant(Record):
    """Virtual time: the ticks below ``until`` (ns since T0) may run."""

    NAME = Op.GRANT
    until: int = field(NS)


@dataclass(frozen=True, kw_only=True)
class Redeclare(Record):
    """Before the start: ``nodes`` declare their subscriptions and queryables again (a consumer
    never got their answer: worker/starts.py, REDECLARE_AFTER_S)."""

    NAME = Op.REDECLARE
    nodes: tuple[str, ...] = field(ListOf(Name(), min_items=1))


@dataclass(frozen=True, kw_only=True)
class Restarted(Record):
    """``node`` started afresh in a new process: the first seq of each of its output ports."""

    NAME = Op.RESTARTED
    node: str = field(Name())
    seqs: dict[str, int] = field(MapOf(port(), Int(0, SEQ_MAX)))
    values: bool = field(Bool())


@dataclass(frozen=True, kw_only=True)
class Handover(Record):
    """``node``'s restarting process: write your state and hand over to the new one."""

    NAME = Op.HANDOVER
    node: str = field(Name())


@dataclass(frozen=True, kw_only=True)
class Resume(Record):
    """``node``'s new process: take the state handed over and go on."""

    NAME = Op.RESUME
    node: str = field(Name())


@dataclass(frozen=True, kw_only=True)
class End(Record):
    """A step's sys.exit(0) ended the run: no tick at or past ``at`` (ns since T0)."""

    NAME = Op.END
    at: int = field(NS)


@dataclass(frozen=True, kw_only=True)
class Have(Record):
    """The coordinator has every event of each stream up to its seq: ``(producer, port, seq)``
    (-1: none yet)."""

    NAME = Op.HAVE
    streams: tuple[tuple[str, str, int], ...] = field(ListOf(Row(
        Name(), port(), Int(-1, SEQ_MAX), expects="[producer, port, last seq] (a seq from -1)")))

    @cached_property
    def last_seqs(self) -> dict[tuple[str, str], int]:
        """``streams`` by stream: ``(producer, port)`` -> its last seq (the greatest, if named
        twice). Made once per message: each node of a group looks up its few inputs in it."""
        seqs: dict[tuple[str, str], int] = {}
        for producer, out, seq in self.streams:
            if seq > seqs.get((producer, out), -1):
                seqs[(producer, out)] = seq
        return seqs


@dataclass(frozen=True, kw_only=True)
class Lost(Record):
    """``node``'s process is counted dead: it stops at once if it still runs; its consumers may
    see its streams jump (RESTART_SEQ_GAP) once it restarts."""

    NAME = Op.LOST
    node: str = field(Name())


@dataclass(frozen=True, kw_only=True)
class Stop(Record):
    """The run stops: every worker sends its last reports and says done."""

    NAME = Op.STOP


@dataclass(frozen=True, kw_only=True)
class Finished(Record):
    """The answer on ``status/finished``: the nodes done, those done with every report in, those
    starting afresh after their process died, and those whose old process handed over to a
    restarted flow's and has every report in (that process may exit)."""

    NAME = Op.FINISHED
    nodes: tuple[str, ...] = field(ListOf(Name()))
    complete: tuple[str, ...] = field(ListOf(Name()))
    restarting: tuple[str, ...] = field(ListOf(Name()))
    handed_over: tuple[str, ...] = field(ListOf(Name()))


RUN_CONTROL = Channel("ctl/run", (Start, Grant, Redeclare, Restarted, Handover, Resume, End, Have, Lost, Stop))
FINISHED_REPLY = Channel("status/finished", (Finished,))
