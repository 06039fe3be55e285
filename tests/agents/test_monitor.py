"""The execution monitor's rules (paper Appendix E-c..f, E-o), table-driven.

Each scenario is a table of monitor ticks: at time ``t`` these inputs arrived, so the tick must
start this skill (or none) and ask for a plan for this reason (or not). Rows are applied in
order to one monitor, exactly as the Monitor flow feeds it.
"""

import pytest

from agents.monitor import ExecutionMonitor, MonitorConfig, plan_ends
from agents.plan import parse_program

SEARCH_TL = ["OpenDrawer(TL-H) -> InspectDrawer(TL)",
             "IF at(spice, TL) = yes THEN Pick(spice) -> Season(food) -> CloseDrawer(TL-H) -> Done() "
             "ELSE CloseDrawer(TL-H)"]


def run_table(rows, config=None, monitor=None):
    """Apply rows ``(t, inputs, command, request)``; ``inputs`` may hold task, belief=(version,
    predicates), plan=(request_id, lines), failure=(request_id, error), progress=[(skill_id, p,
    status)], teleop=skill."""
    m = monitor or ExecutionMonitor(config or MonitorConfig())
    for i, (t, inputs, command, request) in enumerate(rows):
        if "task" in inputs:
            m.on_task(inputs["task"])
        changed = "belief" in inputs and m.on_belief(*inputs["belief"])
        if "plan" in inputs:
            m.on_plan(*inputs["plan"])
        if "failure" in inputs:
            m.on_planner_failure(*inputs["failure"])
        started = None
        if "teleop" in inputs:
            started = m.on_teleop(inputs["teleop"], t).command
        for skill_id, p, status in inputs.get("progress", ()):
            m.on_progress(skill_id, p, status, t)
        decision = m.tick(t, changed)
        started = decision.command or started
        assert (str(started) if started else None) == command, f"row {i} (t={t}): started {started}, wanted {command}"
        assert decision.request == request, f"row {i} (t={t}): asked {decision.request!r}, wanted {request!r}"
    return m


def test_the_task_asks_for_a_plan_and_the_plan_starts_its_first_skill():
    m = run_table([
        (0.0, {}, None, None),                                  # no task yet: nothing happens
        (0.1, {"task": "season the food"}, None, "task"),
        (0.2, {}, None, None),                                  # waiting for the answer
        (2.1, {"plan": (1, SEARCH_TL)}, "OpenDrawer(TL-H)", None),
    ])
    assert m.current_id == 1 and m.waiting == ""


def started(plan=SEARCH_TL, config=None):
    """A monitor running the plan's first skill (id 1) since t=2."""
    first = str(parse_program(plan)[0])
    return run_table([(0.0, {"task": "t"}, None, "task"), (2.0, {"plan": (1, plan)}, first, None)], config)


def test_progress_threshold_switching_needs_p_sustained_for_half_a_second():
    run_table([
        (2.5, {"progress": [(1, 0.5, "running")]}, None, None),
        (3.0, {"progress": [(1, 0.92, "running")]}, None, None),   # above since 3.0
        (3.3, {"progress": [(1, 0.95, "running")]}, None, None),
        (3.4, {"progress": [(1, 0.85, "running")]}, None, None),   # a dip restarts the clock
        (3.5, {"progress": [(1, 0.95, "running")]}, None, None),   # above since 3.5
        (3.9, {}, None, None),
        (4.0, {}, "InspectDrawer(TL)", None),                       # 0.5 s sustained: hand off
    ], monitor=started())


def test_stale_feedback_for_another_skill_id_is_ignored_and_progress_restarts_at_each_skill():
    m = started()
    run_table([
        (2.5, {"progress": [(1, 1.0, "done")]}, None, None),
        (3.0, {}, "InspectDrawer(TL)", None),
        # progress of the skill before (id 1), arriving late, must not finish skill 2
        (3.1, {"progress": [(1, 1.0, "done")]}, None, None),
        (3.7, {"progress": [(1, 1.0, "done")]}, None, None),
        (4.0, {}, None, None),
    ], monitor=m)
    assert m.stale_feedback == 2 and m.progress == 0.0 and str(m.current) == "InspectDrawer(TL)"


def finish(m, skill_id, t):
    """Report ``skill_id`` done at ``t`` and tick until its handoff (t + 0.5)."""
    m.on_progress(skill_id, 1.0, "done", t)
    m.tick(t)
    return m.tick(t + 0.5)


@pytest.mark.parametrize("verdict, after_inspect", [("yes", "Pick(spice)"), ("no", "CloseDrawer(TL-H)")])
def test_a_branch_is_resolved_against_the_newest_belief(verdict, after_inspect):
    m = started()
    assert str(finish(m, 1, 3.0).command) == "InspectDrawer(TL)"
    run_table([
        (4.0, {"belief": (1, {"at(spice, TL)": verdict})}, None, "belief_updated"),
        (4.1, {"progress": [(2, 1.0, "done")]}, None, None),
        (4.6, {}, after_inspect, None),
    ], monitor=m)


