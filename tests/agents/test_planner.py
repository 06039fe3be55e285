"""Planners: the scripted stand-in gives the paper's search, and a real model behind an
OpenAI-compatible endpoint (here a local HTTP server answering as one would) drops in; what a
model answers is checked like any plan."""

import json
import threading
from http.server import BaseHTTPRequestHandler, HTTPServer

import pytest

from agents.monitor import ExecutionMonitor
from agents.plan import parse_program
from agents.planner import (
    FixedOrderPlanner, OpenAICompatiblePlanner, PlannerError, ScriptedPlanner, make_planner, parse_answer,
)

UNKNOWN = {f"at(spice, {d})": "unknown" for d in ("TL", "TR", "BL", "BR")}


def test_the_scripted_planner_searches_in_order_and_branches_at_each_inspection():
    plan = ScriptedPlanner().propose("season", UNKNOWN, {"executed": []})
    assert plan == ["OpenDrawer(TL-H)", "InspectDrawer(TL)",
                    "IF at(spice, TL) = yes THEN Pick(spice) -> Season(food) -> CloseDrawer(TL-H) -> Done() "
                    "ELSE CloseDrawer(TL-H)"]
    assert 3 <= len([n for n in parse_program(plan)]) <= 5


def test_the_scripted_planner_closes_what_it_opened_and_fetches_once_it_knows():
    belief = dict(UNKNOWN, **{"at(spice, TL)": "no"})
    assert ScriptedPlanner().propose("s", belief, {"executed": ["OpenDrawer(TL-H)"], "current": "InspectDrawer(TL)"}) \
        == ["CloseDrawer(TL-H)", "OpenDrawer(TR-H)", "InspectDrawer(TR)",
            "IF at(spice, TR) = yes THEN Pick(spice) -> Season(food) -> CloseDrawer(TR-H) -> Done() "
            "ELSE CloseDrawer(TR-H)"]
    belief["at(spice, TR)"] = "yes"
    done = ["OpenDrawer(TL-H)", "InspectDrawer(TL)", "CloseDrawer(TL-H)", "OpenDrawer(TR-H)"]
    assert ScriptedPlanner().propose("s", belief, {"executed": done, "current": "InspectDrawer(TR)"}) \
        == ["Pick(spice) -> Season(food) -> CloseDrawer(TR-H) -> Done()"]
    # after a slip the monitor says the gripper is empty again: pick again
    held = dict(belief, **{"holding(spice)": "no"})
    assert ScriptedPlanner().propose("s", held, {"executed": done + ["InspectDrawer(TR)", "Pick(spice)"]}) \
        == ["Pick(spice) -> Season(food) -> CloseDrawer(TR-H) -> Done()"]
    searched = {k: "no" for k in UNKNOWN}
    assert ScriptedPlanner().propose("s", searched, {"executed": []}) == ["Done()"]


def test_the_scripted_planner_reopens_the_bag_unless_the_hand_holds_it_open():
    """The bag's paper springs shut when the hand leaves the mouth: Pick follows the OpenBag (and
    InspectBag) that holds it open, and after anything else the bag is opened again."""
    bag = ScriptedPlanner(task_kind="bag")
    assert bag.propose("t", {}, {"executed": []}) == [
        "OpenBag(bag) -> InspectBag(bag)",
        "IF in(target, bag) = yes THEN Pick(target) -> Extract(target) -> Done() ELSE Done()"]
    seen = {"in(target, bag)": "yes", "holding(target)": "no"}
    assert bag.propose("t", seen, {"executed": ["OpenBag(bag)"], "current": "InspectBag(bag)"}) \
        == ["Pick(target) -> Extract(target) -> Done()"]
    after_a_miss = ["OpenBag(bag)", "InspectBag(bag)", "Pick(target)"]
    assert bag.propose("t", seen, {"executed": after_a_miss}) \
        == ["OpenBag(bag) -> Pick(target) -> Extract(target) -> Done()"]
    assert bag.propose("t", dict(seen, **{"holding(target)": "yes"}), {"executed": after_a_miss}) \
        == ["Extract(target) -> Done()"]
    assert parse_program(bag.propose("t", seen, {"executed": after_a_miss}), "bag")


