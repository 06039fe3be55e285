"""A tick: select the inputs, call ``step()``, and decide what its outcome means (publish, hold,
record; an overrun, a LET deadline missed, an error: skip, stop, restart, or end the run).

Taking the inputs, the timed step call and the step records of a skipped or failed tick are the
reference tick's own (tick.take_inputs, tick.timed_step, tick.skipped_outcome and the others, as
the in-process backend uses them); what is here is a real-time node's accounts of the outcome."""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from typing import Any, Protocol

from ....errors import CodecError, StopRun
from ....graph import Node
from ....flow.core import make_invoker, with_step_detail
from ....flow.burst import Burst
from ....flow.read_only import make_read_only
from ....tick import (Decision, decide, ending, error_outcome, error_text, exit_outcome, skipped_outcome, take_inputs,
                      timed_step)
from ....time import format_tag
from ....trace import StepStatus
from .clock import RunClock
from .ending import Ending
from .frontiers import Streams
from .in_place import InPlaceRestart
from .notes import Notes
from .outputs import Outputs
from .reports import Reports
from .schedule import Schedule


class StepsOwner(Protocol):
    """What :class:`Steps` reads and sets of the loop it serves (a NodeLoop), as it changes."""

    #: how long the last step took (set here; the loop reads it to run a tick inline or not)
    last_wall: int | None
    #: set here when a failed step starts a restart (on_error="restart")
    restarting: bool
    #: called with the tick whose step called sys.exit(0); with (tag, error) when a restart starts
    on_exit: Callable[[tuple[int, int]], None] | None
    on_restart: Callable[[tuple[int, int], str], None] | None
    #: a flow restarted where it runs (a group's member: in_place.py); None: in a new process
    in_place: InPlaceRestart | None

    def stop(self, ending: Ending) -> None: ...


