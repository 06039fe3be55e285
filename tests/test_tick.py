"""retriever.tick: the reference tick's selection and the one on_error decision."""

from __future__ import annotations

from types import SimpleNamespace

import pytest

from retriever import Latest, Queue, RestartLimitError, StepError
from retriever.backends.base import NodeStats
from retriever.errors import ReplayedError, RunEnded
from retriever.flow.core import PortSpec
from retriever.sync import PortBuffer
from retriever.tick import (Decision, RestartBudget, decide, ending, error_text, run_tick, select_inputs, take_inputs,
                            take_restart, timed_step)


def buffer(*values) -> PortBuffer:
    buf = PortBuffer()
    for seq, value in enumerate(values):
        buf.insert(((seq * 10, 1), "src", "x", seq, value))
    return buf


def node(inputs, fallbacks=None, step=lambda values: values):
    return SimpleNamespace(stats=NodeStats(), inputs=inputs, fallbacks=fallbacks or {}, invoke=step,
                           read=lambda raw: raw)


def test_a_skipped_tick_consumes_nothing_and_a_tick_that_runs_commits():
    queue = buffer("a", "b")
    inputs = [("q", queue, Queue(), PortSpec("q")), ("need", PortBuffer(), Queue(), PortSpec("need"))]
    values, consumed, missing, commits, dropped = select_inputs(inputs, (100, 0))
    assert values["q"] == ["a", "b"] and missing is None and commits and dropped is None

    inputs[1] = ("need", PortBuffer(), Latest(), PortSpec("need"))
    outcome = []
    rt = node(inputs, {"spare": PortSpec("spare", default=3)})
    run_tick(rt, (100, 0), lambda *a: outcome.append(("skipped", a[2])), None, None)
    assert outcome == [("skipped", ["need"])] and queue.cursor == 0 and rt.stats.ticks == 1

    inputs[1] = ("need", buffer("n"), Latest(), PortSpec("need"))
    run_tick(rt, (100, 0), None, None, lambda rt, tau, outputs, *rest: outcome.append(("ok", outputs)))
    assert outcome[-1] == ("ok", {"q": ["a", "b"], "need": "n", "spare": 3}) and queue.cursor == 2
    assert (rt.stats.ticks, rt.stats.steps) == (2, 1)


def test_a_step_that_raises_goes_to_failed_with_what_it_consumed():
    def step(values):
        raise ValueError("bad")

    failed = []
    rt = node([("x", buffer(1), Queue(), PortSpec("x"))], step=step)
    run_tick(rt, (50, 0), None, lambda rt, tau, consumed, exc, start, wall: failed.append((consumed, exc)), None)
    (consumed, exc), = failed
    assert consumed == {"x": (("src", "x", 0),)} and type(exc) is ValueError and rt.stats.steps == 0


@pytest.mark.parametrize("on_error", ["stop", "skip_tick", "restart"])
def test_sys_exit_0_ends_the_run_whatever_on_error_says(on_error):
    assert decide(on_error, SystemExit(0), None, 0) is Decision.END_RUN
    assert decide(on_error, SystemExit(), None, 0) is Decision.END_RUN
    assert decide(on_error, SystemExit(1), None, 0) is not Decision.END_RUN


def test_on_error_decides_skip_stop_or_restart():
    assert decide("skip_tick", ValueError(), None, 0) is Decision.SKIP
    assert decide("stop", ValueError(), None, 0) is Decision.STOP
    assert decide("restart", ValueError(), None, 0) is Decision.RESTART  # the budget's holder decides later


def test_restarts_past_the_budget_within_its_window_stop_the_run():
    budget = RestartBudget(2, 1.0)
    decisions = [decide("restart", "its process died", budget, t) for t in (0, 400_000_000, 900_000_000)]
    assert decisions == [Decision.RESTART, Decision.RESTART, Decision.OUT_OF_RESTARTS]
    assert decide("restart", ValueError(), budget, 1_000_000_000) is Decision.RESTART  # the first left the window


def test_the_coordinators_restart_decides_as_decide_does_on_the_same_budget():
    """take_restart (a restart the node asked for, a restarting flow's dead process) decides as
    decide("restart", ...) with the budget, and takes from the same budget."""
    times = (0, 400_000_000, 900_000_000, 1_000_000_000)
    by_decide, by_take = RestartBudget(2, 1.0), RestartBudget(2, 1.0)
    assert [take_restart(by_take, t) for t in times] == [decide("restart", "died", by_decide, t) for t in times] == [
        Decision.RESTART, Decision.RESTART, Decision.OUT_OF_RESTARTS, Decision.RESTART]
    shared = RestartBudget(1, 1.0)
    assert take_restart(shared, 0) is Decision.RESTART
    assert decide("restart", ValueError(), shared, 1) is Decision.OUT_OF_RESTARTS


def test_the_decisions_that_end_a_run_say_why():
    exc = ValueError("bad")
    assert type(ending(Decision.STOP, "n", (5, 0), exc)) is StepError
    limit = ending(Decision.OUT_OF_RESTARTS, "n", (5, 0), exc, RestartBudget(3, 2.0))
    assert type(limit) is RestartLimitError and "after 3 restart(s) within 2 s" in str(limit)
    assert type(ending(Decision.END_RUN, "n", (5, 0), exc)) is RunEnded
    assert ending(Decision.SKIP, "n", (5, 0), exc) is None and ending(Decision.RESTART, "n", (5, 0), exc) is None


def test_a_replayed_error_is_named_as_it_was_logged():
    assert error_text(ReplayedError("KeyError: 'k'")) == "KeyError: 'k'"
    assert error_text(ValueError("bad")) == "ValueError: bad"


def test_the_timed_step_returns_what_the_step_raised_but_a_keyboard_interrupt():
    def raising(exc):
        def invoke(values):
            raise exc
        return invoke

    outputs, exc, start, end = timed_step(lambda values: values["x"] * 2, lambda raw: [("y", raw)], {"x": 4})
    assert outputs == [("y", 8)] and exc is None and start <= end
    for error in (ValueError("bad"), SystemExit(0), SystemExit(3)):
        outputs, exc, start, end = timed_step(raising(error), lambda raw: raw, {})
        assert outputs is None and exc is error and start <= end
    with pytest.raises(KeyboardInterrupt):
        timed_step(raising(KeyboardInterrupt()), lambda raw: raw, {})


def test_taking_the_inputs_of_a_skipped_tick_consumes_nothing_and_adds_no_fallback():
    queue = buffer("a", "b", "c")
    inputs = [("q", queue, Queue(maxsize=1), PortSpec("q")), ("need", PortBuffer(), Latest(), PortSpec("need"))]
    fallbacks = {"spare": PortSpec("spare", default=3)}
    values, consumed, missing, dropped = take_inputs(inputs, fallbacks, (100, 0))
    assert missing == ["need"] and "spare" not in values and queue.cursor == 0

    inputs[1] = ("need", buffer("n"), Latest(), PortSpec("need"))
    values, consumed, missing, dropped = take_inputs(inputs, fallbacks, (100, 0))
    assert values == {"q": ["c"], "need": "n", "spare": 3} and missing is None
    assert dropped == {"q": 2} and queue.cursor == 3 and consumed["need"] == (("src", "x", 0),)
