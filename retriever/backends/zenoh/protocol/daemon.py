"""Coordinator ↔ worker daemon: requests on ``ctl/<name>``, their replies, and the daemon's events.

    ctl/<name>              query from a coordinator (or `retriever workers`)   [2, op, {fields}]: a REQUEST
                            reply of the daemon, to the querier alone             [2, op, {fields}]: that op's reply
                            reply_err                                             [2, "error", {message}]: an ErrorReply
    workers/<name>/events   put by the daemon                                     [2, op, {fields}]: a DAEMON_EVENT

A query reaches every queryable on its key, an insider's too: nothing secret goes in a request
(a spawn's key is the daemon's to make, and comes back in its reply, which reaches the querier
alone: remote.py). The coordinator takes replies only from the session it learned the daemon by.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import StrEnum
from typing import Any

from ....errors import OtherProtocolReply, WireError
from ..command import parse_mode
from ..origin import KEY_BYTES
from .run_spec import RunSpec
from .schema import (MAX_NAME_CHARS, NS_MAX, PID_MAX, Bool, Channel, Float, HexKey, Int, Kind, ListOf, MapOf, Name,
                     Nested, OneOf, Record, Text, field)


class DaemonOp(StrEnum):
    """A daemon's ops (in the order its unknown-op error lists them)."""

    INFO = "info"
    PREPARE = "prepare"
    SPAWN = "spawn"
    SIGNAL = "signal"
    END = "end"
    USAGE = "usage"


#: the ops a deployment's coordinator seals (seal.RequestSealer) and a daemon with a secret takes
#: only sealed: each starts a process, links one to a run, or tells of a run; ``info`` tells nothing secret
SEALED_OPS = frozenset(DaemonOp) - {DaemonOp.INFO}


class DaemonEvent(StrEnum):
    OUTPUT = "output"
    EXIT = "exit"


class Stream(StrEnum):
    STDOUT = "stdout"
    STDERR = "stderr"


#: the op of every error reply (of a daemon, and of a deployment)
ERROR = "error"
#: the protocol version a daemon's info says, first: raised whenever a message changes its fields
#: or their meaning, so that a coordinator and a worker of different versions refuse each other
#: with a word on the versions (OtherProtocolReply) instead of misreading each other's records
PROTOCOL_VERSION = 2
#: the largest control request a daemon reads (a prepare carries the run's IR)
MAX_REQUEST_BYTES = 8 << 20
#: an output line as a daemon sends it: runs.MAX_LINE_BYTES of bytes, decoded with replacement
MAX_LINE_CHARS = 1 << 17

RUN = Text(256, min_chars=1)
PID = Int(1, PID_MAX)


class Mode(Kind):
    """A spawn's mode: ``[]``, or ``[--join|--fresh, T0, END]`` with ns as ASCII digits: the
    worker's command line takes it as it comes (command.parse_mode, which checks both)."""

    expects = "a spawn mode: [] or [--join|--fresh, T0, END] (ns, non-negative, in ASCII digits)"

    def read(self, value: Any, where: str) -> tuple[str, ...]:
        try:
            mode = parse_mode(value)
        except ValueError:
            raise self.refuse(value, where) from None
        return () if mode.kind is None else (mode.kind, value[1], value[2])

    def write(self, value: tuple[str, ...]) -> list:
        return [str(part) for part in value]


@dataclass(frozen=True, kw_only=True)
class InfoRequest(Record):
    NAME = DaemonOp.INFO


@dataclass(frozen=True, kw_only=True)
class PrepareRequest(Record):
    """Check ``nodes`` of the run's ``spec`` (its fields: run_spec.py; its IR: ir.IR; its plan
    and modules: daemon/runs.py) and keep it."""

    NAME = DaemonOp.PREPARE
    run: str = field(RUN)
    spec: RunSpec = field(Nested(RunSpec))
    nodes: tuple[str, ...] = field(ListOf(Name()))


@dataclass(frozen=True, kw_only=True)
class SpawnRequest(Record):
    """Start ``node``'s worker process (``mode``: as it joins the run); ``group``: ``node`` names a
    group of the spec's (flows that share a process), whose one process starts."""

    NAME = DaemonOp.SPAWN
    REFUSED = {"key": "a spawn request carries no key: the worker makes its process's key and answers it to the "
                      "coordinator alone (a coordinator of an older Retriever sends one)"}
    run: str = field(RUN)
    node: str = field(Name())
    mode: tuple[str, ...] = field(Mode())
    group: bool = field(Bool(), default=False)


@dataclass(frozen=True, kw_only=True)
class SignalRequest(Record):
    NAME = DaemonOp.SIGNAL
    run: str = field(RUN)
    pid: int = field(PID)
    signal: int = field(Int(1, 64))


@dataclass(frozen=True, kw_only=True)
class UsageRequest(Record):
    NAME = DaemonOp.USAGE
    run: str = field(RUN)