def test_the_one_skill_planner_proposes_the_next_skill_only():
    belief = dict(UNKNOWN, **{"at(spice, TL)": "no"})
    one = ScriptedPlanner(one_skill=True)
    assert one.propose("s", UNKNOWN, {"executed": []}) == ["OpenDrawer(TL-H)"]
    assert one.propose("s", belief, {"executed": ["OpenDrawer(TL-H)", "InspectDrawer(TL)"]}) == ["CloseDrawer(TL-H)"]


def test_the_fixed_order_planner_tries_one_drawer_once():
    fixed = FixedOrderPlanner()
    assert parse_program(fixed.propose("s", {}, {"executed": []}))
    assert fixed.propose("s", {}, {"executed": ["OpenDrawer(TL-H)"]}) == ["Done()"]


def test_the_scripted_planner_and_the_monitor_give_the_papers_trace_for_a_spice_in_TR():
    """Planner and monitor alone, every skill finishing 1 s after it starts and the planner
    answering 2 s after each request: the skill trace is the paper's (Sec. V)."""
    truth = "TR"
    m, planner, t, pending = ExecutionMonitor(), ScriptedPlanner(), 0.0, []
    m.on_task("season the food")
    version, belief = 0, {}
    started_at = None
    while not m.finished and t < 120:
        t = round(t + 0.1, 3)
        for due, rid, program in [p for p in pending if p[0] <= t]:
            pending.remove((due, rid, program))
            m.on_plan(rid, program)
        if m.current is not None and started_at is not None and t - started_at >= 1.0:
            m.on_progress(m.current_id, 1.0, "done", t)
            if m.current.name == "InspectDrawer" and f"at(spice, {m.current.arg})" not in belief:
                version += 1
                belief[f"at(spice, {m.current.arg})"] = "yes" if m.current.arg == truth else "no"
        changed = m.on_belief(version, dict(belief))
        decision = m.tick(t, changed)
        if decision.command is not None:
            started_at = t
        if decision.request is not None:
            context = {"executed": [str(s) for s in m.executed], "current": str(m.current) if m.current else ""}
            pending.append((t + 2.0, decision.request_id, planner.propose("s", dict(belief), context)))
    assert m.finished
    assert [str(s) for s in m.executed] == [
        "OpenDrawer(TL-H)", "InspectDrawer(TL)", "CloseDrawer(TL-H)", "OpenDrawer(TR-H)", "InspectDrawer(TR)",
        "Pick(spice)", "Season(food)", "CloseDrawer(TR-H)"]


class _Model(BaseHTTPRequestHandler):
    """An OpenAI-compatible endpoint: answers each chat completion with ``server.reply``."""

    def do_POST(self):  # noqa: N802 (http.server's name)
        body = json.loads(self.rfile.read(int(self.headers["Content-Length"])))
        self.server.seen.append((self.path, self.headers.get("Authorization"), body))
        payload = json.dumps({"choices": [{"message": {"content": self.server.reply}}]}).encode()
        self.send_response(200)
        self.send_header("Content-Type", "application/json")
        self.send_header("Content-Length", str(len(payload)))
        self.end_headers()
        self.wfile.write(payload)

    def log_message(self, *args):
        pass


@pytest.fixture
def model_server():
    server = HTTPServer(("127.0.0.1", 0), _Model)
    server.seen, server.reply = [], ""
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    yield server
    server.shutdown()
    server.server_close()
    thread.join()


