"""The short way for a plain source: a node on a Rate clock, in real time, with no inputs and
outputs not delayed (issue 21: an idle 100 Hz flow's CPU). Its idle passes of the loop skip what
only nodes with inputs or held outputs need; the ticks it runs are those ``Steps.tick`` would
run, with the same step call (tick.timed_step) and the same records."""

from __future__ import annotations

import queue
import threading
import time
from typing import Any, Protocol

from ....flow.core import with_step_detail
from ....tick import timed_step
from ....trace import StepStatus
from .clock import RunClock
from .notes import Notes
from .outputs import Outputs
from .reports import Reports
from .schedule import Schedule
from .steps import Steps
from .timing import WARM_AHEAD_NS, Warmup
from .waiting import Waiting


class SourceOwner(Protocol):
    """What :class:`PlainSource` reads and sets of the loop it serves (a NodeLoop), as it changes."""

    #: what a message comes into (read on each pass: a group gives its loops inboxes of their own)
    inbox: queue.SimpleQueue
    #: whether the loop was told to end, or its flow is being restarted: the quiet ticks stop
    stopping: bool
    restarting: bool
    #: how long the last step took (set here, as Steps sets it)
    last_wall: int | None

    def wait(self, ns: int) -> bool:
        """Wait up to ``ns`` for a message and handle it; whether one came."""

    def after_tick(self) -> int | str:
        """Right after a tick: look again at once, or when."""


class PlainSource:
    """The short way of a plain source's loop, over the loop's parts: its ticks run by ``steps``
    (its step call, a failure, an overrun), recorded in ``reports``, paced by ``warmup``;
    ``owner`` is the loop's state it reads and changes (:class:`SourceOwner`)."""

    def __init__(self, owner: SourceOwner, *, steps: Steps, waiting: Waiting, schedule: Schedule, notes: Notes,
                 outputs: Outputs, reports: Reports, warmup: Warmup, clock: RunClock, lock: threading.Lock):
        self.owner, self.steps, self.waiting, self.schedule, self.notes = owner, steps, waiting, schedule, notes
        self.outputs, self.reports, self.warmup, self.clock, self.lock = outputs, reports, warmup, clock, lock

    def fits(self, *, virtual: bool, edges: list, spin_ns: int) -> bool:
        """Whether the node may take the short way (``edges``: its input edges)."""
        steps = self.steps
        return (not virtual and not edges and not steps.inputs and not steps.fallbacks
                and self.schedule.clock.hz is not None and not self.outputs.latency_ns and not spin_ns)

    def one_pass(self, now: int) -> int | str | None:
        """``NodeLoop.try_tick`` for a plain source with nothing pending, held, queued or
        restarting: its next Rate tick, run as ``Steps.tick`` would (no inputs to select or wait
        for). None when the run is over; else the wall time to look again, or the result of the
        owner's ``after_tick``."""
        schedule, steps, notes = self.schedule, self.steps, self.notes
        tau = schedule.next_rate
        if tau is None or tau[0] >= self.clock.end:
            return self.waiting.done_waiting(now)
        if tau[0] > now:
            return tau[0]
        schedule.take(tau)
        schedule.last_tick = tau
        detail: dict[str, Any] | None = notes.detail or None
        notes.detail = {}
        outputs, exc, start, end = timed_step(steps.invoke, steps.read, {})
        if exc is not None:
            steps.step_failed(tau, {}, detail, exc, start)
            return self.owner.after_tick()
        wall = self.owner.last_wall = end - start
        steps.source_stepped(tau, outputs, detail, start, wall)
        return self.owner.after_tick()

    def run_quiet(self) -> None:
        """Run the source's ticks for as long as they are quiet: nothing pending, held, queued or
        restarting, and steps that return no event, on time. Each such tick takes about as few
        operations as a hand-written loop that waits on an inbox (right after a wake-up the
        interpreter runs cold: every operation saved counts, benchmarks/reports/idle_cpu.md). A
        source that has published still warms up before each tick, as in the general loop.
        Anything else returns to the general loop: a message (handled first), a step's events,
        error or overrun (its tick finished first), a flush due, the end."""
        owner, schedule, steps, reports, warmup, outputs = (self.owner, self.schedule, self.steps, self.reports,
                                                            self.warmup, self.outputs)
        lock, time_ns, t0, end = self.lock, time.time_ns, self.clock.t0, self.clock.end
        invoke, read, tick_time, period, queued = (steps.invoke, steps.read, schedule.clock.tick_time, steps.period_ns,
                                                   owner.inbox.qsize)
        flow = steps.flow
        while not (owner.stopping or owner.restarting or queued()):  # (what came during a step: handled first)
            tau = schedule.next_rate
            if tau is None or tau[0] >= end:
                return
            wait = tau[0] - (time_ns() - t0)
            if wait > 0:
                if reports.flush_due is not None and reports.flush_due <= tau[0]:
                    return  # the general loop flushes before it waits
                # a node with consumers that has published warms up just before the tick, by the
                # general loop's rule (Warmup.target; a source has no arrivals to warm for)
                warm_at = None
                if outputs.warm_publish is not None:
                    target, _ = warmup.target(tau[0] - wait, tau[0])
                    warm_at = None if target is None else target - WARM_AHEAD_NS
                if owner.wait(wait if warm_at is None else warm_at - (tau[0] - wait)):
                    return  # a message came, and was handled
                if warm_at is not None and time_ns() - t0 >= warm_at:
                    warmup.warm(None)
                    warmup.warmed_for = tau[0]
                continue
            with lock:
                schedule.running = tau
                schedule.k = k = schedule.k + 1
                schedule.next_rate = (tick_time(k), 0)
            schedule.last_tick = tau
            values, exc, start, finished = timed_step(invoke, read, {})
            if exc is not None:
                steps.step_failed(tau, {}, None, exc, start)
                return
            wall = owner.last_wall = finished - start
            if values or (period and wall > period):  # (None, {}, an output object of Nones: quiet)
                steps.source_stepped(tau, values, None, start, wall)
                return
            with lock:
                schedule.running = None
            if outputs.consumed:
                outputs.publish(())  # the frontier, for its consumers
            reports.record(tau, {}, (), StepStatus.OK, with_step_detail(flow, None), start, wall)
