"""The reference tick: what one tick of one node at tag ``τ`` does, on every backend
(docs/semantics.md, Sync policies and Errors).

    select_inputs(τ) ──▶ a required port MISSING? ──yes──▶ skipped (nothing consumed)
          │ no
          ▼
    commit what the policies took; fallbacks for the optional ports nothing feeds
          ▼
    step (timed) ──returned──▶ ok: the outputs, to record and deliver
          │ raised
          ▼
    decide(on_error) ──▶ SKIP · STOP · RESTART · OUT_OF_RESTARTS · END_RUN

:func:`run_tick` is that tick, which the in-process backend runs for every node whose tick it
does not generate; its generated ticks (``backends/inproc_ticks.py``) are the fast path, held
to the same trace on random graphs (tests/backends/test_inproc_ticks.py). The zenoh node loop
runs the same tick from the same two parts, :func:`take_inputs` (select, commit, fallbacks) and
:func:`timed_step`, with the accounts of a real-time node around them; a quiet Rate source
there runs its ticks in a loop of its own while nothing else is due (node/source.py,
``PlainSource.run_quiet``: a tick with no inputs, no events and no error, held to the general
loop's records by tests/backends/zenoh/test_realtime_semantics.py and test_warmup.py).
:func:`select_inputs` is the one place inputs are selected; :func:`decide` the one decision on a
step that raised (its restart, :func:`take_restart`, is also the coordinator's, which holds a
real-time flow's budget; a flow that restarts in place, a group's member, has its loop hold it:
backends/zenoh/node/in_place.py). Elsewhere ``on_error`` is read only for what a restart needs before any
step raised: a process of its own (coordinator/spec.py; dora refuses it), and a flow whose process
died started afresh (coordinator/processes.py). A value the codec cannot encode stops the run
whatever ``on_error`` says: it is no error of the step, but an output the run cannot carry.
:func:`skipped_outcome`, :func:`exit_outcome` and :func:`error_outcome` are the one place the step
record of a tick that did not end ``ok`` with outputs is made. Recording and delivering a tick's
outputs is each backend's own: it knows where they go.
"""

from __future__ import annotations

import enum
from collections import deque
from collections.abc import Callable
from time import time_ns
from typing import Any

from .errors import ReplayedError, RestartLimitError, RetrieverError, RunEnded, StepError
from .sync import MISSING
from .trace import StepStatus


def select_inputs(inputs: list[tuple], tau: tuple[int, int]) -> tuple[dict, dict, list | None, list | None, dict | None]:
    """One tick's input snapshot at ``tau``: each ``(port, buffer, policy, port spec)`` selects.

    Returns ``(values, consumed, missing, commits, dropped)``: the step's arguments (a MISSING
    optional port gets its fallback), the consumed event ids per port, the required ports that
    were MISSING (None if none: then the tick runs), the ``(policy, buffer, commit)`` to apply
    if it does, and the Queue drop counts per port (None if none).
    """
    values: dict[str, Any] = {}
    consumed: dict[str, tuple] = {}
    missing: list[str] | None = None
    commits: list | None = None
    dropped: dict[str, int] | None = None
    for port, buf, policy, spec in inputs:
        value, ids, n_dropped, commit = policy.select(buf, tau)
        if value is MISSING:
            if spec.required:
                (missing := missing or []).append(port)
            else:
                values[port] = spec.fallback()
            continue
        values[port] = value
        consumed[port] = ids
        if commit is not None:
            (commits := commits or []).append((policy, buf, commit))
        if n_dropped:
            (dropped := dropped or {})[port] = n_dropped
    return values, consumed, missing, commits, dropped


