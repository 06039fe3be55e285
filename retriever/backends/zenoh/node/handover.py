"""Restarting a flow (``on_error="restart"``) in a new process: the hand-over of a loop's state,
and, when the old process died, a fresh start and the word its consumers get of it.

A step raised. This process runs no more ticks, but keeps receiving (its input buffers stay
whole) and answering for its frontier (it stays at the tick due), releases held LET outputs on
time, and says ``restart``. The coordinator starts a new process, which listens to the same
inputs and says ``ready``; then it tells this one to hand over: this loop stops, and its state
goes to the new process in a file (``handover_state``, ``take_over``). The new loop goes on from
that state with a fresh flow, so what it consumes is what one process would have consumed: a log
replays, the replay resetting the flow at the error record as the in-process backend does. Rate
ticks that came due meanwhile are skipped but the newest (like an overrun), and triggered ticks
run late. Of each input buffer, filled meanwhile, only what its policy can still select goes
(SyncPolicy.selectable), a burst's events as one run; more than HANDOVER_EVENTS_MAX of them (a
Queue far behind) stop the run instead, saying why (too_many_to_hand_over).

The process died (kill -9, a segfault): nothing can be handed over. The flow starts afresh in a
new process, with empty input buffers. The coordinator says ``lost`` {node} at once; the new
process subscribes to its inputs and learns from each producer's progress answer the seq its
streams go on from (``sync_inputs``; older ones it ignores), links to its consumers and says
``ready``. The coordinator then puts ``restarted`` {node, seqs}: the new process's first seq per
output port (``start_fresh``), past every one the dead process may have used (RESTART_SEQ_GAP).
Each consumer of it gives up the seqs it still missed from the dead process, tells its next
record which (``restart_gap``, so a replay withholds exactly those), and takes the stream on from
there (``producer_restarted``). The new process's first record says where its inputs began
(``restarted``): a replay resets the flow and empties its buffers there, as the run did.
"""

from __future__ import annotations

import heapq
import time
from bisect import bisect_left
from pathlib import Path
from typing import Any

from ....errors import StopRun, WorkerError
from ....flow.burst import Burst, travels_as_rows
from ....time import format_tag
from ..protocol import HANDOVER_EVENTS_MAX, RESTART_SEQ_GAP, HandoverState, decode_handover_state
from ..wire import DataMessage, WireError
from .frontiers import EARLY_SEQS_MAX, NEVER, Streams


def handover_state(loop) -> dict:
    """The state of ``loop`` (a NodeLoop), for the process that takes over (call after
    ``undeclare`` and the loop's last drain: no more messages come). StopRun when its inputs hold
    more than HANDOVER_EVENTS_MAX events a later tick may still select."""
    streams, schedule, outputs = loop.streams, loop.schedule, loop.outputs
    kept = [(port, policy, policy.selectable(buf, schedule.last_tick)) for port, buf, policy, _ in loop.steps.inputs]
    if sum(len(buf.entries) for *_, buf in kept) > HANDOVER_EVENTS_MAX:
        raise too_many_to_hand_over(loop.id, kept, schedule.last_tick)
    for what, items in (("trigger ticks pending", schedule.pending), ("LET outputs held", outputs.held)):
        if len(items) > HANDOVER_EVENTS_MAX:  # as many as the reader takes (protocol/handover.py)
            raise StopRun(f"flow '{loop.id}' cannot restart after its step failed: it has {len(items):,} {what}, "
                          f"more than a new process takes over (HANDOVER_EVENTS_MAX = {HANDOVER_EVENTS_MAX:,})\n"
                          "    hint: on_error='skip_tick' goes on in the same process", schedule.last_tick)
    return {
        "buffers": [[port, _runs(buf.entries), buf.visible, buf.cursor, buf.last_id] for port, _, buf in kept],
        "streams": [[src, port, streams.frontiers[(src, port)], streams.expect[(src, port)],
                     [tuple(m) for m in streams.early[(src, port)].values()], streams.waiting[(src, port)]]
                    for src, port in sorted(streams.frontiers)],
        "pending": schedule.pending, "k": schedule.k, "next_rate": schedule.next_rate,
        "last_tick": schedule.last_tick, "last_stamp": outputs.last_stamp, "seqs": outputs.seqs, "sent": outputs.sent,
        # a held burst goes as its values, marked (the codec encodes values, not bursts)
        "held": [(tag, port, value.values, seq, "burst") if type(value) is Burst else (tag, port, value, seq)
                 for tag, port, value, seq in outputs.held],
        "pending_detail": loop.notes.detail, "values": loop.reports.values,
    }


