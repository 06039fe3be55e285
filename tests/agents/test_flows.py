"""Each flow of Retriever-0 by direct calls (no runtime): what it emits for what it is given."""

import json

import numpy as np
import pytest

from agents.flows import Goal, Monitor, PlannerFlow, Teleop, load_schedule, merge_three_valued
from agents.messages import Belief, Frame, Observation, PlanChunk, PlanFailure, PlanRequest, Progress, Task, TeleopEvent


def obs(t, **facts):
    return Observation(t=t, qpos=np.zeros(3), robot=np.zeros(5), facts=facts)


def test_the_goal_is_said_once():
    goal = Goal()
    first = goal.step()
    assert isinstance(first["task"], Task) and first["task"].task == "drawers"
    assert goal.step() == {} and goal.step() == {}


def test_the_bag_tasks_goal_is_the_bags_in_the_graph_the_planner_reads():
    """The bag task's goal names the bag task and says to take the target out of the bag (it
    said "Find the spice in the drawers and season the food." with task "drawers", which a
    model behind an endpoint read under the bag's system prompt)."""
    from agents.retriever0 import build
    goal = next(n for n in build(task="bag").build_ir().doc["nodes"] if n["id"] == "goal")
    said = Goal(**goal["params"]).step()["task"]        # as every backend rebuilds it from the IR
    assert said.task == "bag" and said.target == "target" and "bag" in said.text and "spice" not in said.text
    drawers = Goal().step()["task"]
    assert drawers.task == "drawers" and drawers.text == "Find the spice in the drawers and season the food."


def test_the_monitor_flow_asks_then_starts_the_plan_and_reports_its_status():
    monitor = Monitor(end_after=None)
    out = monitor.step(obs(0.1), task=Task(text="season"))
    assert out["request"].request_id == 1 and out["request"].reason == "task"
    assert out["request"].belief == {"holding(spice)": "no"} and "skill" not in out
    assert out["status"].waiting == "plan" and out["status"].score == 0
    plan = PlanChunk(request_id=1, program=["OpenDrawer(TL-H) -> InspectDrawer(TL) -> Done()"])
    out = monitor.step(obs(2.1), plan=[plan])
    assert (out["skill"].skill_id, str(out["skill"])) == (1, "OpenDrawer(TL-H)") and "request" not in out
    out = monitor.step(obs(2.6), progress=[Progress(skill_id=1, t=2.5, p=0.95, status="running")])
    assert "skill" not in out and out["status"].p == 0.95
    out = monitor.step(obs(3.1), progress=[Progress(skill_id=1, t=3.0, p=1.0, status="done")])
    assert str(out["skill"]) == "InspectDrawer(TL)" and out["status"].executed == ["OpenDrawer(TL-H)"]


def test_the_monitor_ends_the_run_after_done():
    monitor = Monitor(end_after=0.5)
    monitor.step(obs(0.1), task=Task(text="season"))
    monitor.step(obs(0.2), plan=[PlanChunk(request_id=1, program=["Done()"])])
    assert monitor.step(obs(0.3))["status"].finished
    with pytest.raises(SystemExit) as ended:
        monitor.step(obs(0.8))
    assert ended.value.code == 0


def test_the_monitor_says_once_that_it_gave_up(capsys):
    """Verbose, the monitor says "gave up" once; the idle ticks after it until the run ends say
    nothing (it alternated "gave up" and "(idle)" lines at every tick)."""
    monitor = Monitor(end_after=None, verbose=True, task="bag")
    monitor.step(obs(0.1), task=Task(text="open the bag", task="bag"))
    t = 0.2
    for request_id in (1, 2, 3):
        monitor.step(obs(t), plan=[PlanChunk(request_id=request_id, program=["OpenBag(bag) -> Done()"])])
        skill_id = monitor.logic.current_id
        monitor.step(obs(t + 0.1), progress=[Progress(skill_id=skill_id, t=t + 0.1, p=0.2, status="failed")])
        t += 0.2
    assert monitor.logic.gave_up == "OpenBag(bag) failed 3 times"
    capsys.readouterr()
    for k in range(5):
        monitor.step(obs(t + 0.1 * k))
    assert capsys.readouterr().out == ""