def take_inputs(inputs: list[tuple], fallbacks: dict,
                tau: tuple[int, int]) -> tuple[dict, dict, list | None, dict | None]:
    """The inputs of the tick at ``tau`` (:func:`select_inputs` on ``inputs``), taken: unless a
    required port is MISSING, what the policies selected is committed (consumed) and every port
    in ``fallbacks`` (optional, fed by nothing) gets its fallback. Returns ``(values, consumed,
    missing, dropped)``: with ``missing`` not None the tick is skipped, and nothing was consumed."""
    values, consumed, missing, commits, dropped = select_inputs(inputs, tau)
    if missing is not None:
        return values, consumed, missing, dropped
    if commits is not None:
        for policy, buf, commit in commits:
            policy.commit_to(buf, commit)
    if fallbacks:
        for port, spec in fallbacks.items():
            values[port] = spec.fallback()
    return values, consumed, None, dropped


def timed_step(invoke: Callable, read: Callable, values: dict) -> tuple[Any, BaseException | None, int, int]:
    """Call the step (``read(invoke(values))``) between two clock readings: ``(outputs, None,
    start, end)``, or ``(None, exc, start, end)`` if it raised ``exc``. Anything a step raises is
    its error, SystemExit included (``sys.exit()`` in a step is that step's: :func:`decide`), but a
    KeyboardInterrupt, which is the user's: it propagates."""
    start = time_ns()
    try:
        outputs = read(invoke(values))
    except KeyboardInterrupt:
        raise
    except BaseException as exc:
        return None, exc, start, time_ns()
    return outputs, None, start, time_ns()


def run_tick(node: Any, tau: tuple[int, int], skipped: Callable, failed: Callable, emit: Callable) -> None:
    """One tick of ``node`` at ``tau``, the reference (module docstring). ``node`` has ``stats``
    (NodeStats), ``inputs`` (plan.bind_inputs), ``fallbacks``, ``invoke`` and ``read``
    (flow.core.make_invoker, make_output_reader); what became of the tick goes to one of:
    ``skipped(node, tau, missing)``, ``failed(node, tau, consumed, exc, start, wall)`` (the
    backend records it, then acts on :func:`decide`), ``emit(node, tau, outputs, consumed,
    start, end, dropped)``. A KeyboardInterrupt in the step is not the step's: it propagates.
    A backend that keeps other accounts of a tick (the zenoh node loop: backends/zenoh/node/steps.py)
    runs the same tick from :func:`take_inputs` and :func:`timed_step`."""
    stats = node.stats
    stats.ticks += 1
    values, consumed, missing, dropped = take_inputs(node.inputs, node.fallbacks, tau)
    if missing is not None:
        skipped(node, tau, missing)
        return
    outputs, exc, start, end = timed_step(node.invoke, node.read, values)
    stats.step_ns += end - start
    if exc is not None:
        failed(node, tau, consumed, exc, start, end - start)
        return
    stats.steps += 1
    emit(node, tau, outputs, consumed, start, end, dropped)


# ---------------------------------------------------------------------------------------------
# A step that raised: the one on_error decision
# ---------------------------------------------------------------------------------------------
class Decision(enum.Enum):
    """What a run does after a step raised (docs/semantics.md, Errors)."""

    SKIP = "skip_tick"  # the tick made no outputs; the run goes on
    STOP = "stop"  # the run stops: StepError
    RESTART = "restart"  # the flow starts afresh (reset, or a new process) and the run goes on
    OUT_OF_RESTARTS = "out_of_restarts"  # a restart past the budget: the run stops, RestartLimitError
    END_RUN = "end_run"  # sys.exit() or sys.exit(0) in the step: the whole run ends here, cleanly


class RestartBudget:
    """The restarts of one flow with on_error="restart", by run time: at most ``max_restarts``
    within any ``restart_window`` seconds (FlowSettings); the same rule on every backend."""

    def __init__(self, max_restarts: int, window_s: float):
        self.max_restarts, self.window_s = max_restarts, window_s
        self.window_ns = round(window_s * 1e9)
        self.times: deque[int] = deque()

    def take(self, t_ns: int) -> bool:
        """Count a restart at run time ``t_ns``; False, counting nothing, if the budget is spent."""
        while self.times and self.times[0] <= t_ns - self.window_ns:
            self.times.popleft()
        if len(self.times) >= self.max_restarts:
            return False
        self.times.append(t_ns)
        return True


