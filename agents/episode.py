"""What an episode of Retriever-0 did, read back from its trace or its log: the skill trace, the
task-progress score and when it was reached, replans, and how each flow kept its clock."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from retriever import NOT_KEPT, StepStatus


@dataclass
class FlowRate:
    node: str
    hz: float | None                 # its Rate, None for a triggered flow
    steps: int
    achieved_hz: float               # real time: steps per wall second, first to last; virtual: per world second
    late_p99_ms: float | None        # real time only: how late its ticks started, 99th percentile
    behind: int = 0                  # real time only: ticks that started more than one period late
    missed: int = 0                  # steps a real-time run marked late (LET deadline), overrun or incomplete


@dataclass
class Episode:
    skills: list[str]                # the skills handed off, in order, then the one running at the end
    score: float
    best_at: float                   # world seconds when the score last rose
    milestones: dict
    finished: bool
    replans: int
    failures: int
    duration: float                  # world seconds covered
    gave_up: str = ""                # why the monitor gave the task up, if it did
    ignored: dict = field(default_factory=dict)    # stale_feedback, stale_plans, bad_plans: what the monitor ignored
    statuses: list = field(default_factory=list)   # (t, MonitorStatus) at every monitor tick
    rates: list[FlowRate] = field(default_factory=list)

    @property
    def skill_trace(self) -> str:
        return " → ".join(self.skills)


def summarize(trace, ir=None) -> Episode:
    """The episode a trace shows (its monitor's statuses must be kept: ``keep="trace"``)."""
    statuses = [(e.value.t, e.value) for e in trace.events_of("monitor", "status") if e.value is not NOT_KEPT]
    if not statuses:
        return Episode([], 0.0, 0.0, {}, False, 0, 0, 0.0, "", {}, [], _rates(trace, ir, 0.0))
    last = statuses[-1][1]
    skills = list(last.executed) + ([last.skill] if last.skill else [])
    best_at = next((t for t, s in statuses if s.score >= last.score), 0.0) if last.score > 0 else 0.0
    duration = statuses[-1][0]
    ignored = {k: getattr(last, k) for k in ("stale_feedback", "stale_plans", "bad_plans")}
    return Episode(skills, last.score, best_at, dict(last.milestones), last.finished, last.replans, last.failures,
                   duration, last.gave_up, ignored, statuses, _rates(trace, ir, duration))


def _wall_t0(trace) -> int | None:
    """Real time: the wall-clock ns of world time 0 (None for a virtual-time trace). A tick never
    starts before T0 + its tag, so the smallest start − tag is T0, to within the quickest tick's
    reaction: lateness is measured from there."""
    offsets = [s.wall_start_ns - s.tag[0] for s in trace.steps if s.wall_start_ns]
    return min(offsets) if offsets and trace.steps[0].wall_start_ns > 1e17 else None


def lateness(trace) -> dict[str, tuple[list[float], list[float]]]:
    """Real time: per flow, the world time (s) of each tick that ran and how late it started (ms
    after T0 + its tag); empty for a virtual-time trace, whose ticks are never late."""
    t0 = _wall_t0(trace)
    late: dict[str, tuple[list[float], list[float]]] = {}
    if t0 is None:
        return late
    for s in trace.steps:
        if s.status != StepStatus.SKIPPED and s.wall_start_ns:
            times, ms = late.setdefault(s.node, ([], []))
            times.append(s.tag[0] / 1e9)
            ms.append((s.wall_start_ns - s.tag[0] - t0) / 1e6)
    return late


def _rates(trace, ir, duration: float) -> list[FlowRate]:
    clocks = {}
    if ir is not None:
        for node in ir.doc["nodes"]:
            clock = node.get("config", {}).get("clock", {})
            spec = clock.get("Rate") or clock.get("Hybrid") or {}
            clocks[node["id"]] = spec.get("hz")
    by_node: dict[str, list] = {}
    for step in trace.steps:
        by_node.setdefault(step.node, []).append(step)
    t0, late_ms = _wall_t0(trace), lateness(trace)
    rates = []
    for node, steps in sorted(by_node.items()):
        ran = [s for s in steps if s.status != StepStatus.SKIPPED]
        hz = clocks.get(node)
        late = late_ms.get(node, ([], []))[1]
        starts = sorted(s.wall_start_ns for s in steps if s.wall_start_ns)
        if t0 is not None and len(starts) > 1 and starts[-1] > starts[0]:
            # ticks (a skipped one ticked too: its inputs had nothing yet) per wall second: a flow
            # that fell behind its clock stretched its ticks over more wall time than world time
            achieved = (len(starts) - 1) / ((starts[-1] - starts[0]) / 1e9)
        else:
            achieved = len(steps) / duration if duration else 0.0
        rates.append(FlowRate(node, hz, len(ran), achieved, float(np.percentile(late, 99)) if late else None,
                              behind=sum(x > 1e3 / hz for x in late) if hz else 0,
                              missed=sum(s.status in (StepStatus.LATE, StepStatus.OVERRUN, StepStatus.INCOMPLETE)
                                         for s in steps)))
    return rates