class Steps:
    """The ticks of ``node``: its flow, called as the in-process backend calls it (``invoke``,
    ``read``), and its settings (``on_error``, ``on_overrun``, ``on_deadline_miss``;
    ``realtime``). The parts of the loop it works with are handed in; ``owner`` is the loop's
    state it changes (:class:`StepsOwner`)."""

    def __init__(self, owner: StepsOwner, node: Node, inputs: list[tuple], fallbacks: dict, invoke, read, *,
                 realtime: str, virtual: bool, notes: Notes, schedule: Schedule, outputs: Outputs, reports: Reports,
                 streams: Streams, clock: RunClock, lock: threading.Lock):
        self.owner = owner
        self.id, self.flow, self.spec, self.virtual = node.id, node.flow, node.spec, virtual
        self.inputs = inputs  # (port, buffer, policy, port spec), as in the in-process backend
        self.fallbacks = fallbacks
        self.invoke, self.read = invoke, read
        self.notes, self.schedule, self.outputs, self.reports = notes, schedule, outputs, reports
        self.streams, self.clock, self.lock = streams, clock, lock
        settings = node.settings
        self.realtime = realtime
        self.on_error, self.on_overrun, self.on_deadline_miss = (
            settings.on_error, settings.on_overrun, settings.on_deadline_miss)
        if realtime == "best_effort":  # misses are counted and logged, never fatal
            self.on_overrun = "skip" if self.on_overrun == "error" else self.on_overrun
            self.on_deadline_miss = "publish_late" if self.on_deadline_miss == "error" else self.on_deadline_miss
        self.period_ns = round(1e9 / float(node.clock.hz)) if node.clock.hz is not None else 0

    def tick(self, tau: tuple[int, int], incomplete: list[str]) -> None:
        """Run the tick ``tau`` (taken from the schedule); ``incomplete``: its edges past deadline."""
        self.schedule.last_tick = tau
        notes = self.notes
        detail: dict[str, Any] | None = notes.detail or None
        if detail:
            notes.detail = {}
        if incomplete:
            notes.counts["incomplete"] += 1
            detail = {**(detail or {}), "incomplete": incomplete, "had_below": self.streams.had_below(incomplete)}
            if self.realtime == "hard":  # the tick does not step: skipped, and the run stops
                self.reports.record(tau, {}, (), StepStatus.SKIPPED, detail, time.time_ns(), 0)
                raise StopRun(f"{self.id}: input(s) {', '.join(incomplete)} not complete up to the tick at "
                              f"t={tau[0] / 1e9:.6f} s within the deadline (realtime='hard')\n"
                              "    hint: raise the edge's deadline= or the Pipeline's, or use realtime='soft'", tau)
        values, consumed, missing, dropped = take_inputs(self.inputs, self.fallbacks, tau)
        if dropped:
            detail = {**(detail or {}), **dropped}
        if missing is not None:
            self.finish_tick(tau, {}, (), *skipped_outcome(missing, detail), time.time_ns(), 0)
            return
        outputs, exc, start, end = timed_step(self.invoke, self.read, values)
        if exc is not None:
            self.step_failed(tau, consumed, detail, exc, start)
            return
        wall = end - start
        self.owner.last_wall = wall
        overran = self.period_ns and wall > self.period_ns and not self.virtual
        self.emit(tau, consumed, outputs, detail, start, wall,
                  StepStatus.OVERRUN if overran else StepStatus.INCOMPLETE if incomplete else StepStatus.OK)
        if overran:
            self.overran(tau, wall, start + wall - self.clock.t0)

    def step_failed(self, tau, consumed, detail, exc: BaseException, start: int) -> None:
        """The step raised ``exc`` (not KeyboardInterrupt): record it, then act on what
        tick.decide makes of ``on_error``: stop the run, go on, restart the flow (in place, within
        the budget held here; or in a new process: ask the coordinator, which holds the budget),
        or end the whole run cleanly (``sys.exit(0)``)."""
        owner, in_place = self.owner, self.owner.in_place
        wall = owner.last_wall = time.time_ns() - start
        decision = decide(self.on_error, exc, None if in_place is None else in_place.budget, tau[0])
        if decision is Decision.END_RUN:
            # the coordinator is told first (it stops every node), then this loop ends as if told to stop
            self.finish_tick(tau, consumed, (), *exit_outcome(detail), start, wall)
            if owner.on_exit is not None:
                owner.on_exit(tau)
            owner.stop(Ending.TOLD_TO_STOP)
            return
        error = error_text(exc)
        self.finish_tick(tau, consumed, (), *error_outcome(error, self.on_error, detail), start, wall)
        if decision is Decision.STOP:
            raise StopRun(f"{self.id}.step() raised {error}", tau, raised=error) from exc
        if decision is Decision.OUT_OF_RESTARTS:  # (in place: a new process's budget is the coordinator's)
            limit = ending(decision, self.id, tau, error, in_place.budget)
            raise StopRun(str(limit), tau, raised=error, out_of_restarts=True) from exc
        if decision is Decision.RESTART and in_place is not None:
            self.notes.counts["restarts"] += 1
            self.flow = in_place.renew(self.flow, self.id)
            self.invoke = make_invoker(self.flow, self.spec)
        elif decision is Decision.RESTART:
            owner.restarting = True
            if owner.on_restart is not None:
                owner.on_restart(tau, error)

    def emit(self, tau, consumed, outputs, detail, start, wall, status) -> None:
        """Publish a step's outputs (or hold them, LET) and record it with ``status``: ``ok``,
        ``incomplete`` or ``overrun``, or ``late`` when it misses its LET deadline."""
        events = []  # (a loop, not a comprehension: one call less per tick)
        for port, value in outputs:  # None, or an empty burst: no event
            if value is not None and not (type(value) is Burst and not value.values):
                try:
                    make_read_only(value)  # an emitted value is immutable: consumers in this process share it
                except CodecError as e:  # it contains itself: it cannot be sent either (as Outputs.encode says)
                    raise StopRun(f"{self.id}.{port}: the step at {format_tag(tau)} returned a value the run cannot "
                                  f"send or record: {e}", tau) from None
                events.append((port, value))
        tag, batch, produced = self.outputs.stamp(tau, events)
        if self.outputs.latency_ns and not self.virtual:  # (in virtual time, LET outputs go at once: the tag says when)
            finished = start + wall - self.clock.t0
            if finished > tag[0]:  # the step outlasted its logical execution time
                self.missed_deadline(tau, consumed, batch, produced, detail, start, wall, finished - tag[0])
                return
            self.outputs.hold(batch)
            self.finish_tick(tau, consumed, produced, status, detail, start, wall)
            return
        self.finish_tick(tau, consumed, produced, status, detail, start, wall, publish=batch)

    def missed_deadline(self, tau, consumed, batch, produced, detail, start, wall, late_ns: int) -> None:
        """A LET step finished ``late_ns`` past t+latency: its outputs published late, or dropped
        (and the run stopped), as ``on_deadline_miss`` says (``error`` under realtime='hard')."""
        self.notes.counts["deadline_miss"] += 1
        stop = self.realtime == "hard" or self.on_deadline_miss == "error"
        # what was done with the outputs: published late, or dropped (and the run stopped)
        detail = {**(detail or {}), "deadline_miss_ns": late_ns,
                  "on_deadline_miss": "error" if stop else self.on_deadline_miss}
        if stop or self.on_deadline_miss == "drop":
            self.outputs.unnumber(batch)
            self.finish_tick(tau, consumed, (), StepStatus.LATE, detail, start, wall)
            if stop:
                hint = ("raise latency=, or run the pipeline with realtime='soft', where on_deadline_miss "
                        f"(now '{self.on_deadline_miss}') decides" if self.realtime == "hard" else
                        "raise latency=, or set on_deadline_miss='publish_late' or 'drop'")
                raise StopRun(f"{self.id} missed its LET deadline: the step at t={tau[0] / 1e9:.6f} s "
                              f"finished {late_ns / 1e6:.3f} ms after t+latency\n    hint: {hint}", tau)
            return
        self.outputs.release(start + wall - self.clock.t0)  # earlier ticks' held outputs go first
        self.finish_tick(tau, consumed, produced, StepStatus.LATE, detail, start, wall, publish=batch)

    def finish_tick(self, tau, consumed, produced, status, detail, start, wall, publish=()) -> None:
        outputs = self.outputs
        with self.lock:  # (one section: the tick done, and the frontier its outputs carry read)
            self.schedule.running = None
            if publish:
                outputs.sending = publish[0][0]
            frontier = outputs.frontier_held(sent=True) if publish or outputs.consumed else None
        outputs.publish(publish, frontier)  # first: the record is for the coordinator, and can wait
        self.reports.record(tau, consumed, produced, status, with_step_detail(self.flow, detail), start, wall)

    def source_stepped(self, tau, outputs: list, detail, start: int, wall: int) -> None:
        """A plain source's step returned ``outputs``: publish them and keep the record, as
        ``tick`` would, then handle an overrun."""
        overran = self.period_ns and wall > self.period_ns
        status = StepStatus.OVERRUN if overran else StepStatus.OK
        if outputs:
            self.emit(tau, {}, outputs, detail, start, wall, status)
        else:  # as emit with no event: no stamp, nothing to publish but progress
            self.finish_tick(tau, {}, (), status, detail, start, wall)
        if overran:
            self.overran(tau, wall, start + wall - self.clock.t0)

    def overran(self, tau: tuple[int, int], wall: int, done: int) -> None:
        """After a Rate tick's step outlasted the period: skip the ticks that came due meanwhile
        but the newest (on_overrun="skip"), run every one of them, late, in order
        (on_overrun="catch_up": none is lost, so a LET flow's trace stays the virtual-time one),
        or stop (on_overrun="error", realtime="hard")."""
        if self.on_overrun == "catch_up" and self.realtime != "hard":
            self.notes.counts["overrun"] += 1
            return
        missed = self.skip_missed_ticks(done, "overrun", "overrun_skipped")
        if missed and (self.realtime == "hard" or self.on_overrun == "error"):
            raise StopRun(f"{self.id} overran its period: the step at t={tau[0] / 1e9:.6f} s took "
                          f"{wall / 1e6:.3f} ms, {missed} tick(s) missed\n    hint: make step() faster, lower the "
                          f"rate, or set on_overrun='skip' (realtime='{self.realtime}')", tau)

    def skip_missed_ticks(self, now: int, counter: str, detail_key: str) -> int:
        """Skip the Rate ticks that came due before ``now`` but the newest, which runs next;
        count them under ``counter`` and tell the next record under ``detail_key``."""
        missed = self.schedule.skip_missed(now, self.clock.end)
        if missed:
            self.notes.counts[counter] += missed
            self.notes.detail[detail_key] = self.notes.detail.get(detail_key, 0) + missed
        return missed
