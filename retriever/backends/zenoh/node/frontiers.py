"""A node's input streams: each taken in seq order, each with its producer's frontier.

A *frontier* is a producer's promise: every later event of it has a tag ``≥`` the frontier.
Producers send theirs on data messages, on progress messages after ticks whose outputs do not
carry it, and on demand (waiting.py asks). A stream's events are delivered to its edges' buffers
in seq order; a frontier holds once every seq before it has been taken.
"""

from __future__ import annotations

import heapq
import threading
from bisect import bisect_left, insort
from typing import Any

from ....sync import PortBuffer, before, bound, fill
from ..protocol import RESTART_SEQ_GAP
from ..wire import WireError
from .clock import RunClock
from .notes import Notes

#: a frontier no event reaches: the producer is finished
NEVER = (1 << 62, 0)

#: What a message may claim, past which it is refused as garbage (never applied): a frontier is a
#: producer's promise, and a producer can promise no tag past the run's end plus its latency
#: (its ticks end there; LET outputs are stamped tick + latency), except NEVER once it is done and,
#: without latency, its HLC stamp at completion: at most CLOCK_AHEAD_MAX_NS past this process's
#: clock, the skew Zenoh's own HLC tolerates between sessions (500 ms). A seq may arrive ahead of
#: the next one expected (Zenoh orders per route; a message may overtake on another), by a few,
#: not by EARLY_SEQS_MAX: a message that far ahead would hold its stream's gap open forever.
CLOCK_AHEAD_MAX_NS = 500_000_000
EARLY_SEQS_MAX = 4096

#: A progress message may come far ahead of the data messages it comes after (another key; a
#: consumer that lags behind a producer of bursts may be millions of seqs behind): it waits for
#: them, whatever its seq. At most WAITING_MAX wait per stream; past that every other one is
#: forgotten (a frontier is a promise that only makes a tick run sooner: forgetting one delays a
#: tick to the next promise, it never changes what a tick sees).
WAITING_MAX = 4096

class InEdge:
    """One incoming edge: where its events go and how long a tick waits for it."""

    __slots__ = ("src", "src_port", "port", "buf", "delay_ns", "triggers", "deadline_ns", "src_latency_ns")

    def __init__(self, src: str, src_port: str, port: str, buf: PortBuffer, delay_ns: int, triggers: bool,
                 deadline_ns: int, src_latency_ns: int = 0):
        self.src, self.src_port, self.port, self.buf = src, src_port, port, buf
        self.delay_ns, self.triggers, self.deadline_ns = delay_ns, triggers, deadline_ns
        self.src_latency_ns = src_latency_ns  # the producer's declared latency: how far past the end it stamps


