"""What went wrong in a run, as typed records: a lost process (:class:`Fault`), the failure
that stops the run (:class:`RunFailure`).

The coordinator's parts pass these records around; only :meth:`Fault.log_fields` turns one into
the fields of the log's fault record (``retriever.fault.N``, log/writer.py), whose format the
log's readers (log/reader.py, log/deployment.py, replay) depend on.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Any

from ..protocol import Failed

#: the one kind of fault a run logs: a process that went with state the run had not seen yet
PROCESS_LOST = "process_lost"


@dataclass(frozen=True)
class Fault:
    """A worker process of ``node`` lost at ``at_ns`` (ns since T0): its ``pid``, how it ended
    (``exit``), where its node started afresh (``moved_to``, a deployment's worker), whether it
    did (``restarted``, with the seqs its streams went on from), and the events its step records
    claimed that no report carried (``lost_events``: a replay must know them)."""

    node: str
    at_ns: int
    pid: int
    exit: str
    moved_to: str | None = None
    kind: str = PROCESS_LOST
    restarted: bool = False
    seqs: dict[str, int] = field(default_factory=dict)
    lost_events: list[list] = field(default_factory=list)

    def settled(self, seqs: dict[str, int] | None, lost_events: list[list]) -> Fault:
        """This fault once its last reports are in: its node restarted from ``seqs`` (None: it did
        not), and ``lost_events`` lost with it."""
        return dataclasses.replace(self, restarted=seqs is not None, seqs=seqs or {}, lost_events=lost_events)

    def log_fields(self) -> dict[str, Any]:
        """The fields of the log's fault record, in its order (``moved_to`` only when it moved)."""
        moved = {} if self.moved_to is None else {"moved_to": self.moved_to}
        return {"kind": self.kind, "node": self.node, "at_ns": self.at_ns, "pid": self.pid, "exit": self.exit,
                **moved, "restarted": self.restarted, "seqs": self.seqs, "lost_events": self.lost_events}


@dataclass(frozen=True)
class RunFailure:
    """What stops a run: the ``node`` that failed it and why (``error``); ``failed``: its
    process's own ``failed`` status, when it said so (a step raised, its setup failed...)."""

    node: str
    error: str
    failed: Failed | None = None

    @classmethod
    def said(cls, status: Failed) -> RunFailure:
        """The failure a node's process said (its ``failed`` status)."""
        return cls(status.node, status.error, status)
