"""What a node loop does with the run's control messages (from the coordinator, to every node)."""

from __future__ import annotations

from ..protocol import End, Finished, Grant, Handover, Have, Lost, Record, Redeclare, Restarted, Stop
from ..wire import WireError
from .ending import Ending
from .handover import producer_restarted
from .inbox import CONTROL


def obey(loop, record: Record | WireError) -> None:
    """One control message to ``loop`` (a NodeLoop), as the loop's control subscriber queued it:
    a record of protocol.RUN_CONTROL or the coordinator's Finished answer to the loop's question, or
    the WireError that refused it (malformed, or not sealed for this process: plane.ControlPlane),
    which is garbage, never applied."""
    kind = type(record)
    if isinstance(record, WireError):
        loop.notes.garbage(loop.keys.run_control(), record)
    elif kind is Stop:
        loop.stop(Ending.TOLD_TO_STOP)
    elif kind is End:  # a step's sys.exit(0) ended the run there: the ticks before it still run
        with loop.lock:
            loop.run_clock.end = min(loop.run_clock.end, record.at)
    elif kind is Redeclare:  # only for a node not started yet (worker/waits.py, await_control)
        loop.notes.garbage(loop.keys.run_control(), WireError("a 'redeclare' control message during the run"))
    elif kind is Handover and record.node == loop.id and loop.restarting:
        loop.stop(Ending.HANDING_OVER)
    elif kind is Have:
        loop.reports.coordinator_has(record.last_seqs)
    elif kind is Grant and loop.virtual:
        loop.waiting.granted(record.until)
    elif kind is Lost and record.node == loop.id:
        # the coordinator counts this process dead (its worker daemon hung or was cut off)
        # and starts another: this one must not run on beside it, nor promise anything
        loop.stop(Ending.ABANDONED)
    elif kind is Lost and record.node in loop.streams.sources:
        loop.streams.lost_producers.add(record.node)
    elif kind is Restarted and record.node in loop.streams.sources:
        producer_restarted(loop, record.node, record.seqs)
    elif kind is Finished:  # the coordinator's answer to the loop's question (waiting.py, last_word)
        loop.waiting.said_finished(record)


def opened_control(opener, sample) -> tuple:
    """The inbox item of a put on ctl/run: its record of protocol.RUN_CONTROL, opened with this
    process's key (``opener``: a ControlOpener) and decoded, or, when it does not open (forged,
    replayed, another run's) or does not decode, the WireError saying so (garbage)."""
    try:
        record = opener.control(str(sample.key_expr), sample.payload.to_bytes(), sample.attachment)
    except WireError as e:
        return CONTROL, None, e
    return CONTROL, None, record