class Streams:
    """Per input stream (producer, port): its frontier, the next seq to take in order,
    out-of-order arrivals, and progress messages waiting for the seqs they come after. What the
    events make ready goes to ``schedule`` (trigger ticks); ``lock`` guards what the progress
    queryable reads (the frontiers, through the schedule's tick bound)."""

    def __init__(self, node_id: str, edges: list[InEdge], schedule, clock: RunClock, notes: Notes,
                 lock: threading.Lock):
        self.id, self.edges, self.schedule, self.clock, self.notes, self.lock = (
            node_id, edges, schedule, clock, notes, lock)
        streams = {(e.src, e.src_port) for e in edges}
        self.frontiers: dict[tuple[str, str], tuple[int, int]] = {k: (0, 0) for k in streams}
        self.expect: dict[tuple[str, str], int] = {k: 0 for k in streams}
        self.early: dict[tuple[str, str], dict[int, Any]] = {k: {} for k in streams}
        self.waiting: dict[tuple[str, str], list[tuple[int, tuple[int, int]]]] = {k: [] for k in streams}
        self.src_latency_ns = {(e.src, e.src_port): e.src_latency_ns for e in edges}
        self.stream_edges: dict[tuple[str, str], list[InEdge]] = {k: [] for k in streams}  # where each goes
        for e in edges:
            self.stream_edges[(e.src, e.src_port)].append(e)
        self.sources = sorted({e.src for e in edges})
        self.triggering = [e for e in edges if e.triggers]
        self.taken_over: dict[tuple[str, str], int] = {}  # per stream, the seqs an earlier process took
        self.lost_producers: set[str] = set()  # producers whose process died, until they restart
        self.fresh_inputs: dict[str, list] = {}  # a fresh process: per input port, where its streams began

    def edge_frontier(self, e: InEdge) -> tuple[int, int]:
        """The producer's frontier as this edge delivers it (a delay shifts it, microstep 0)."""
        f = self.frontiers[(e.src, e.src_port)]
        return (f[0] + e.delay_ns, 0) if e.delay_ns else f

    def tick_bound(self) -> tuple[int, int]:
        """No future tick of this node has a tag below this (call with ``lock`` held, or on the
        main thread)."""
        schedule = self.schedule
        bound = schedule.next_rate if schedule.next_rate is not None else NEVER
        if schedule.pending and schedule.pending[0] < bound:
            bound = schedule.pending[0]
        frontiers = self.frontiers
        for e in self.triggering:  # (edge_frontier and min, inline: per event published, per progress answer)
            f = frontiers[(e.src, e.src_port)]
            if e.delay_ns:
                f = (f[0] + e.delay_ns, 0)
            if f < bound:
                bound = f
        return bound

    def horizon(self, tag: tuple[int, int]) -> tuple[int, int]:
        """Every future tick of this node is past this tag, while an event with tag ``tag`` is
        delivered: past the last one, and at or after the tick in progress, the next Rate tick,
        the pending trigger ticks, each triggering edge's frontier (:meth:`tick_bound`) and
        ``tag`` (the event may trigger a tick there, not yet pending; its frontier already
        counts it). What sync.fill bounds a buffer by."""
        schedule = self.schedule
        with self.lock:
            running, bound = schedule.running, self.tick_bound()
        bound = min(bound, tag) if running is None else min(bound, tag, running)
        return max(schedule.last_tick, before(bound))

    def check_claims(self, stream: tuple[str, str], seq: int | None, frontier: tuple[int, int]) -> None:
        """Refuse a data message's seq from the future or a frontier its producer cannot promise
        (see CLOCK_AHEAD_MAX_NS): applied, one would hold the stream back, or make every later
        event of it late, for the rest of the run."""
        expect = self.expect[stream]
        ahead = EARLY_SEQS_MAX + (RESTART_SEQ_GAP if stream[0] in self.lost_producers else 0)
        if seq is not None and seq > expect + ahead:
            raise WireError(f"seq {seq} of {stream[0]}.{stream[1]} is {seq - expect} past the next one expected "
                            f"({expect}): a seq from the future")
        if frontier == NEVER:
            return
        if frontier > NEVER:
            raise WireError(f"frontier {frontier} of {stream[0]} is past every tag a run has")
        end = self.clock.promised_end
        if end and frontier[0] > end + self.src_latency_ns[stream] + 1:  # the run started: end known
            # past the run's end plus the producer's latency only an ASAP stamp can be, near the clock
            limit = self.clock.now() + CLOCK_AHEAD_MAX_NS
            if frontier[0] > limit:
                raise WireError(f"frontier {frontier} of {stream[0]} is past what it can promise now (t <= "
                                f"{end + self.src_latency_ns[stream] + 1} ns, the run's end plus its latency, "
                                f"or {limit} ns, its clock)")

    def in_order(self, stream: tuple[str, str], msg) -> None:
        """Take a stream's events in seq order (Zenoh may reorder across routes); a frontier
        holds once every seq before it has been taken."""
        expect, seq = self.expect[stream], msg[1]  # (msg.seq: a NamedTuple's field is a slow read in 3.11)
        if seq < expect or seq in self.early[stream]:
            # a duplicate; below taken_over it is one the process this one took over from had
            # too (both listened meanwhile): expected, not garbage
            if seq >= self.taken_over.get(stream, 0):
                self.notes.garbage(stream, WireError(f"seq {seq} of {stream[0]}.{stream[1]} arrived twice"))
            return
        if seq > expect:
            self.early[stream][seq] = msg
            return
        early, frontiers, edges = self.early[stream], self.frontiers, self.stream_edges[stream]
        schedule = self.schedule
        while msg is not None:
            due = None  # the trigger ticks it makes (one per edge at most)
            for e in edges:
                tick = self.deliver(e, msg)
                if tick is not None:
                    due = [tick] if due is None else due + [tick]
            # its frontier and the ticks it triggers, together under the lock (one acquisition
            # per event; advance, inline): the progress queryable never sees the frontier past
            # a tick not yet pending, which would let this node promise past that tick's outputs
            frontier = msg[2]  # (msg.frontier)
            if due is not None or frontier > frontiers[stream]:
                with self.lock:
                    if frontier > frontiers[stream]:
                        frontiers[stream] = frontier
                    if due is not None:
                        for tick in due:
                            if tick not in schedule.pending_set:
                                schedule.pending_set.add(tick)
                                heapq.heappush(schedule.pending, tick)
            expect += 1
            msg = early.pop(expect, None)
        self.expect[stream] = expect
        waiting = self.waiting[stream]
        if waiting and waiting[0][0] < expect:  # (sorted by seq)
            ready = bisect_left(waiting, (expect,))
            self.advance(stream, max(f for _, f in waiting[:ready]))
            del waiting[:ready]

    def progress(self, stream: tuple[str, str], after_seq: int, frontier: tuple[int, int]) -> None:
        """A progress message: ``frontier`` holds once the seqs up to ``after_seq`` are taken."""
        if after_seq < self.expect[stream]:
            self.advance(stream, frontier)
            return
        waiting = self.waiting[stream]
        insort(waiting, (after_seq, frontier))
        if len(waiting) > WAITING_MAX:  # every other one goes, the last one stays: a later one promises as much
            del waiting[-2::-2]

    def advance(self, stream: tuple[str, str], frontier: tuple[int, int]) -> None:
        if frontier > self.frontiers[stream]:
            with self.lock:
                self.frontiers[stream] = frontier

    def deliver(self, e: InEdge, msg) -> tuple[int, int] | None:
        """Put an event in its edge's buffer; the tick it triggers, for the caller to schedule
        (None if it triggers none, or one pending already)."""
        tag, seq, _, producer, port, value = msg  # (one unpacking: a NamedTuple's fields are slow reads in 3.11)
        arrival = (tag[0] + e.delay_ns, 0) if e.delay_ns else tag
        entry = (arrival, producer, port, seq, value)
        schedule = self.schedule
        if arrival <= schedule.last_tick:
            # A tick at or after this tag already ran without it: never applied to that past tick,
            # but in the buffer, by its tag, for every tick from the next one on (a slow policy's
            # chunk still reaches its controller). Its next record names it, by id: a replay puts
            # it in the buffer at exactly that point (retriever/replay/steps.py). It triggers no past tick.
            self.notes.counts["late"] += 1
            self.notes.detail.setdefault("late", {}).setdefault(e.port, []).append((producer, port, seq))
            fill(e.buf, entry, self.horizon, tag)
            return None
        # (sync.fill and PortBuffer.insert, inline for an event after the buffer's last: in order)
        buf = e.buf
        entries = buf.entries
        if entries and not entries[-1] < entry:
            fill(buf, entry, self.horizon, tag)
        else:
            entries.append(entry)
            if len(entries) >= buf.bound_at:
                bound(buf, self.horizon(tag))
        if e.triggers and arrival[0] < self.clock.end and arrival not in schedule.pending_set:
            return arrival
        return None

    def had_below(self, ports: list[str]) -> dict[str, list[list]]:
        """For a tick run incomplete: per port, each of its producers' streams and the seq it
        expects next. The tick saw that stream's events below it and none from it on (a stream
        is taken in order), so a replay can withhold the later ones with an earlier tag that came
        after this tick: those its next record names late, and those that never came (its
        process died, or the run ended first), which no record names."""
        return {port: [[e.src, e.src_port, self.expect[(e.src, e.src_port)]] for e in self.edges if e.port == port]
                for port in ports}
