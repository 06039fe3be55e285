"""`retriever status` / `retriever stop` ↔ a running deployment's coordinator, on ``deployment``.

    deployment   query from the CLI     [2, op, {}]: a StatusQuery or a StopQuery
                 reply of the deployment [2, op, {fields}]: a StatusReply or a StopReply
                 reply_err               [2, "error", {message}]: an ErrorReply (daemon/core.py)
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import StrEnum

from .schema import (MAX_NAME_CHARS, NS_MAX, Bool, Channel, Float, Int, MapOf, Name, Nested, Nullable, OneOf, Record,
                     Text, field)
from .to_coordinator import State


class DeploymentOp(StrEnum):
    """A deployment's ops (in the order its unknown-op error lists them)."""

    STATUS = "status"
    STOP = "stop"


class NodeState(StrEnum):
    """A node's state in a deployment's status (NodeStatus.state), as the coordinator keeps it:
    from its process's spawn until that process says its first state, ``starting``; then the
    last of these states (State) its process said."""

    STARTING = "starting"
    READY = State.READY.value
    FAILED = State.FAILED.value
    DONE = State.DONE.value


COUNT = Int(0, NS_MAX)


@dataclass(frozen=True, kw_only=True)
class StatusQuery(Record):
    NAME = DeploymentOp.STATUS


@dataclass(frozen=True, kw_only=True)
class StopQuery(Record):
    NAME = DeploymentOp.STOP


@dataclass(frozen=True, kw_only=True)
class NodeStatus(Record):
    """One node of a deployment's status: its worker, state and counters, and the CPU seconds
    its process used so far (as last read; absent before the first reading)."""

    worker: str | None = field(Nullable(Name()))
    state: NodeState | None = field(Nullable(OneOf(NodeState)))
    ticks: int = field(COUNT)
    steps: int = field(COUNT)
    skips: int = field(COUNT)
    errors: int = field(COUNT)
    counts: dict[str, int] = field(MapOf(Text(256), COUNT))
    cpu_s: float = field(Float(0.0, 1e12), optional=True)


@dataclass(frozen=True, kw_only=True)
class StatusReply(Record):
    """The deployment, node by node: ``t_ns`` of ``end_ns`` so far, once ``started``."""

    NAME = DeploymentOp.STATUS
    pipeline: str = field(Text(MAX_NAME_CHARS))
    run: str = field(Text(256))
    t_ns: int = field(Int(0, NS_MAX))
    end_ns: int = field(Int(0, NS_MAX))
    started: bool = field(Bool())
    nodes: dict[str, NodeStatus] = field(MapOf(Name(), Nested(NodeStatus)))


@dataclass(frozen=True, kw_only=True)
class StopReply(Record):
    """The deployment stops, as Ctrl-C at its coordinator would stop it."""

    NAME = DeploymentOp.STOP
    pipeline: str = field(Text(MAX_NAME_CHARS))


DEPLOYMENT_QUERY = Channel("deployment", (StatusQuery, StopQuery))
DEPLOYMENT_REPLY = Channel("the deployment's reply", (StatusReply, StopReply))