def too_many_to_hand_over(node: str, kept: list[tuple], tag: tuple[int, int]) -> StopRun:
    """Why the run stops: ``node``'s inputs hold more events than a restart hands over in time
    (``kept``: per input, its port, its policy and what that can still select)."""
    port, policy, buf = max(kept, key=lambda k: len(k[2].entries))
    total, most = sum(len(b.entries) for *_, b in kept), len(buf.entries)
    held = f"{most:,} events of {node}.{port} ({policy!r})" if total == most else \
        f"{total:,} events, {most:,} of them of {node}.{port} ({policy!r}),"
    return StopRun(
        f"flow '{node}' cannot restart after its step failed at {format_tag(tag)}: its new process would take "
        f"over {held} that its next ticks may still select, more than it can in time (HANDOVER_EVENTS_MAX = "
        f"{HANDOVER_EVENTS_MAX:,})\n    hint: on {node}.{port}, Latest() or Window(n) hand over only the events "
        "they may still select; or on_error='skip_tick' goes on in the same process", tag)


def _runs(entries: list[tuple]) -> list[list]:
    """A buffer's entries (tag, producer, port, seq, value), in order, as runs of one tag, producer
    and port with consecutive seqs: ``[tag, producer, port, first seq, values]`` (a burst is one
    run: its events are written, and checked when read, as a whole). Values that are arrays of
    one dtype and shape go as the rows of one array, as a burst of them travels (flow/burst.py)."""
    runs, start, end = [], 0, len(entries)
    while start < end:
        tag, producer, port, seq, _ = entries[start]
        # past every entry at this tag from this port: no port name sorts between it and port + "\0"
        stop = bisect_left(entries, (tag, producer, port + "\0"), start, end)
        if entries[stop - 1][3] - seq != stop - 1 - start:  # a gap in the seqs: the run ends before it
            stop = start + bisect_left(range(start, stop), True, key=lambda i: entries[i][3] - seq != i - start)
        values = [e[4] for e in entries[start:stop]]
        rows = Burst.unchecked(values).stacked()
        runs.append([tag, producer, port, seq, rows if rows is not None and travels_as_rows(rows) else values])
        start = stop
    return runs


def take_over(loop, state: HandoverState) -> None:
    """Go on from the state of the process ``loop`` replaces (:func:`read_state` of what
    :func:`handover_state` wrote)."""
    buffers = {port: buf for port, buf, *_ in loop.steps.inputs}
    for port, entries, visible, cursor, last_id in state.buffers:
        buf = buffers[port]
        buf.entries, buf.visible, buf.cursor, buf.last_id = list(entries), visible, cursor, last_id
    streams = loop.streams
    for src, port, frontier, expect, early, waiting in state.streams:
        stream = (src, port)
        streams.frontiers[stream], streams.expect[stream] = frontier, expect
        streams.early[stream] = {m[1]: DataMessage(*m) for m in early}
        streams.waiting[stream] = sorted(waiting)
        streams.taken_over[stream] = max([expect, *(seq + 1 for seq in streams.early[stream])])
    loop.schedule.restore(state.k, state.next_rate, state.pending, state.last_tick)
    outputs = loop.outputs
    outputs.last_stamp = state.last_stamp
    outputs.held = [(h[0], h[1], Burst.unchecked(h[2]), h[3]) if len(h) == 5 else h for h in state.held]
    heapq.heapify(outputs.held)
    loop.reports.values = state.values
    _replace(outputs.seqs, state.seqs)
    _replace(outputs.sent, state.sent)
    loop.notes.detail = dict(state.pending_detail)


# ---------------------------------------------------------------------------------------------
# The state file, read exactly (protocol/handover.py), of this loop's inputs
# ---------------------------------------------------------------------------------------------
#: how the new process learns what went wrong, and what to do
_HINT = ("    hint: the flow's old process writes it in the run's private folder just before the new one "
         "reads it: both must run the same Retriever, and nothing else may write there; run again")


def read_state(path: Path, loop) -> HandoverState:
    """The state file ``path`` that ``loop``'s (a NodeLoop's) old process wrote, decoded
    exactly (:func:`decode_state`); WorkerError naming the file for anything else: a new
    process that cannot take over says so rather than going on from a state it misread."""
    try:
        data = path.read_bytes()
    except OSError as e:
        raise WorkerError(f"cannot read the hand-over state file {path}: {e.strerror}\n{_HINT}") from None
    try:
        return decode_state(data, loop)
    except WireError as e:
        raise WorkerError(f"the hand-over state file {path} is no state of node '{loop.id}': {e}\n{_HINT}") from None


def decode_state(data: bytes, loop) -> HandoverState:
    """:func:`handover_state`'s map, encoded by the codec, as a :class:`HandoverState`
    (protocol.decode_handover_state) of ``loop``'s inputs: the same ports and streams; WireError
    naming the field otherwise."""
    state = decode_handover_state(data)
    ports, held = sorted(port for port, *_ in loop.steps.inputs), sorted(b[0] for b in state.buffers)
    if held != ports:
        raise WireError(f"'buffers' holds the ports {held}; the node's are {ports}")
    streams, mine = sorted(s[:2] for s in state.streams), sorted(loop.streams.frontiers)
    if streams != mine:
        raise WireError(f"'streams' holds {streams}; the node's are {mine}")
    return state


def _replace(mapping: dict, items: dict) -> None:
    """In place: the loop hands these dicts out (the worker reads ``loop.sent``)."""
    mapping.clear()
    mapping.update(items)