def test_an_unresolved_branch_waits_for_the_belief():
    m = started()
    finish(m, 1, 3.0)
    decision = finish(m, 2, 4.0)
    assert decision.command is None and m.waiting == "belief" and m.current is None
    run_table([(5.0, {"belief": (1, {"at(spice, TL)": "no"})}, "CloseDrawer(TL-H)", "belief_updated")], monitor=m)


def test_a_plan_that_branches_on_what_nobody_inspects_is_asked_again_not_waited_on_forever():
    """A first plan that opens with a branch on an uninspected drawer: no skill runs, so no
    belief update will come; after branch_patience idle seconds the monitor asks again (once per
    patience), and a plan that inspects first goes on."""
    branch_first = ["IF at(spice, TR) = yes THEN OpenDrawer(TR-H) -> Pick(spice) ELSE OpenDrawer(TL-H)"]
    run_table([
        (0.0, {"task": "t"}, None, "task"),
        (2.0, {"plan": (1, branch_first)}, None, None),         # unknown: it waits ...
        (4.9, {}, None, None),
        (5.0, {}, None, "branch_unresolved"),                   # ... branch_patience (3 s), then asks
        (6.0, {}, None, None),                                  # once: the question is out
        (7.0, {"plan": (2, branch_first)}, None, None),         # the same answer: wait again
        (9.9, {}, None, None),
        (10.0, {}, None, "branch_unresolved"),
        (11.0, {"plan": (3, SEARCH_TL)}, "OpenDrawer(TL-H)", None),
    ])


def test_a_proposal_is_spliced_at_the_running_skills_handoff():
    """Running InspectDrawer(TL), a new chunk that repeats it arrives: the running skill is never
    interrupted, and after it the chunk goes on past it (the paper's A, B, C, D, E example)."""
    m = started()
    finish(m, 1, 3.0)                                            # InspectDrawer(TL) runs (id 2)
    proposal = ["OpenDrawer(TL-H) -> InspectDrawer(TL) -> CloseDrawer(TL-H) -> OpenDrawer(TR-H) -> InspectDrawer(TR)"]
    run_table([
        (3.6, {"belief": (1, {"at(spice, TL)": "no"})}, None, "belief_updated"),
        (5.6, {"plan": (2, proposal)}, None, None),              # buffered: InspectDrawer(TL) still runs
        (5.7, {"progress": [(2, 1.0, "done")]}, None, None),
        (6.2, {}, "CloseDrawer(TL-H)", None),
    ], monitor=m)
    assert [str(s) for s in m.active] == ["OpenDrawer(TR-H)", "InspectDrawer(TR)"]


def test_only_the_newest_requests_answer_is_taken():
    m = started()
    run_table([
        (2.5, {"belief": (1, {"at(spice, TL)": "no"})}, None, "belief_updated"),    # request 2
        (2.6, {"plan": (1, ["CloseDrawer(TL-H)"])}, None, None),                     # the answer to 1: stale
    ], monitor=m)
    assert m.stale_plans == 1 and m.pending is None


def test_a_plan_outside_the_vocabulary_is_refused_and_asked_again():
    m = run_table([
        (0.0, {"task": "t"}, None, "task"),
        (2.0, {"plan": (1, ["Teleport(kitchen)"])}, None, "invalid_plan"),
        (4.0, {"plan": (2, ["OpenDrawer(TL-H) -> InspectDrawer(TL) -> Done()"])}, "OpenDrawer(TL-H)", None),
    ])
    assert m.bad_plans == 1 and "unknown skill 'Teleport'" in m.failures[0]


def test_requests_that_get_no_plan_are_asked_again_then_the_task_is_given_up_with_the_planners_word():
    """A planner that gives up on a request (its model answered no plan, however often it was
    asked) is asked once more with what went wrong; a second request in a row that gets no plan
    gives the task up, saying the planner's last word (it asked again forever, every 2 s)."""
    gone = "planner http://127.0.0.1:9/v1 (model m) gave no plan in 3 attempts; the last: the answer is not JSON"
    m = run_table([
        (0.0, {"task": "t"}, None, "task"),
        (2.0, {"failure": (1, gone)}, None, "planner_failed"),
        (4.0, {"failure": (2, gone)}, None, None),
        (6.0, {}, None, None),
    ])
    assert m.finished and m.gave_up == f"no plan for 2 requests in a row: {gone}"
    assert m.failures == [f"plan 1: {gone}", f"plan 2: {gone}"] and m.bad_plans == 2


def test_a_plan_between_two_planner_failures_starts_the_count_again_and_a_running_plan_goes_on():
    m = run_table([
        (0.0, {"task": "t"}, None, "task"),
        (2.0, {"plan": (1, ["Teleport(kitchen)"])}, None, "invalid_plan"),       # refused: the first in a row
        (4.0, {"plan": (2, ["OpenDrawer(TL-H) -> InspectDrawer(TL)"])}, "OpenDrawer(TL-H)", "horizon"),
        (6.0, {"failure": (3, "the endpoint answered HTTP 500")}, None, "planner_failed"),
        (8.0, {"failure": (2, "an old request's")}, None, None),                 # stale: counts nothing
    ])
    assert not m.finished and str(m.current) == "OpenDrawer(TL-H)" and [str(s) for s in m.active] == [
        "InspectDrawer(TL)"]
    assert m.stale_plans == 1 and m.refused_in_row == 1
    run_table([(10.0, {"failure": (4, "the endpoint answered HTTP 500")}, None, None)], monitor=m)
    assert m.finished and m.gave_up == "no plan for 2 requests in a row: the endpoint answered HTTP 500"


