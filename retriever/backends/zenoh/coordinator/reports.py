"""Report ingest: the step records and events a worker's report brings, into the trace.

(The log is written from the trace: the coordinator's wait loop (waiting.py) hands what is new
to ``session.write_log()``, that is ``LogWriter.write``, every ``LOG_HANDOVER_S``.)

A report (status/report/<node>) holds a node's step records and the events it published (or a
consumer carried for its producer, whose own report may be lost). Each is checked against what
the node may claim (its clock's ticks, its own output ports, seqs not seen before); what fails is
counted as garbage, or as forged, and dropped. The coordinator is not on the events' path: the
workers send these reports after the fact, for the record.
"""

from __future__ import annotations

import mmap
import os
from collections.abc import Callable
from pathlib import Path

from ....trace import NOT_KEPT, STEPPED, StepStatus, Trace
from ..protocol import Have, Report, ReportedStep
from ..wire import WireError, decode_events
from .book import Intake, RunBook
from .control import RunControl
from .exits import ExitCut


class ReportIngest:
    """Takes reports into ``trace``; ``spill_dir``: where workers write the events too big for a
    message; ``on_exit_recorded(node)``: a step's record says it called sys.exit(0). A record or
    event checked goes on to :meth:`take_step` or :meth:`take_event`, or, in virtual time, to the
    run's ``exits`` (exits.ExitCut), which hands it on there once no exit can cut it off."""

    def __init__(self, book: RunBook, trace: Trace, spill_dir: Path, on_exit_recorded: Callable[[str], None],
                 exits: ExitCut | None = None):
        self.book, self.trace, self.spill_dir = book, trace, spill_dir
        self.on_exit_recorded = on_exit_recorded
        self.may_tick_at = {name: node.clock.may_tick_at for name, node in book.graph.nodes.items()}
        self.step, self.event = self.take_step, self.take_event
        if exits is not None:
            exits.hand_to(self.take_step, self.take_event)
            self.step, self.event = exits.step, exits.event

    def take(self, key: str, data: bytes, sender: object) -> None:
        """A report on ``key``, signed by ``sender`` (a process of its node: origin.py)."""
        book, intake = self.book, self.book.intake
        intake.reported_bytes += len(data)
        try:
            report = Report.decode(data, node=key.rsplit("/", 1)[1])
        except WireError as e:
            book.garbage(key, e)
            return
        if report.node not in intake.stats:
            book.garbage(key, WireError(f"a report of an unknown node '{report.node}'"))
            return
        intake.reports[report.node] += 1
        for wall, message in report.events:
            self._events(key, report.node, wall, message)
        for record in report.records:
            self._record(key, report.node, sender, record)

    def _record(self, key: str, node: str, sender: object, record: ReportedStep) -> None:
        """One step record of ``node``, checked: on to :meth:`take_step` (in virtual time, once final)."""
        book, intake = self.book, self.book.intake
        tag, consumed, produced, status, detail, start, wall = record
        if (node, tag) in intake.ticks:
            book.garbage(key, WireError(f"a second step record of {node} at {tag}"))
            return
        if not self.may_tick_at[node](tag, book.end_ns if book.t0 is not None else None):
            clock = book.graph.nodes[node].clock
            book.processes.senders.refuse(f"a step record of {node} at {tag}, which is no tick of its {clock!r}")
            return
        intake.ticks.add((node, tag))
        exit_code = detail.get("exit") if detail is not None else None
        if status == StepStatus.OK and type(exit_code) is int and exit_code == 0:  # its step's sys.exit(0)
            book.ending.exit_recorded[node] = (tag, sender)
            self.on_exit_recorded(node)
        self.step((node, tag, consumed, produced, status, detail, start, wall))

    def take_step(self, record: tuple) -> None:
        """A step record final: into the trace, the node's counters and the starvation watch."""
        intake = self.book.intake
        node, tag, consumed, produced, status, detail, start, wall = record
        self.trace.raw_steps.append(record)
        if intake.live is not None:
            intake.live.step(node, tag, consumed, produced, status, detail, start, wall)
        intake.starvation.step(node, tag, produced, detail)
        for event_id in produced:  # a LET output is published after its record went
            if event_id not in intake.event_ids:
                intake.unseen.add(event_id)
            if event_id[2] > intake.max_seq.get(event_id[:2], -1):
                intake.max_seq[event_id[:2]] = event_id[2]
        stats = intake.stats[node]
        stats.ticks += 1
        if status in STEPPED:
            stats.steps += 1
            stats.step_ns += wall
        elif status == StepStatus.SKIPPED:
            stats.skips += 1
        else:
            stats.errors += 1
            stats.step_ns += wall

    # ---------------------------------------------------------------------------------------
    # Events
    # ---------------------------------------------------------------------------------------
    def _events(self, key: str, node: str, wall: int, message: bytes | str) -> None:
        try:
            events = decode_events(message if type(message) is bytes else self._unspill(node, message), blank_ok=True)
        except WireError as e:
            self.book.garbage(key, e)
            return
        for msg in events:
            self._event(key, node, wall, msg)

    def _event(self, key: str, node: str, wall: int, msg) -> None:
        book, intake = self.book, self.book.intake
        stream = (msg.producer, msg.port)
        event_id = (msg.producer, msg.port, msg.seq)
        if msg.producer != node:  # carried by a consumer, for a producer whose report may be lost
            if (msg.producer, msg.port, node) not in intake.feeds:
                book.garbage(key, WireError(f"{node} reported an event of {msg.producer}.{msg.port}, "
                                            "which is no output port of it nor one it consumes"))
            elif event_id not in intake.event_ids:
                intake.carried.add(event_id)
                self._keep(event_id, msg, wall)
            return
        if stream not in intake.streams and node not in intake.open_outputs:
            book.garbage(key, WireError(f"{node} reported an event of {msg.producer}.{msg.port}, "
                                        "which is no output port of it"))
            return
        if event_id in intake.carried:  # its producer's report came after all
            intake.carried.discard(event_id)
            return
        if event_id in intake.event_ids:
            book.garbage(key, WireError(f"event {event_id} arrived twice"))
            return
        self._keep(event_id, msg, wall)

    def _keep(self, event_id: tuple[str, str, int], msg, wall: int) -> None:
        book, intake = self.book, self.book.intake
        intake.event_ids.add(event_id)
        intake.unseen.discard(event_id)
        producer, port, seq = event_id
        have = intake.have.get((producer, port), -1)
        while (producer, port, have + 1) in intake.event_ids:  # every seq up to it (carried ones may skip)
            have += 1
        intake.have[(producer, port)] = have
        self.event((msg.tag, producer, port, seq, msg.value if book.values else NOT_KEPT, wall))

    def take_event(self, event: tuple) -> None:
        """An event final: into the trace."""
        intake = self.book.intake
        tag, producer, port, seq, value, wall = event
        if seq > intake.max_seq.get((producer, port), -1):
            intake.max_seq[(producer, port)] = seq
        self.trace.raw_events.append(event)
        if intake.live is not None:
            intake.live.event(producer, port, tag, seq, value, wall)

    def _unspill(self, node: str, name: str) -> mmap.mmap:
        """A message a worker wrote to a file of the run directory: mapped (its arrays are views
        of the mapping), and the file removed (the mapping keeps its pages)."""
        if not name.startswith(f"{node}.") or not name.endswith(".msg") or "/" in name:
            raise WireError(f"{node} reported an event in the file {name!r:.80}, which is not one of its files")
        path = self.spill_dir / name
        try:
            fd = os.open(path, os.O_RDONLY)
        except OSError as e:
            raise WireError(f"{node} reported an event in {path}, which cannot be opened: {e.strerror}") from None
        try:
            path.unlink()
            mapped = mmap.mmap(fd, 0, access=mmap.ACCESS_READ)
            self.book.intake.reported_bytes += len(mapped)
            return mapped
        except (OSError, ValueError) as e:  # ValueError: an empty file
            raise WireError(f"{node} reported an event in {path}, which cannot be mapped: {e}") from None
        finally:
            os.close(fd)


def tell_have(intake: Intake, control: RunControl) -> None:
    """Tell the consumers which events the coordinator has (the last seq of each stream that
    moved on since last told): they forget those messages and report the records that wait."""
    moved = tuple((src, port, seq) for (src, port), seq in intake.have.items()
                  if intake.have_told.get((src, port)) != seq)
    if moved:
        control.put(Have(streams=moved))
        intake.have_told.update(((src, port), seq) for src, port, seq in moved)
