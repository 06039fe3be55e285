"""What a node loop does with the run's control messages (from the coordinator, to every node)."""

from __future__ import annotations

from ..protocol import End, Grant, Handover, Have, Lost, Record, Redeclare, Restarted, Stop
from ..wire import WireError
from .handover import producer_restarted


def obey(loop, record: Record | WireError) -> None:
    """One control message to ``loop`` (a NodeLoop), as the loop's control subscriber queued it:
    a record of protocol.RUN_CONTROL, or the WireError that refused it (malformed, or not sealed
    for this process: NodeLoop._control_in), which is garbage, never applied."""
    kind = type(record)
    if isinstance(record, WireError):
        loop.notes.garbage("ctl/run", record)
    elif kind is Stop:
        loop.stopping = loop.told_to_stop = True
    elif kind is End:  # a step's sys.exit(0) ended the run there: the ticks before it still run
        with loop.lock:
            loop.run_clock.end = min(loop.run_clock.end, record.at)
    elif kind is Redeclare:  # only for a node not started yet (worker._await_control)
        loop.notes.garbage("ctl/run", WireError("a 'redeclare' control message during the run"))
    elif kind is Handover and record.node == loop.id and loop.restarting:
        loop.stopping = loop.handing_over = True
    elif kind is Have:
        loop.reports.coordinator_has(record.streams)
    elif kind is Grant and loop.virtual:
        loop.waiting.granted(record.until)
    elif kind is Lost and record.node == loop.id:
        # the coordinator counts this process dead (its worker daemon hung or was cut off)
        # and starts another: this one must not run on beside it, nor promise anything
        loop.abandoned = loop.stopping = True
    elif kind is Lost and record.node in loop.streams.sources:
        loop.streams.lost_producers.add(record.node)
    elif kind is Restarted and record.node in loop.streams.sources:
        producer_restarted(loop, record.node, record.seqs)
