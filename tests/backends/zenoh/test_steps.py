"""node/steps.py: a node loop's failed step does what tick.decide says, as the in-process backend does.

The Steps of a stand-in loop (only what a failed step touches: its records, its hooks to the
worker, its flags) take each kind of failure under each ``on_error``; what they do is checked
against the decision tick.decide takes for it. The restart budget is the coordinator's, so the
node itself never runs out of restarts: it asks for one.
"""

from __future__ import annotations

import threading
from types import SimpleNamespace

import pytest

from retriever.backends.zenoh.node.steps import Steps
from retriever.errors import StopRun
from retriever.tick import Decision, decide

TAU = (150_000_000, 0)


def stand_in_loop(on_error: str) -> SimpleNamespace:
    settings = SimpleNamespace(on_error=on_error, on_overrun="skip", on_deadline_miss="publish_late")
    loop = SimpleNamespace(
        id="faulty", virtual=False, node=SimpleNamespace(settings=settings, clock=SimpleNamespace(hz=None)),
        notes=SimpleNamespace(detail={}), schedule=SimpleNamespace(running=TAU),
        outputs=SimpleNamespace(publish=lambda batch: None), reports=SimpleNamespace(records=[]),
        streams=None, run_clock=None, lock=threading.Lock(), last_wall=0,
        stopping=False, told_to_stop=False, restarting=False, exits=[], restarts=[])
    loop.reports.record = lambda *record: loop.reports.records.append(record)
    loop.on_exit = loop.exits.append
    loop.on_restart = lambda tau, error: loop.restarts.append((tau, error))
    return loop


@pytest.mark.parametrize("on_error", ["stop", "skip_tick", "restart"])
@pytest.mark.parametrize("exc", [ValueError("bad"), SystemExit(3), SystemExit(0), SystemExit()],
                         ids=["ValueError", "exit-3", "exit-0", "exit"])
def test_a_failed_step_does_what_decide_says(on_error, exc):
    loop = stand_in_loop(on_error)
    steps = Steps(loop, [], {}, None, None, realtime="soft")
    decision = decide(on_error, exc, None, TAU[0])
    if decision is Decision.STOP:
        with pytest.raises(StopRun, match=f"faulty.step\\(\\) raised {type(exc).__name__}") as info:
            steps.step_failed(TAU, {"x": ()}, None, exc, 0)
        assert info.value.tag == TAU and info.value.__cause__ is exc
    else:
        steps.step_failed(TAU, {"x": ()}, None, exc, 0)
    (tau, consumed, produced, status, detail, *_), = loop.reports.records
    assert (tau, consumed, produced, loop.schedule.running) == (TAU, {"x": ()}, (), None)
    error = f"{type(exc).__name__}: {exc}"
    if decision is Decision.END_RUN:
        assert (status, detail) == ("ok", {"exit": 0})
        assert loop.exits == [TAU] and loop.stopping and loop.told_to_stop
    else:
        assert (status, detail) == ("error", {"error": error, "on_error": on_error})
        assert not loop.exits and not loop.stopping
    assert loop.restarting is (decision is Decision.RESTART)
    assert loop.restarts == ([(TAU, error)] if decision is Decision.RESTART else [])