def test_a_model_behind_an_openai_compatible_endpoint_drops_in(model_server, monkeypatch):
    monkeypatch.setenv("TEST_PLANNER_KEY", "sk-test")
    model_server.reply = "```json\n" + json.dumps({"action_plan": ["OpenDrawer(BL-H) -> InspectDrawer(BL)"],
                                                   "reasoning": "start low"}) + "\n```"
    url = f"http://127.0.0.1:{model_server.server_port}/v1"
    planner = OpenAICompatiblePlanner(url, "some-vlm", api_key_env="TEST_PLANNER_KEY", timeout=10)
    assert planner.propose("season", UNKNOWN, {"executed": []}) == ["OpenDrawer(BL-H) -> InspectDrawer(BL)"]
    path, auth, body = model_server.seen[0]
    assert path == "/v1/chat/completions" and auth == "Bearer sk-test" and body["model"] == "some-vlm"
    assert "Always close drawers" in body["messages"][0]["content"]
    assert json.loads(body["messages"][1]["content"])["belief"] == UNKNOWN
    assert isinstance(make_planner(f"openai:{url}#some-vlm"), OpenAICompatiblePlanner)


@pytest.mark.parametrize("reply", [
    "I would open the top-left drawer.",                                       # not JSON
    json.dumps({"plan": ["OpenDrawer(TL-H)"]}),                                # no action_plan
    json.dumps({"action_plan": ["__import__('os').system('touch /tmp/x')"]}),  # code, not a skill
    json.dumps({"action_plan": ["Teleport(kitchen)"]}),                        # outside the vocabulary
    json.dumps({"action_plan": "OpenDrawer(TL-H)"}),                           # not a list
])
def test_a_models_answer_that_is_not_a_plan_is_refused(model_server, reply):
    model_server.reply = reply
    planner = OpenAICompatiblePlanner(f"http://127.0.0.1:{model_server.server_port}/v1", "m", timeout=10)
    with pytest.raises(PlannerError, match="not a program of the vocabulary|not text"):
        planner.propose("season", UNKNOWN, {})


def test_an_unreachable_endpoint_and_a_bad_planner_name_say_what_to_do():
    with pytest.raises(PlannerError, match="gave no usable answer"):
        OpenAICompatiblePlanner("http://127.0.0.1:9/v1", "m", timeout=2).propose("s", {}, {})
    with pytest.raises(ValueError, match="openai:<base_url>#<model>"):
        make_planner("gpt")
    with pytest.raises(ValueError, match="must start with http"):
        OpenAICompatiblePlanner("file:///etc/passwd", "m")
    with pytest.raises(PlannerError):
        parse_answer(None)


def test_a_run_with_a_model_and_a_teleop_file_replays_without_either(model_server, tmp_path):
    """The planner behind an endpoint and the teleop schedule consult the world outside the
    program: their flows are replayed from the log (replay="log"), so the replay calls no
    endpoint and reads no file, and re-executes every other flow against what they said."""
    from agents.retriever0 import build
    from retriever import read_log
    from retriever.log import replay

    model_server.reply = json.dumps({"action_plan": ["OpenDrawer(TL-H) -> InspectDrawer(TL) -> CloseDrawer(TL-H)"]})
    schedule = tmp_path / "teleop.json"
    schedule.write_text(json.dumps([{"t_start": 1.0, "payload": "OpenDrawer(TR-H)"}]))
    pipe = build(seed=0, drawer="TR", planner=f"openai:http://127.0.0.1:{model_server.server_port}/v1#m",
                 planner_latency=0.5, teleop=str(schedule))
    log = tmp_path / "run.mcap"
    trace = pipe.run(duration=8.0, backend="inproc", log=str(log))
    asked = len(model_server.seen)
    assert asked >= 1 and any(e.value.payload == "OpenDrawer(TR-H)" for e in trace.events_of("teleop", "teleop"))
    schedule.unlink()
    model_server.reply = "the endpoint answers something else today"
    report = replay(read_log(log))
    assert report.identical and len(model_server.seen) == asked
    assert report.nodes["planner"].from_log and report.nodes["teleop"].from_log
    assert report.nodes["monitor"].replayed > 0 and report.nodes["monitor"].divergent == 0