@dataclass(frozen=True, kw_only=True)
class EndRequest(Record):
    NAME = DaemonOp.END
    run: str = field(RUN)


@dataclass(frozen=True, kw_only=True)
class InfoReply(Record):
    """What a daemon is: its protocol version first (a daemon of another version answers with
    other fields: the version says so, not a field it lacks)."""

    NAME = DaemonOp.INFO
    protocol: int = field(Int(PROTOCOL_VERSION, PROTOCOL_VERSION))
    name: str = field(Name())
    labels: tuple[str, ...] = field(ListOf(Text(MAX_NAME_CHARS)))
    host: str = field(Text(MAX_NAME_CHARS))
    pid: int = field(PID)
    python: str = field(Text(64))
    packages: dict[str, str] = field(MapOf(Text(MAX_NAME_CHARS), Text(MAX_NAME_CHARS)))
    clock_ns: int = field(Int(0, NS_MAX))
    nodes: tuple[str, ...] = field(ListOf(Name()))
    counts: dict[str, int] = field(MapOf(Text(256), Int(0, NS_MAX)))

    @classmethod
    def from_fields(cls, fields: Any, where: str, **envelope: Any) -> Record:
        protocol = fields.get("protocol") if type(fields) is dict else None
        if type(protocol) is int and protocol != PROTOCOL_VERSION:
            packages = fields.get("packages")
            retriever = packages.get("retriever") if type(packages) is dict else None
            raise OtherProtocolReply(f"{where}: the worker speaks protocol {protocol}, this process "
                                     f"{PROTOCOL_VERSION}", protocol, retriever if type(retriever) is str else None)
        return super().from_fields(fields, where, **envelope)


@dataclass(frozen=True, kw_only=True)
class PrepareReply(Record):
    """The nodes the daemon runs of the run, what it warns of (code mismatches it runs anyway),
    and the key the run's events are signed with (origin.sign), to the querier alone."""

    NAME = DaemonOp.PREPARE
    nodes: tuple[str, ...] = field(ListOf(Name()))
    warnings: tuple[str, ...] = field(ListOf(Text()))
    key: bytes = field(HexKey(KEY_BYTES))


@dataclass(frozen=True, kw_only=True)
class SpawnReply(Record):
    """The process started, and the key it signs with (origin.py), to the querier alone."""

    NAME = DaemonOp.SPAWN
    pid: int = field(PID)
    key: bytes = field(HexKey(KEY_BYTES))


@dataclass(frozen=True, kw_only=True)
class SignalReply(Record):
    NAME = DaemonOp.SIGNAL


@dataclass(frozen=True, kw_only=True)
class UsageReply(Record):
    """The CPU seconds each live process of the run used so far, by node."""

    NAME = DaemonOp.USAGE
    cpu_s: dict[str, float] = field(MapOf(Name(), Float(0.0, 1e12)))


@dataclass(frozen=True, kw_only=True)
class EndReply(Record):
    NAME = DaemonOp.END


@dataclass(frozen=True, kw_only=True)
class ErrorReply(Record):
    """Why a request was refused (a daemon's or a deployment's ``reply_err``)."""

    NAME = ERROR
    message: str = field(Text())


@dataclass(frozen=True, kw_only=True)
class ProcessOutput(Record):
    """Lines a process of the run printed, on its stdout or stderr."""

    NAME = DaemonEvent.OUTPUT
    run: str = field(RUN)
    node: str = field(Name())
    stream: Stream = field(OneOf(Stream))
    lines: tuple[str, ...] = field(ListOf(Text(MAX_LINE_CHARS), max_items=1024))


@dataclass(frozen=True, kw_only=True)
class ProcessExit(Record):
    """A process of the run ended with ``code`` (Popen's: minus the signal that killed it)."""

    NAME = DaemonEvent.EXIT
    run: str = field(RUN)
    node: str = field(Name())
    pid: int = field(PID)
    code: int = field(Int(-64, 255))


REQUEST = Channel("ctl/<name>", (InfoRequest, PrepareRequest, SpawnRequest, SignalRequest, EndRequest, UsageRequest),
                  max_bytes=MAX_REQUEST_BYTES)
REPLY = Channel("a daemon's reply", (InfoReply, PrepareReply, SpawnReply, SignalReply, EndReply, UsageReply))
ERROR_REPLY = Channel("an error reply", (ErrorReply,))
DAEMON_EVENT = Channel("workers/<name>/events", (ProcessOutput, ProcessExit))


def decode_reply(data: Any, op: DaemonOp) -> Record:
    """A daemon's reply to a request of ``op``: that op's reply record (exact), or WireError."""
    record = REPLY.decode(data)
    if record.NAME != op:
        raise WireError(f"a '{record.NAME}' reply to a '{op}' request")
    return record


def error_message(data: Any) -> str | None:
    """What an error reply says; None for one that is no daemon's or deployment's (Zenoh's own,
    "Timeout", when the query went unanswered)."""
    try:
        return ErrorReply.decode(data).message[:4000]
    except WireError:
        return None
