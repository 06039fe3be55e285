"""What a node tells the coordinator: its step records and the events it published, in reports
(reporter.py sends them on its own thread), and the consumed events the coordinator may lack.

Consumed events reach the log through their producer's report, which may be lost with its
process (kill -9). So a consumer keeps the message of each event it received until the
coordinator says it has the event (control ``have``: per stream, the last seq its producer
reported), and holds back its step records that consumed an event the coordinator lacks, for at
most HOLD_RECORDS_NS; past that, or when the loop ends, a record goes with the messages of those
events, and the coordinator takes them as the producer's (each event is logged once).
"""

from __future__ import annotations

import time

from .clock import RunClock
from .notes import Notes
from .reporter import Reporter

#: how long published events may wait before they go to the coordinator (with the step records
#: before them), and at most how many records or bytes of events go at once. Every report wakes
#: the reporter's thread, Zenoh's and the coordinator, so a report gathers many ticks of a fast
#: flow rather than one or two; and it is due well within HOLD_RECORDS_NS, so a consumer's held
#: records find their events reported. Nothing else waits on a report: the coordinator logs the
#: events and shows them live (--foxglove), where a tenth of a second is no delay a user sees.
FLUSH_AFTER_NS = 100_000_000
#: how long step records may wait when no event waits with them (a flow that outputs nothing, or
#: not on every tick): nothing but the coordinator's counts and live view waits for those, so they
#: go once a second, and an idle flow's cost is its ticks, not its reports
#: (benchmarks/reports/idle_cpu.md has what each costs)
RECORDS_FLUSH_AFTER_NS = 1_000_000_000
FLUSH_MAX = 512
FLUSH_MAX_BYTES = 64 << 20
FLUSH_MAX_SEQS = 1 << 16  # seqs published: a flush at least this often (bursts), see frontiers.RESTART_SEQ_GAP
#: published messages at least this big reach the coordinator as files in the run's shared-memory
#: directory (one copy, and none on its side) instead of inside the report
SPILL_BYTES = 64 << 10
#: how long a step record that consumed an event the coordinator lacks may wait for it (above)
HOLD_RECORDS_NS = 200_000_000
#: a report handed over before the loop waits goes halfway into that wait, but at most this late
#: (reporter.py says why: its work and the coordinator's then run beside no message on its way)
REPORT_DEFER_MAX_NS = 20_000_000


class Reports:
    """``records``: step records not yet handed to the reporter; ``recorded``: step records made
    in all (the coordinator checks it got every tick); ``published``: (wall ns, data message) not
    yet reported; ``flush_due``: when the oldest of them must go (ns since T0). ``values``:
    whether the coordinator wants the events' values (for the trace or the log; the start says):
    without, reports carry each event without its value, and consumers keep nothing."""

    def __init__(self, reporter: Reporter, node_id: str, clock: RunClock, notes: Notes, streams: set):
        self.reporter, self.id, self.clock, self.notes = reporter, node_id, clock, notes
        self.streams = streams  # the input streams, (producer, port): what a `have` may name
        self.records: list = []
        self.recorded = 0
        self.held_records: list[tuple[int, tuple]] = []  # (held since, record): see HOLD_RECORDS_NS
        self.kept: dict[tuple[str, str, int], tuple[int, bytes]] = {}  # event id -> (arrival wall ns, message)
        self.values = True
        self.have: dict[tuple[str, str], int] = {}  # per input stream, the last seq the coordinator has
        self.published: list[tuple[int, bytes]] = []
        self.published_bytes = 0
        self.published_seqs = 0  # the seqs of the events in it (a burst's are many)
        self.flush_due: int | None = None

    def record(self, tau, consumed, produced, status, detail, start, wall) -> None:
        self.records.append((tau, consumed, produced, status, detail, start, wall))
        self.recorded += 1
        if self.flush_due is None:
            self.flush_due = self.clock.now() + RECORDS_FLUSH_AFTER_NS
        elif len(self.records) >= FLUSH_MAX:
            self.flush()

    def published_batch(self, now: int) -> None:
        """Events were just published: they go within FLUSH_AFTER_NS, or at once past the bounds."""
        if self.published_bytes >= FLUSH_MAX_BYTES or self.published_seqs >= FLUSH_MAX_SEQS:
            self.flush()
        else:  # (held LET outputs are released after their record went)
            due = now + FLUSH_AFTER_NS
            if self.flush_due is None or self.flush_due > due:  # (records alone may wait longer)
                self.flush_due = due

    def coordinator_has(self, last_seqs: dict[tuple[str, str], int]) -> None:
        """Control ``have`` (protocol.Have.last_seqs): per stream, the last seq the coordinator
        has; forget those messages. Looks up this node's input streams, not every stream named."""
        have = self.have
        for stream in self.streams:
            seq = last_seqs.get(stream)
            if seq is not None and seq > have.get(stream, -1):
                have[stream] = seq
        if self.kept:
            self.kept = {eid: kept for eid, kept in self.kept.items() if eid[2] > self.have.get(eid[:2], -1)}

    def unlogged(self, record: tuple) -> list[tuple[str, str, int]]:
        """The events a step record consumed that the coordinator may not have (and wants)."""
        if not self.values:
            return []
        have, me = self.have, self.id  # its own events go in its own reports, before its records
        return [eid for ids in record[1].values() for eid in ids if eid[0] != me and eid[2] > have.get(eid[:2], -1)]

    def flush(self, final: bool = False, defer_ns: int = 0) -> None:
        """Hand step records and published events to the reporter, for the coordinator: records
        that consumed an event it may lack wait (HOLD_RECORDS_NS), in order; past that, or when
        ``final``, they go with the messages of those events. ``defer_ns``: a report with events
        goes that much later (Reporter.send's ``not_before``; reporter.py says why); one of step
        records alone goes at once (nothing of size goes with it, and the reporter's thread
        wakes once, not twice: an idle flow's cost, benchmarks/reports/idle_cpu.md)."""
        held = self.held_records
        if self.records:
            since = time.monotonic_ns()
            held.extend((since, record) for record in self.records)
            self.records = []
        ready = 0
        if held:
            give_up = time.monotonic_ns() - HOLD_RECORDS_NS
            while ready < len(held) and (final or held[ready][0] <= give_up or not self.unlogged(held[ready][1])):
                ready += 1
        records = [record for _, record in held[:ready]]
        del held[:ready]
        events = self.published
        carried = {eid for record in records for eid in self.unlogged(record)}
        if carried:
            kept = (self.kept[eid] for eid in sorted(carried) if eid in self.kept)
            events = events + list({id(k): k for k in kept}.values())  # a burst's events share a message
        if records or events:
            self.reporter.send(records, events, self.published_seqs,
                               time.monotonic_ns() + defer_ns if defer_ns > 0 and events else None)
        self.published, self.published_bytes, self.published_seqs = [], 0, 0
        self.flush_due = self.clock.now() + FLUSH_AFTER_NS if held else None

    def finish(self) -> None:
        """Report what is left and return once every report is out (before a last status), and
        count how often and how long the loop waited for the reporter (it then ran late)."""
        self.flush(final=True)
        self.reporter.close()
        if self.reporter.waits:
            self.notes.counts["report_waits"] = self.reporter.waits
            self.notes.counts["report_wait_ns"] = self.reporter.waited_ns
