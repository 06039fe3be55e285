"""The re-simulation (``retriever replay --resim``): the whole graph re-run in virtual time, its
sources emitting their logged events, and the full trace compared with the log's."""

from __future__ import annotations

from dataclasses import dataclass, field

from ..backends.inproc import InprocSession
from ..errors import LogError, ReplayedError, StepError
from ..log import format as fmt
from ..log.reader import RunLog
from ..pipeline import Pipeline
from ..trace import StepRecord, StepStatus, Trace
from .prepare import code_changes, from_the_log, pipeline_for, set_up_flows


@dataclass
class ResimReport:
    horizon_ns: int
    steps_compared: int
    events_compared: int
    difference: str | None
    code_changes: list[str] = field(default_factory=list)  # flow modules whose file differs from the run's

    @property
    def identical(self) -> bool:
        return self.difference is None


def _logged_outputs(step: StepRecord, values: dict) -> list | ReplayedError:
    """What a replayed source's tick gives the re-simulation: its logged events, or its logged
    error (raised again, so that the tick is an error record, handled by ``on_error``, as in
    the run)."""
    if step.status == StepStatus.ERROR:
        error = (step.detail or {}).get("error")
        return ReplayedError(error if type(error) is str else "an error (the log does not say which)")
    return [(i[1], values[i]) for i in step.produced]


def resim(log: RunLog, pipeline: Pipeline | None = None) -> ResimReport:
    """Re-run the graph in virtual time from the logged source events; compare the trace."""
    if log.faults:  # the run lost state with a process: no re-run from the start can match it
        nodes = ", ".join(sorted({fault["node"] for fault in log.faults}))
        raise LogError(f"{log.path}: a process of the run died (of {nodes}), so its flow lost its state there: "
                       "--resim re-runs every flow from its start, which this run did not",
                       "retriever replay LOG (without --resim) follows the run through its restarts")
    pipeline = pipeline_for(log, pipeline)
    graph = pipeline.compile()
    changes = code_changes(log, graph)
    original = log.trace()
    end = log.end
    if end is not None and end.get("status") == fmt.RunEnd.FINISHED:
        horizon = int(end["end_ns"])
    else:  # a recovered or failed run: its last instant may be cut short, compare before it
        horizon = max((s.tag[0] for s in original.steps), default=0)

    session = InprocSession(graph)
    values = {e.id: e.value for e in original.events}
    logged = from_the_log(graph)
    for nid in logged:
        ticks = sorted((s for s in original.steps if s.node == nid and s.status != StepStatus.SKIPPED),
                       key=lambda s: s.tag)
        session.replace_step(nid, iter([_logged_outputs(s, values) for s in ticks]))
    try:
        set_up_flows(session, logged)
        session.advance(horizon)
    except StepError as e:
        if not isinstance(e.__cause__, ReplayedError):  # (a logged source's error stopped the run too)
            return ResimReport(horizon, 0, 0, f"the re-simulation stopped: {e}", changes)
    finally:
        session.close()
    kept_steps = [s for s in original.steps if s.tag[0] < horizon]
    kept_ids = {i for s in kept_steps for i in s.produced}
    expected = Trace([e for e in original.events if e.id in kept_ids], kept_steps)
    again = session.trace
    return ResimReport(horizon, len(kept_steps), len(expected.raw_events), expected.first_difference(again), changes)