def test_the_monitor_takes_a_teleop_override_at_once():
    monitor = Monitor(end_after=None)
    monitor.step(obs(0.1), task=Task(text="season"))
    out = monitor.step(obs(0.2), teleop=[TeleopEvent(t_start=0.2, t_end=1.0, mode="skill_override",
                                                      payload="Pick(spice)")])
    assert (str(out["skill"]), out["skill"].source) == ("Pick(spice)", "teleop")


def test_the_monitor_takes_only_newer_beliefs():
    monitor = Monitor(end_after=None)
    monitor.step(obs(0.1), task=Task(text="season"))
    out = monitor.step(obs(0.2), belief=Belief(version=1, predicates={"at(spice, TL)": "no"}))
    assert out["request"].reason == "belief_updated"
    out = monitor.step(obs(0.3), belief=Belief(version=1, predicates={"at(spice, TL)": "no"}))
    assert "request" not in out


def test_the_planner_flow_answers_each_request_with_a_chunk_and_a_broken_planner_with_a_failure(capsys):
    flow = PlannerFlow()
    flow.setup()
    request = PlanRequest(request_id=3, reason="task", t=0.0, belief={}, executed=[])
    out = flow.step(request, Task(text="season"))
    assert out["plan"].request_id == 3 and out["plan"].program[0] == "OpenDrawer(TL-H)"
    frame = Frame(camera="head", t=0.0, rgb=np.zeros((4, 4, 3), np.uint8))
    assert flow.step(request, Task(text="season"), frame) == out      # the scripted planner has no use for it
    broken = PlannerFlow(planner="openai:http://127.0.0.1:9/v1#m")
    broken.setup()
    broken.planner.timeout = 2
    out = broken.step(request, Task(text="season"), frame)
    assert list(out) == ["failure"] and out["failure"].request_id == 3
    assert out["failure"].error.startswith("planner endpoint http://127.0.0.1:9/v1 gave no answer: ")
    assert "hint: is the model server still up?" in capsys.readouterr().err


def test_the_monitor_flow_gives_up_after_two_requests_in_a_row_got_no_plan(capsys):
    monitor = Monitor(end_after=None, verbose=True)
    monitor.step(obs(0.1), task=Task(text="season"))
    error = "planner http://127.0.0.1:9/v1 (model m) gave no plan in 3 attempts; the last: the answer is not JSON"
    out = monitor.step(obs(2.1), plan_failure=[PlanFailure(request_id=1, error=error)])
    assert out["request"].reason == "planner_failed" and out["request"].failures == [f"plan 1: {error}"]
    out = monitor.step(obs(4.1), plan_failure=[PlanFailure(request_id=2, error=error)])
    assert "request" not in out and out["status"].gave_up == f"no plan for 2 requests in a row: {error}"
    assert f"gave up: no plan for 2 requests in a row: {error}" in capsys.readouterr().out


def test_three_valued_merge_never_forgets_to_unknown():
    old = {"at(spice, TL)": "no", "at(spice, TR)": "yes"}
    assert merge_three_valued(old, {"at(spice, TL)": "unknown", "at(spice, TR)": "no", "at(spice, BL)": "unknown"}) \
        == {"at(spice, TL)": "no", "at(spice, TR)": "no", "at(spice, BL)": "unknown"}


def test_teleop_sends_its_schedule_when_the_world_reaches_each_start(tmp_path):
    path = tmp_path / "teleop.json"
    path.write_text(json.dumps([{"t_start": 5.0, "t_end": 8.0, "payload": "CloseDrawer(TL-H)"},
                                {"t_start": 1.0, "payload": "Pick(spice)"}]))
    teleop = Teleop(schedule=str(path))
    teleop.setup()
    sent = [teleop.step(obs(t)).get("teleop") for t in (0.5, 1.0, 1.1, 5.0, 9.0)]
    assert [e.payload if e else None for e in sent] == [None, "Pick(spice)", None, "CloseDrawer(TL-H)", None]


