"""node/steps.py: a node loop's failed step does what tick.decide says, as the in-process backend does;
and its tick takes its inputs and calls its step as the reference tick (tick.run_tick) does.

The Steps of a stand-in loop (only what a failed step touches: its records, its hooks to the
worker, its flags) take each kind of failure under each ``on_error``; what they do is checked
against the decision tick.decide takes for it. The restart budget is the coordinator's, so the
node itself never runs out of restarts: it asks for one; unless it restarts in place (a group's
member: node/in_place.py), with the budget its loop holds.
"""

from __future__ import annotations

import threading
from collections import Counter
from types import SimpleNamespace

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from retriever import Latest, Queue
from retriever.backends.base import NodeStats
from retriever.backends.zenoh.node import Ending
from retriever.backends.zenoh.node.in_place import InPlaceRestart
from retriever.backends.zenoh.node.steps import Steps
from retriever.errors import StopRun
from retriever.flow.core import Flow, PortSpec, flow_spec, set_up
from retriever.sync import PortBuffer
from retriever.tick import Decision, RestartBudget, decide, run_tick

TAU = (150_000_000, 0)


class Faulty(Flow):
    """The stand-in loop's flow: says nothing of its ticks (Flow.add_step_detail); counts its teardowns."""

    def __init__(self):
        self.torn_down = 0

    def step(self, x: int) -> int:
        return x

    def teardown(self) -> None:
        self.torn_down += 1


def stand_in_loop(on_error: str) -> SimpleNamespace:
    settings = SimpleNamespace(on_error=on_error, on_overrun="skip", on_deadline_miss="publish_late")
    flow = Faulty()
    loop = SimpleNamespace(
        id="faulty", virtual=False,
        node=SimpleNamespace(id="faulty", flow=flow, spec=flow_spec(Faulty), settings=settings,
                             clock=SimpleNamespace(hz=None)),
        notes=SimpleNamespace(detail={}, counts=Counter()), schedule=SimpleNamespace(running=TAU),
        outputs=SimpleNamespace(publish=lambda batch, frontier=None: None, consumed=False,
                                frontier_held=lambda sent=False: (0, 0)),
        reports=SimpleNamespace(records=[]),
        streams=None, run_clock=None, lock=threading.Lock(), last_wall=0,
        endings=[], restarting=False, exits=[], restarts=[], flow=flow, in_place=None)
    loop.stop = loop.endings.append
    loop.reports.record = lambda *record: loop.reports.records.append(record)
    loop.on_exit = loop.exits.append
    loop.on_restart = lambda tau, error: loop.restarts.append((tau, error))
    return loop


def steps_of(loop: SimpleNamespace, inputs: list[tuple], fallbacks: dict, invoke, read) -> Steps:
    """The stand-in loop's Steps, handed its parts as NodeLoop hands them."""
    return Steps(loop, loop.node, inputs, fallbacks, invoke, read, realtime="soft", virtual=loop.virtual,
                 notes=loop.notes, schedule=loop.schedule, outputs=loop.outputs, reports=loop.reports,
                 streams=loop.streams, clock=loop.run_clock, lock=loop.lock)


@pytest.mark.parametrize("on_error", ["stop", "skip_tick", "restart"])
@pytest.mark.parametrize("exc", [ValueError("bad"), SystemExit(3), SystemExit(0), SystemExit()],
                         ids=["ValueError", "exit-3", "exit-0", "exit"])
def test_a_failed_step_does_what_decide_says(on_error, exc):
    loop = stand_in_loop(on_error)
    steps = steps_of(loop, [], {}, None, None)
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
        assert loop.exits == [TAU] and loop.endings == [Ending.TOLD_TO_STOP]
    else:
        assert (status, detail) == ("error", {"error": error, "on_error": on_error})
        assert not loop.exits and not loop.endings
    assert loop.restarting is (decision is Decision.RESTART)
    assert loop.restarts == ([(TAU, error)] if decision is Decision.RESTART else [])