def test_a_depleted_horizon_asks_for_more_once_and_a_plan_that_ends_never_does():
    m = run_table([
        (0.0, {"task": "t"}, None, "task"),
        # its first skill starts, one remains (< 2): ask at once, and once
        (2.0, {"plan": (1, ["OpenDrawer(TL-H) -> InspectDrawer(TL)"])}, "OpenDrawer(TL-H)", "horizon"),
        (2.1, {}, None, None),
    ])
    assert m.request_id == 2
    ending = started(["OpenDrawer(TL-H) -> Done()"])
    assert plan_ends(ending.active) and ending.tick(2.1).request is None
    branching = started()                                         # 1 certain skill left, but a branch ahead
    assert branching.tick(2.1).request is None


def test_reaching_done_finishes_the_task():
    m = started(["OpenDrawer(TL-H) -> Done()"])
    assert finish(m, 1, 3.0).request is None                     # nothing left to ask for
    assert m.finished and m.current is None and m.request_id == 1
    assert m.tick(5.0).command is None


def test_timeout_switching_hands_off_whatever_the_progress_says():
    m = started(config=MonitorConfig(switching="timeout", timeout=4.0))
    run_table([
        (3.0, {"progress": [(1, 1.0, "done")]}, None, None),     # done, but the timer decides
        (5.9, {}, None, None),
        (6.0, {}, "InspectDrawer(TL)", None),
    ], monitor=m)


def test_a_failed_skill_drops_the_plan_and_asks_again():
    m = started()
    run_table([(2.5, {"progress": [(1, 0.3, "failed")]}, None, "failed")], monitor=m)
    assert m.active == [] and m.current is None and m.skill_failures == 1 and m.last_failed == "OpenDrawer(TL-H)"


def test_a_failed_skill_drops_a_proposal_made_before_it_failed_too():
    m = started()
    run_table([
        (2.5, {"belief": (1, {"at(spice, TL)": "no"})}, None, "belief_updated"),
        (3.0, {"plan": (2, ["OpenDrawer(TL-H) -> Done()"])}, None, None),           # buffered
        (3.5, {"progress": [(1, 0.3, "failed")]}, None, "failed"),                  # not retried from it
        (4.0, {}, None, None),
    ], monitor=m)
    assert m.pending is None and m.waiting == "plan"


def test_a_skill_that_keeps_failing_ends_the_task_where_it_is():
    m = started(["Pick(spice) -> Season(food) -> Done()"], config=MonitorConfig(max_failures=2))
    m.on_progress(1, 0.2, "failed", 2.5)
    assert m.tick(2.5).request == "failed"
    m.on_plan(2, ["Pick(spice) -> Season(food) -> Done()"])
    assert str(m.tick(4.5).command) == "Pick(spice)"
    m.on_progress(m.current_id, 0.1, "failed", 5.0)
    assert m.tick(5.0).request is None and m.finished and m.gave_up == "Pick(spice) failed 2 times"


def test_a_teleop_override_preempts_and_the_plan_resumes_after_it():
    m = started()
    run_table([
        (2.5, {"teleop": "CloseDrawer(BL-H)"}, "CloseDrawer(BL-H)", None),
        (3.0, {"progress": [(1, 1.0, "done")]}, None, None),     # feedback for the preempted id: stale
        (3.1, {"progress": [(2, 1.0, "done")]}, None, None),
        (3.6, {}, "OpenDrawer(TL-H)", None),                     # the interrupted skill runs again
    ], monitor=m)
    assert m.current_source == "plan" and [str(s) for s in m.executed] == ["CloseDrawer(BL-H)"]


def test_without_plan_chunking_the_monitor_asks_only_when_idle():
    m = started(["OpenDrawer(TL-H)"], config=MonitorConfig(chunking=False))
    assert m.tick(2.1).request is None                            # the skill runs: no overlap
    m.on_progress(1, 1.0, "done", 2.5)
    m.tick(2.5)
    decision = m.tick(3.0)
    assert decision.command is None and decision.request == "horizon" and m.waiting == "plan"


def test_task_progress_counts_milestones_in_order_and_never_falls():
    m = ExecutionMonitor()
    m.observe_world({"drawers_closed": True}, 1.0)               # closed at the start: no credit
    assert m.score == 0
    m.on_belief(1, {"at(spice, TR)": "yes"})
    m.observe_world({"drawers_closed": False}, 10.0)
    m.observe_world({"grasped": True}, 12.0)
    m.observe_world({"grasped": False, "seasoned": True}, 20.0)
    m.observe_world({"drawers_closed": True, "seasoned": True}, 25.0)
    m.observe_world({}, 30.0)
    assert m.score == 1.0 and m.best_at == 25.0
    assert all(m.milestones.values())
