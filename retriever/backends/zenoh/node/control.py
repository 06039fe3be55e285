"""What a node loop does with the run's control messages (from the coordinator, to every node)."""

from __future__ import annotations

from ..wire import WireError, decode_control
from .handover import producer_restarted


def opened(data: bytes | WireError) -> tuple[str, dict]:
    """A queued control message, decoded; one refused as it came (its seal did not open with the
    process's key: NodeLoop._control_in) raises the WireError that says why."""
    if isinstance(data, WireError):
        raise data
    return decode_control(data)


def obey(loop, data: bytes | WireError) -> None:
    """One control message to ``loop`` (a NodeLoop); a malformed or unsealed one is garbage, never applied."""
    try:
        op, args = opened(data)
    except WireError as e:
        loop.notes.garbage("ctl/run", e)
        return
    node = args.get("node")
    if op == "stop":
        loop.stopping = loop.told_to_stop = True
    elif op == "end":  # a step's sys.exit(0) ended the run there: the ticks before it still run
        at = args.get("at")
        if type(at) is int and at >= 0:
            with loop.lock:
                loop.run_clock.end = min(loop.run_clock.end, at)
        else:
            loop.notes.garbage("ctl/run", WireError(f"an 'end' control message with at {at!r:.30}"))
    elif op == "redeclare":  # only for a node not started yet (worker._await_control)
        loop.notes.garbage("ctl/run", WireError("a 'redeclare' control message during the run"))
    elif op == "handover" and node == loop.id and loop.restarting:
        loop.stopping = loop.handing_over = True
    elif op == "have":
        loop.reports.coordinator_has(args)
    elif op == "grant" and loop.virtual:
        until = args.get("until")
        if type(until) is int and until >= 0:
            loop.waiting.granted(until)
        else:
            loop.notes.garbage("ctl/run", WireError(f"a 'grant' control message with until {until!r:.30}"))
    elif op == "lost" and node == loop.id:
        # the coordinator counts this process dead (its worker daemon hung or was cut off)
        # and starts another: this one must not run on beside it, nor promise anything
        loop.abandoned = loop.stopping = True
    elif op == "lost" and node in loop.streams.sources:
        loop.streams.lost_producers.add(node)
    elif op == "restarted" and node in loop.streams.sources:
        producer_restarted(loop, node, args.get("seqs"))