def decide(on_error: str, exc: BaseException | str, budget: RestartBudget | None, t_ns: int) -> Decision:
    """What to do after a step raised ``exc`` at run time ``t_ns`` (a process that died: a text
    saying how), for a flow whose ``on_error`` is ``stop``, ``skip_tick`` or ``restart``. A restart
    is taken from ``budget``; with None, whoever holds the budget decides on it later (a real-time
    node asks its coordinator, which calls this with the budget)."""
    if isinstance(exc, SystemExit) and exc.code in (None, 0):
        return Decision.END_RUN
    if on_error == "stop":
        return Decision.STOP
    if on_error == "restart":
        return Decision.RESTART if budget is None else take_restart(budget, t_ns)
    return Decision.SKIP


def take_restart(budget: RestartBudget, t_ns: int) -> Decision:
    """:func:`decide` for a flow with ``on_error="restart"``, by the holder of its ``budget``, at
    run time ``t_ns``: RESTART, taken from the budget, or OUT_OF_RESTARTS. The zenoh coordinator
    decides so on a restart its node asked for (the node decided RESTART, with no budget) and on a
    dead process of a restarting flow: neither is a step's SystemExit, which ends the run instead."""
    return Decision.RESTART if budget.take(t_ns) else Decision.OUT_OF_RESTARTS


def error_text(exc: BaseException) -> str:
    """How a step record names the error a step raised (a replayed one: as it was logged)."""
    return exc.error if type(exc) is ReplayedError else f"{type(exc).__name__}: {exc}"


def ending(decision: Decision, node: str, tau: tuple[int, int] | None, exc: BaseException | str,
           budget: RestartBudget | None = None) -> RetrieverError | None:
    """The exception that ends the run after ``decision`` (None: the run goes on): StepError,
    RestartLimitError (``budget``: the spent one) or RunEnded."""
    if decision is Decision.STOP:
        return StepError(node, tau, exc)
    if decision is Decision.OUT_OF_RESTARTS:
        return RestartLimitError(node, tau, exc, budget.max_restarts, budget.window_s)
    if decision is Decision.END_RUN:
        return RunEnded(node, tau)
    return None


# ---------------------------------------------------------------------------------------------
# What became of a tick that made no outputs: its step record's status and detail
# ---------------------------------------------------------------------------------------------
# Each takes ``detail``, what a backend noted of the tick besides (a real-time node: incomplete
# edges, Queue drops), and returns ``(status, detail)`` for the step record. The keys are read
# back by the coordinator (an ``exit`` status is believed only beside its ``{"exit": 0}`` record)
# and by replay (a skipped tick re-runs only with its ``missing`` ports): one spelling for both.
def skipped_outcome(missing: list[str], detail: dict | None = None) -> tuple[StepStatus, dict]:
    """A tick skipped because the required ports ``missing`` had nothing (nothing consumed)."""
    return StepStatus.SKIPPED, {**detail, "missing": missing} if detail else {"missing": missing}


def exit_outcome(detail: dict | None = None) -> tuple[StepStatus, dict]:
    """A step that called ``sys.exit()`` or ``sys.exit(0)`` (Decision.END_RUN): the run ends
    cleanly at it, and it counts as a step that ran."""
    return StepStatus.OK, {**detail, "exit": 0} if detail else {"exit": 0}


def error_outcome(error: str, on_error: str, detail: dict | None = None) -> tuple[StepStatus, dict]:
    """A step that raised (``error``: :func:`error_text`), and the ``on_error`` acted on."""
    outcome = {"error": error, "on_error": on_error}
    return StepStatus.ERROR, {**detail, **outcome} if detail else outcome