def test_a_flow_restarted_in_place_goes_on_fresh_within_its_budget_then_stops_the_run():
    """A group's member (in_place set): within the budget its loop holds, the old flow is torn
    down and a fresh one steps from then on, counted under ``restarts``, with no word to the
    coordinator; past the budget, a StopRun that says ``out_of_restarts`` with the
    RestartLimitError's text (the coordinator raises that error)."""
    loop = stand_in_loop("restart")
    made: list[Faulty] = []

    def fresh() -> Faulty:
        made.append(Faulty())
        set_up(made[-1])
        return made[-1]

    loop.in_place = InPlaceRestart(RestartBudget(1, 10.0), fresh)
    steps = steps_of(loop, [], {}, None, None)
    old = steps.flow
    set_up(old)
    steps.step_failed(TAU, {"x": ()}, None, ValueError("bad"), 0)
    assert steps.flow is made[0] is not old and old.torn_down == 1 and made[0].torn_down == 0
    assert steps.invoke({"x": 5}) == 5
    assert loop.notes.counts["restarts"] == 1
    assert not loop.restarting and loop.restarts == [] and loop.endings == []
    with pytest.raises(StopRun, match=r"^flow 'faulty' failed again after 1 restart\(s\) within 10 s "
                                      r"\(max_restarts=1, restart_window=10\): ValueError: worse \(tick at ") as info:
        steps.step_failed(TAU, {"x": ()}, None, ValueError("worse"), 0)
    assert info.value.out_of_restarts and info.value.raised == "ValueError: worse" and info.value.tag == TAU
    assert steps.flow is made[0] and len(made) == 1 and loop.notes.counts["restarts"] == 1
    assert [r[3:5] for r in loop.reports.records] == [
        ("error", {"error": "ValueError: bad", "on_error": "restart"}),
        ("error", {"error": "ValueError: worse", "on_error": "restart"})]


# ---------------------------------------------------------------------------------------------
# A node loop's tick against the reference tick (tick.run_tick), on random inputs
# ---------------------------------------------------------------------------------------------
POLICIES = {"latest": Latest, "queue": Queue, "queue-1": lambda: Queue(maxsize=1)}

# per input port: its policy, whether it is required, and the tags (ns) of the events it holds
ports = st.lists(st.tuples(st.sampled_from(sorted(POLICIES)), st.booleans(),
                           st.lists(st.integers(0, 300), max_size=4)), min_size=1, max_size=3)


def bound_inputs(spec: list) -> list[tuple]:
    """``(port, buffer, policy, port spec)`` per input, as plan.bind_inputs makes them."""
    inputs = []
    for i, (policy, required, times) in enumerate(spec):
        buf = PortBuffer()
        for seq, t in enumerate(sorted(times)):
            buf.insert(((t, 1), "src", f"x{i}", seq, f"v{i}.{seq}"))
        port_spec = PortSpec(f"x{i}") if required else PortSpec(f"x{i}", default="none")
        inputs.append((f"x{i}", buf, POLICIES[policy](), port_spec))
    return inputs


def buffers(inputs: list[tuple]) -> list[tuple]:
    return [(buf.entries, buf.visible, buf.cursor, buf.last_id) for _, buf, _, _ in inputs]


@settings(max_examples=80, deadline=None)
@given(ports, st.booleans())
def test_a_node_loops_tick_takes_its_inputs_and_steps_as_the_reference_tick_does(spec, raises):
    """The same inputs, fallbacks and step: the same outcome, the same values stepped on, the
    same events consumed (and the same left in the buffers), the same drops counted."""
    fallbacks = {"spare": PortSpec("spare", default=7)}

    def step(seen):
        def invoke(values):
            seen.append(dict(values))
            if raises:
                raise ValueError("bad")
            return {"y": len(values)}
        return invoke

    reference, seen_by_reference = [], []
    inputs = bound_inputs(spec)
    rt = SimpleNamespace(stats=NodeStats(), inputs=inputs, fallbacks=fallbacks, invoke=step(seen_by_reference),
                         read=lambda raw: raw.items())
    run_tick(rt, TAU, lambda rt, tau, missing: reference.append(("skipped", {}, {"missing": missing})),
             lambda rt, tau, consumed, exc, start, wall: reference.append(("error", consumed, None)),
             lambda rt, tau, outputs, consumed, start, end, dropped: reference.append(("ok", consumed, dropped)))

    loop = stand_in_loop("skip_tick")
    loop.outputs.latency_ns = 0
    loop.outputs.stamp = lambda tau, events: ((tau[0], tau[1] + 1), events, tuple(port for port, _ in events))
    seen_by_loop = []
    loop_inputs = bound_inputs(spec)
    steps_of(loop, loop_inputs, fallbacks, step(seen_by_loop), lambda raw: raw.items()).tick(TAU, [])

    (tau, consumed, produced, status, detail, *_), = loop.reports.records
    (ref_status, ref_consumed, ref_detail), = reference
    assert (status, consumed, seen_by_loop) == (ref_status, ref_consumed, seen_by_reference)
    assert buffers(loop_inputs) == buffers(inputs)
    if status == "ok":
        assert detail == ref_detail and produced == ("y",)
    elif status == "skipped":  # (the loop's record also counts what the policies would have dropped)
        assert detail["missing"] == ref_detail["missing"]