def sync_inputs(streams: Streams, answers: dict[str, Any]) -> None:
    """Take each input stream on from where its producer stands now (a fresh process):
    ``answers`` maps a producer to its progress answer, or to None when it is finished."""
    first: dict[str, list] = {}
    for e in streams.edges:
        stream = (e.src, e.src_port)
        if e.src not in answers:  # it never answered: its events are taken from seq 0
            continue
        answer = answers[e.src]
        if answer is None:
            streams.frontiers[stream] = NEVER
            streams.taken_over[stream] = streams.expect[stream] = 1 << 62
            continue
        expect = answer.sent.get(e.src_port, -1) + 1
        streams.frontiers[stream] = max(streams.frontiers[stream], answer.frontier)
        streams.expect[stream] = streams.taken_over[stream] = expect  # older ones may still arrive: ignored
        first.setdefault(e.port, []).append([e.src, e.src_port, expect])
    streams.fresh_inputs = {port: sorted(ids) for port, ids in first.items()}


def start_fresh(loop, seqs: dict[str, int], t0: int) -> None:
    """Go on from the coordinator's ``restarted``: each output port's first seq, Rate ticks from now."""
    streams = loop.streams
    _replace(loop.outputs.seqs, seqs)
    _replace(loop.outputs.sent, {port: seq - 1 for port, seq in seqs.items()})
    for e in streams.edges:  # a feedback edge to itself: its inputs are its new outputs
        if e.src == loop.id and e.src_port in seqs:
            stream = (e.src, e.src_port)
            streams.expect[stream] = streams.taken_over[stream] = seqs[e.src_port]
            streams.fresh_inputs.setdefault(e.port, []).append([e.src, e.src_port, seqs[e.src_port]])
    loop.notes.detail["restarted"] = {"seqs": dict(sorted(seqs.items())), "inputs": streams.fresh_inputs}
    clock = loop.schedule.clock
    if clock.hz is not None:  # run() starts at this tick
        loop.schedule.k = clock.first_tick_at_or_after(time.time_ns() - t0)


def producer_restarted(loop, producer: str, seqs: dict[str, int]) -> None:
    """Control ``restarted`` {node: producer, seqs: {port: first seq}}: see above. Checked for
    sense first (a forged one would cut this consumer off a live producer): the producer was
    said ``lost``, and each first seq lies where the coordinator puts it, past every seq taken
    by at most RESTART_SEQ_GAP + EARLY_SEQS_MAX. A process that took its inputs on afresh from
    the producer's own answer (sync_inputs) needs no word of it: one it has caught up is ignored."""
    streams, notes = loop.streams, loop.notes
    mine = [s for s in streams.frontiers if s[0] == producer]
    refusal = _refusal(streams, producer, seqs, mine)
    if refusal is not None:
        if refusal:
            notes.garbage(loop.keys.run_control(), WireError(refusal))
        return
    streams.lost_producers.discard(producer)
    # records that consumed an event of the dead process the coordinator lacks go now, with
    # it: the coordinator's next `have` jumps over the seqs this one gives up
    loop.reports.flush(final=True)
    for stream in mine:
        first = seqs.get(stream[1])
        if first is None:
            continue
        expect = streams.expect[stream]
        for e in streams.edges:
            if (e.src, e.src_port) == stream:
                gaps = notes.detail.setdefault("restart_gap", {}).setdefault(e.port, [])
                gaps.append([producer, stream[1], expect, first])
        later = {seq: msg for seq, msg in streams.early[stream].items() if seq >= first}
        waiting = streams.waiting[stream]
        promised = [f for seq, f in waiting if seq < first]  # the dead process's, and the new one's start
        streams.waiting[stream] = [(seq, f) for seq, f in waiting if seq >= first]
        streams.expect[stream], streams.early[stream] = first, {}
        streams.taken_over[stream] = first  # what the dead process sent and arrives now is ignored
        if promised:
            streams.advance(stream, max(promised))
        for seq in sorted(later):
            streams.in_order(stream, later[seq])


def _refusal(streams: Streams, producer: str, seqs: dict[str, int], mine: list) -> str | None:
    """Why a ``restarted`` of ``producer`` is refused (garbage), "" if it is ignored (no word
    of it was needed), None if it is taken. ``seqs`` has its shape already (protocol.Restarted's
    decoder); what is checked here is whether it makes sense for this consumer's streams."""
    if producer not in streams.lost_producers:
        if any(seqs.get(s[1], -1) > streams.expect[s] for s in mine):
            return f"a 'restarted' control message of {producer}, which was not said lost: refused"
        return ""
    wild = [s for s in mine if s[1] in seqs and not 0 <= seqs[s[1]] - streams.expect[s] <= RESTART_SEQ_GAP
            + EARLY_SEQS_MAX]
    if wild:
        return (f"a 'restarted' control message of {producer} puts {producer}.{wild[0][1]} at seq "
                f"{seqs[wild[0][1]]}, where its stream is at {streams.expect[wild[0]]}: refused")
    return None