@pytest.mark.parametrize("content, message", [
    ("not json", "teleop schedule"),
    (json.dumps({"t_start": 1}), "expected a JSON list"),
    (json.dumps([{"payload": "Pick(spice)"}]), "item 0: needs a number t_start"),
    (json.dumps([{"t_start": 1, "payload": "os:system"}]), "item 0: payload is not a skill of the vocabulary"),
    (json.dumps([{"t_start": 1, "mode": "action_chunk", "payload": "Pick(spice)"}]), "mode must be"),
    ('[{"t_start": NaN, "payload": "Pick(spice)"}]', "t_start must be a number of seconds >= 0$"),
    (json.dumps([{"t_start": -1, "payload": "Pick(spice)"}]), "t_start must be"),
    (json.dumps([{"t_start": True, "payload": "Pick(spice)"}]), "t_start must be"),
    (json.dumps([{"t_start": 1, "payload": ["Pick(spice)"]}]), "payload must be a skill"),
    (json.dumps([{"t_start": 1, "payload": {"os": "system"}}]), "payload must be a skill"),
    (json.dumps(["Pick(spice)"]), "expected an object"),
])
def test_a_bad_teleop_schedule_is_refused_naming_the_item(tmp_path, content, message):
    path = tmp_path / "teleop.json"
    path.write_text(content)
    with pytest.raises(ValueError, match=message):
        load_schedule(str(path))


def test_a_teleop_schedule_that_is_no_schedule_is_refused_without_quoting_it(tmp_path):
    """issue 40: its path comes from the flow's parameters, which an IR from elsewhere sets, and a
    worker's error goes back to whoever deployed it: the first line of a root-only file came back."""
    secret = tmp_path / "secret.json"
    for content in ('["the first line of a secret"]', '[{"t_start": 1, "payload": "the-secret-token"}]',
                    "the-secret-token\n", '{"t_start": "the-secret-token"}'):
        secret.write_text(content)
        with pytest.raises(ValueError) as refused:
            load_schedule(str(secret))
        assert "secret" not in str(refused.value).replace(str(secret), ""), refused.value
    for path in ("/dev/zero", str(tmp_path)):
        with pytest.raises(ValueError, match=r"not a regular file of at most 1048576 bytes"):
            load_schedule(path)


@pytest.mark.parametrize("failed, override", [("Season(food)", "Pick(spice)"), ("Pick(spice)", "Pick(spice)"),
                                              ("OpenDrawer(TR-H)", "OpenDrawer(TR-H)")])
def test_the_scripted_operator_takes_over_after_a_failure(failed, override):
    from agents.messages import MonitorStatus
    teleop = Teleop(recover=True)
    teleop.setup()

    def status(failures):
        return MonitorStatus(t=1.0, skill="", skill_id=3, p=0.0, score=0.5, milestones={}, finished=False,
                             replans=1, executed=[], failures=failures, last_failed=failed if failures else "")
    assert teleop.step(obs(1.0), status(0)) == {}
    sent = teleop.step(obs(1.1), status(1))["teleop"]
    assert (sent.payload, sent.mode) == (override, "skill_override")
    assert teleop.step(obs(1.2), status(1)) == {}               # once per failure


def test_the_scripted_operator_opens_the_bag_again_when_the_target_fell_back_into_it():
    from agents.messages import MonitorStatus
    teleop = Teleop(recover=True, task="bag")
    teleop.setup()
    status = MonitorStatus(t=1.0, skill="", skill_id=3, p=0.0, score=0.5, milestones={}, finished=False,
                           replans=1, executed=[], failures=1, last_failed="Extract(target)")
    assert teleop.step(obs(1.0, object_location="bag", bag_opened=False), status)["teleop"].payload == "OpenBag(bag)"
    teleop = Teleop(recover=True, task="bag")
    teleop.setup()
    assert teleop.step(obs(1.0, object_location="table"), status)["teleop"].payload == "Pick(target)"
