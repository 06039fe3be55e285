"""The short way for a plain source: a node on a Rate clock, in real time, with no inputs and
outputs not delayed (issue 21: an idle 100 Hz flow's CPU). Its idle passes of the loop skip what
only nodes with inputs or held outputs need; the ticks it runs are those ``Steps.tick`` would
run, with the same step call (tick.timed_step) and the same records."""

from __future__ import annotations

import time
from typing import Any

from ....flow._base import with_step_detail
from ....tick import timed_step
from ....trace import StepStatus
from .timing import WARM_AHEAD_NS


def is_plain_source(loop) -> bool:
    """Whether ``loop`` (a NodeLoop) may take the short way."""
    return (not loop.virtual and not loop.streams.edges and not loop.steps.inputs and not loop.steps.fallbacks
            and loop.node.clock.hz is not None and not loop.outputs.latency_ns and not loop.spin_ns)


def source_pass(loop, now: int) -> int | str | None:
    """``NodeLoop.try_tick`` for a plain source with nothing pending, held, queued or restarting:
    its next Rate tick, run as ``Steps.tick`` would (no inputs to select or wait for). None when
    the run is over; else the wall time to look again, or the result of ``loop.after_tick``."""
    schedule, steps = loop.schedule, loop.steps
    tau = schedule.next_rate
    if tau is None or tau[0] >= loop.run_clock.end:
        return loop.waiting.done_waiting(now)
    if tau[0] > now:
        return tau[0]
    schedule.take(tau)
    schedule.last_tick = tau
    detail: dict[str, Any] | None = loop.notes.detail or None
    loop.notes.detail = {}
    outputs, exc, start, end = timed_step(steps.invoke, steps.read, {})
    if exc is not None:
        steps.step_failed(tau, {}, detail, exc, start)
        return loop.after_tick()
    wall = loop.last_wall = end - start
    steps.source_stepped(tau, outputs, detail, start, wall)
    return loop.after_tick()


def quiet_source(loop) -> None:
    """Run a plain source's ticks for as long as they are quiet: nothing pending, held, queued or
    restarting, and steps that return no event, on time. Each such tick takes about as few
    operations as a hand-written loop that waits on an inbox (right after a wake-up the
    interpreter runs cold: every operation saved counts, benchmarks/reports/idle_cpu.md). A
    source that has published still warms up before each tick, as in the general loop.
    Anything else returns to the general loop: a message (handled first), a step's events,
    error or overrun (its tick finished first), a flush due, the end."""
    schedule, steps, reports, warmup = loop.schedule, loop.steps, loop.reports, loop.warmup
    lock, time_ns, t0, end = loop.lock, time.time_ns, loop.run_clock.t0, loop.run_clock.end
    invoke, read, tick_time, period, queued = (steps.invoke, steps.read, schedule.clock.tick_time, steps.period_ns,
                                               loop.inbox.qsize)
    while not (loop.stopping or loop.restarting or queued()):  # (what came during a step: handled first)
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
            if loop.outputs.warm_publish is not None:
                target, _ = warmup.target(tau[0] - wait, tau[0])
                warm_at = None if target is None else target - WARM_AHEAD_NS
            if loop.wait(wait if warm_at is None else warm_at - (tau[0] - wait)):
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
        outputs, exc, start, finished = timed_step(invoke, read, {})
        if exc is not None:
            steps.step_failed(tau, {}, None, exc, start)
            return
        wall = loop.last_wall = finished - start
        if outputs or (period and wall > period):  # (None, {}, an output object of Nones: quiet)
            steps.source_stepped(tau, outputs, None, start, wall)
            return
        with lock:
            schedule.running = None
        if loop.outputs.consumed:
            loop.outputs.publish(())  # the frontier, for its consumers
        reports.record(tau, {}, (), StepStatus.OK, with_step_detail(loop.flow, None), start, wall)
