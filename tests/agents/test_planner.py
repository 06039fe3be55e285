"""Planners: the scripted stand-in gives the paper's search, and a real model behind an
OpenAI-compatible endpoint (here a local HTTP server answering as one would) drops in; what a
model answers is checked like any plan."""

import base64
import io
import json
import socketserver
import threading
from http.server import BaseHTTPRequestHandler, HTTPServer

import numpy as np
import pytest
from PIL import Image

from agents.monitor import ExecutionMonitor
from agents.plan import parse_program
from agents.planner import FixedOrderPlanner, OpenAICompatiblePlanner, PlannerError, ScriptedPlanner, make_planner
from agents.vlm import AnswerRefused, check_answer

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
    """An OpenAI-compatible endpoint: answers the n-th chat completion with ``server.replies[n]``
    (the last one from then on): a string is the model's content; ``(status, body)`` is sent as
    it is; ``(status, body, location)`` also sets a Location header."""

    def do_POST(self):  # noqa: N802 (http.server's name)
        body = json.loads(self.rfile.read(int(self.headers["Content-Length"])))
        self.server.seen.append((self.path, self.headers.get("Authorization"), body))
        reply = self.server.replies[min(len(self.server.seen), len(self.server.replies)) - 1]
        if isinstance(reply, str):
            reply = (200, json.dumps({"choices": [{"message": {"role": "assistant", "content": reply}}]}))
        status, payload, *location = reply
        trickle = status == "trickle"  # a byte at a time, until the test lets go (server.let_go)
        status, payload = (200, "x" * 1000) if trickle else (status, payload)
        payload = payload.encode()
        self.send_response(status)
        self.send_header("Content-Type", "application/json")
        self.send_header("Content-Length", str(len(payload)))
        for url in location:
            self.send_header("Location", url)
        self.end_headers()
        if not trickle:
            self.wfile.write(payload)
            return
        for byte in payload:
            if self.server.let_go.wait(0.05):
                return
            self.wfile.write(bytes([byte]))
            self.wfile.flush()

    def log_message(self, *args):
        pass


def _serve():
    server = HTTPServer(("127.0.0.1", 0), _Model)
    server.seen, server.replies, server.let_go = [], [""], threading.Event()
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    return server, thread


@pytest.fixture
def model_server():
    server, thread = _serve()
    yield server
    server.shutdown()
    server.server_close()
    thread.join()


def _url(server) -> str:
    return f"http://127.0.0.1:{server.server_port}/v1"


def _png(data_url: str) -> np.ndarray:
    assert data_url.startswith("data:image/png;base64,")
    return np.asarray(Image.open(io.BytesIO(base64.b64decode(data_url.split(",", 1)[1]))))


NOT_A_PROGRAM = r'its "action_plan" is not a program of the drawers vocabulary \('
PLAN = {"action_plan": ["OpenDrawer(BL-H) -> InspectDrawer(BL)"], "reasoning": "start low"}
IMAGE = np.random.default_rng(0).integers(0, 256, (12, 16, 3), dtype=np.uint8)


def test_the_vlm_planner_sends_the_head_cameras_image_with_the_belief(model_server, monkeypatch):
    monkeypatch.setenv("TEST_PLANNER_KEY", "sk-test")
    model_server.replies = ["```json\n" + json.dumps(PLAN) + "\n```"]
    planner = OpenAICompatiblePlanner(_url(model_server), "some-vlm", api_key_env="TEST_PLANNER_KEY", timeout=10)
    assert planner.propose("season", UNKNOWN, {"executed": []}, image=IMAGE) == PLAN["action_plan"]
    path, auth, body = model_server.seen[0]
    assert path == "/v1/chat/completions" and auth == "Bearer sk-test" and body["model"] == "some-vlm"
    system, user = body["messages"]
    assert system["role"] == "system" and "Always close drawers" in system["content"]
    text, image = user["content"]
    assert text["type"] == "text" and json.loads(text["text"])["belief"] == UNKNOWN
    assert image["type"] == "image_url" and np.array_equal(_png(image["image_url"]["url"]), IMAGE)
    # before the camera's first frame: the state alone, as text
    planner.propose("season", UNKNOWN, {"executed": []})
    assert json.loads(model_server.seen[1][2]["messages"][1]["content"])["belief"] == UNKNOWN
    assert isinstance(make_planner(f"openai:{_url(model_server)}#some-vlm"), OpenAICompatiblePlanner)


def test_an_answer_that_is_no_plan_goes_back_to_the_model_with_what_was_expected(model_server):
    """The model's wrong answer and what was wrong with it, what is expected and an example go
    back to it in the same conversation (image included), and it is asked again."""
    model_server.replies = ["I would open the top-left drawer.", json.dumps(PLAN)]
    planner = OpenAICompatiblePlanner(_url(model_server), "m", timeout=10)
    assert planner.propose("season", UNKNOWN, {}, image=IMAGE) == PLAN["action_plan"]
    assert len(model_server.seen) == 2
    first, again = (body["messages"] for _, _, body in model_server.seen)
    assert again[:2] == first and again[2] == {"role": "assistant", "content": "I would open the top-left drawer."}
    told = again[3]["content"]
    assert again[3]["role"] == "user"
    assert told.startswith("Your answer was refused: the answer is not JSON (Expecting value: line 1 column 1 "
                           "(char 0)): 'I would open the top-left drawer.'. Answer with only a JSON object whose "
                           '"action_plan" is a list of 1 to 32 plan lines of the vocabulary, for example: '
                           '{"action_plan": ["OpenDrawer(TL-H) -> InspectDrawer(TL)", ')
    assert "got list" not in told


@pytest.mark.parametrize("reply, problem", [
    ("I would open the top-left drawer.",
     r"the answer is not JSON \(Expecting value: line 1 column 1 \(char 0\)\): 'I would open the top-left drawer.'"),
    (json.dumps({"plan": ["OpenDrawer(TL-H)"]}), r"""the answer has no "action_plan": '{"plan": \["OpenDrawer"""),
    (json.dumps({"action_plan": ["__import__('os').system('touch /tmp/x')"]}),
     rf"{NOT_A_PROGRAM}plan line 1: .* is not a skill call"),
    (json.dumps({"action_plan": ["Teleport(kitchen)"]}), rf"{NOT_A_PROGRAM}plan line 1: unknown skill 'Teleport'"),
    (json.dumps({"action_plan": "OpenDrawer(TL-H)"}), rf"{NOT_A_PROGRAM}a plan is a list of 1 to 32 lines, got str"),
    (json.dumps({"action_plan": []}), rf"{NOT_A_PROGRAM}a plan is a list of 1 to 32 lines, got 0 lines\): '\[\]'"),
    ("[" * 100_000 + "]" * 100_000, r"the answer is not JSON \(RecursionError: .*… \(200000 characters\)"),
])
def test_a_model_that_never_answers_a_plan_is_asked_three_times_then_refused(model_server, reply, problem):
    model_server.replies = [reply]
    url = _url(model_server)
    planner = OpenAICompatiblePlanner(url, "m", timeout=10)
    with pytest.raises(PlannerError, match=rf"^planner {url} \(model m\) gave no plan in 3 attempts; the last: "
                                           rf"{problem}.*\n    hint: the model must answer with only a JSON object "
                                           r'whose "action_plan" is a list .*, such as \{"action_plan": \[') as refused:
        planner.propose("season", UNKNOWN, {})
    assert len(model_server.seen) == 3 and len(model_server.seen[-1][2]["messages"]) == 2 + 2 * 2
    assert len(refused.value.problem) < 600          # a long answer is quoted shortened


def test_a_server_error_is_tried_again_within_the_bound(model_server):
    model_server.replies = [(500, "model overloaded"), (200, "<html>not a completion</html>"), json.dumps(PLAN)]
    planner = OpenAICompatiblePlanner(_url(model_server), "m", timeout=10)
    assert planner.propose("season", UNKNOWN, {}) == PLAN["action_plan"]
    assert len(model_server.seen) == 3
    assert all(len(body["messages"]) == 2 for _, _, body in model_server.seen)   # no answer to send back
    model_server.seen.clear()
    model_server.replies = [(500, "model overloaded")]
    with pytest.raises(PlannerError, match=r"gave no plan in 2 attempts; the last: the endpoint answered HTTP 500 "
                                           r"Internal Server Error: 'model overloaded'"):
        OpenAICompatiblePlanner(_url(model_server), "m", timeout=10, attempts=2).propose("season", UNKNOWN, {})
    assert len(model_server.seen) == 2
    model_server.seen.clear()
    model_server.replies = [(200, "<html>not a completion</html>")]
    with pytest.raises(PlannerError, match=r"gave no plan in 1 attempts; the last: the endpoint's reply is not a "
                                           r"chat completion \(Expecting value: .*\): '<html>not a completion"):
        OpenAICompatiblePlanner(_url(model_server), "m", timeout=10, attempts=1).propose("season", UNKNOWN, {})
    assert len(model_server.seen) == 1


def test_a_rate_limit_is_tried_again_and_a_failing_server_is_not_blamed_on_the_model(model_server):
    model_server.replies = [(429, "slow down"), json.dumps(PLAN)]
    assert OpenAICompatiblePlanner(_url(model_server), "m", timeout=10).propose("season", UNKNOWN, {}) \
        == PLAN["action_plan"]
    model_server.replies = [(503, "down")]
    with pytest.raises(PlannerError, match=r"the last: the endpoint answered HTTP 503 .*\n    hint: the model server "
                                           r"failed, or its reply was no chat completion; its own log says why$"):
        OpenAICompatiblePlanner(_url(model_server), "m", timeout=10).propose("season", UNKNOWN, {})
    model_server.replies = [(429, "slow down")]
    with pytest.raises(PlannerError, match=r"HTTP 429 .*\n    hint: the model server limits the rate: a longer "
                                           r"planner latency asks less often$"):
        OpenAICompatiblePlanner(_url(model_server), "m", timeout=10).propose("season", UNKNOWN, {})


def test_an_answer_that_trickles_in_is_given_up_at_the_timeout(model_server):
    model_server.replies = [("trickle", "")]
    planner = OpenAICompatiblePlanner(_url(model_server), "m", timeout=0.5, attempts=1)
    try:
        with pytest.raises(PlannerError, match=r"gave no answer: the answer did not come whole within the timeout"):
            planner.propose("season", UNKNOWN, {})
    finally:
        model_server.let_go.set()


def test_credentials_in_the_url_are_refused_and_not_quoted():
    with pytest.raises(ValueError, match=r"credentials in the URL are not sent; give the key in \$OPENAI_API_KEY") \
            as refused:
        OpenAICompatiblePlanner("http://user:s3cret@127.0.0.1:8000/v1", "m")
    assert "s3cret" not in str(refused.value) and "user" not in str(refused.value)


@pytest.mark.parametrize("status, hint", [
    (401, r"hint: set the endpoint's API key in \$OPENAI_API_KEY"),
    (404, r"hint: the base URL ends where /chat/completions is appended \(usually /v1\)"),
    (400, r"hint: check the model name 'm' and the URL"),
])
def test_a_refused_request_is_not_asked_again(model_server, status, hint):
    model_server.replies = [(status, '{"error": "no"}')]
    url = _url(model_server)
    with pytest.raises(PlannerError, match=rf"^planner endpoint {url} refused the request: HTTP {status} .*"
                                           rf"""'{{"error": "no"}}'\n    {hint}$"""):
        OpenAICompatiblePlanner(url, "m", timeout=10).propose("season", UNKNOWN, {})
    assert len(model_server.seen) == 1


def test_a_redirect_is_not_followed_so_the_key_goes_nowhere_else(model_server, monkeypatch):
    monkeypatch.setenv("OPENAI_API_KEY", "sk-test")
    elsewhere, thread = _serve()
    try:
        target = f"{_url(elsewhere)}/chat/completions"
        model_server.replies = [(302, "", target)]
        with pytest.raises(PlannerError, match=rf"redirects to '{target}'\n    hint: give the URL it redirects to"):
            OpenAICompatiblePlanner(_url(model_server), "m", timeout=10).propose("season", UNKNOWN, {})
        assert len(model_server.seen) == 1 and elsewhere.seen == []
    finally:
        elsewhere.shutdown()
        elsewhere.server_close()
        thread.join()


def test_an_unreachable_endpoint_and_a_bad_planner_name_say_what_to_do():
    with pytest.raises(PlannerError, match=r"^planner endpoint http://127.0.0.1:9/v1 gave no answer: .*\n"
                                           r"    hint: is the model server still up\?"):
        OpenAICompatiblePlanner("http://127.0.0.1:9/v1", "m", timeout=2).propose("s", {}, {})
    with pytest.raises(ValueError, match="openai:<base_url>#<model>"):
        make_planner("gpt")
    for url in ("file:///etc/passwd", "http:///v1", "ftp://host/v1"):
        with pytest.raises(ValueError, match=r"must be an http:// or https:// URL with a host"):
            OpenAICompatiblePlanner(url, "m")
    with pytest.raises(ValueError, match=r"attempts=0 must be an integer >= 1"):
        OpenAICompatiblePlanner("http://localhost/v1", "m", attempts=0)
    with pytest.raises(AnswerRefused, match="the answer is not text but NoneType"):
        check_answer(None)


class _NotHttp(socketserver.BaseRequestHandler):
    def handle(self):
        self.request.recv(65536)
        self.request.sendall(b"SSH-2.0-OpenSSH_9.2\r\n")


def test_a_server_that_does_not_speak_http_gives_no_answer_at_once():
    server = socketserver.TCPServer(("127.0.0.1", 0), _NotHttp)
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    try:
        url = f"http://127.0.0.1:{server.server_address[1]}/v1"
        with pytest.raises(PlannerError, match=rf"^planner endpoint {url} gave no answer: .*SSH-2.0"):
            OpenAICompatiblePlanner(url, "m", timeout=10).propose("s", {}, {})
    finally:
        server.shutdown()
        server.server_close()
        thread.join()


def test_an_answer_with_words_around_its_json_is_taken():
    assert check_answer("Here is my plan:\n" + json.dumps(PLAN) + "\nGood luck.") == PLAN["action_plan"]


def test_a_vlm_that_never_answers_a_plan_ends_the_episode_naming_the_endpoint_and_its_answer(model_server):
    """In the agent: each request is tried three times, two requests in a row that get no plan
    end the episode, and the monitor's last word names the endpoint and the answer (the monitor
    asked again every planner latency until the episode's time ran out)."""
    from agents.demo import ending
    from agents.episode import summarize
    from agents.retriever0 import build

    model_server.replies = ["I would open the top-left drawer."]
    url = _url(model_server)
    pipe = build(seed=0, drawer="TR", planner=f"openai:{url}#m", planner_latency=0.5)
    episode = summarize(pipe.run(duration=30.0, backend="inproc"), pipe.build_ir())
    assert len(model_server.seen) == 2 * 3
    assert episode.duration < 5.0 and episode.ignored["bad_plans"] == 2
    assert ending(episode) == (f"gave up (no plan for 2 requests in a row: planner {url} (model m) gave no plan in "
                               "3 attempts; the last: the answer is not JSON (Expecting value: line 1 column 1 "
                               "(char 0)): 'I would open the top-left drawer.')")
    for _, _, body in model_server.seen:                # every request shows the model the head camera's view
        assert _png(body["messages"][1]["content"][1]["image_url"]["url"]).shape == (96, 128, 3)


def test_a_run_with_a_model_and_a_teleop_file_replays_without_either(model_server, tmp_path):
    """The planner behind an endpoint and the teleop schedule consult the world outside the
    program: their flows are replayed from the log (replay="log"), so the replay calls no
    endpoint and reads no file, and re-executes every other flow against what they said."""
    from agents.retriever0 import build
    from retriever import read_log
    from retriever.replay import replay

    model_server.replies = [json.dumps({"action_plan": ["OpenDrawer(TL-H) -> InspectDrawer(TL) -> CloseDrawer(TL-H)"]})]
    schedule = tmp_path / "teleop.json"
    schedule.write_text(json.dumps([{"t_start": 1.0, "payload": "OpenDrawer(TR-H)"}]))
    pipe = build(seed=0, drawer="TR", planner=f"openai:http://127.0.0.1:{model_server.server_port}/v1#m",
                 planner_latency=0.5, teleop=str(schedule))
    log = tmp_path / "run.mcap"
    trace = pipe.run(duration=8.0, backend="inproc", log=str(log))
    asked = len(model_server.seen)
    assert asked >= 1 and any(e.value.payload == "OpenDrawer(TR-H)" for e in trace.events_of("teleop", "teleop"))
    # the model saw the head camera's frame that the planner's tick consumed (Latest)
    frames = {e.id: e.value for e in trace.events_of("head_camera", "frame")}
    ticks = [s for s in trace.steps_of("planner") if s.status == "ok"]
    assert len(ticks) == asked
    for tick, (_, _, body) in zip(ticks, model_server.seen):
        (frame_id,) = tick.consumed["frame"]
        assert np.array_equal(_png(body["messages"][1]["content"][1]["image_url"]["url"]), frames[frame_id].rgb)
    schedule.unlink()
    model_server.replies = ["the endpoint answers something else today"]
    report = replay(read_log(log))
    assert report.identical and len(model_server.seen) == asked
    assert report.nodes["planner"].from_log and report.nodes["teleop"].from_log
    assert report.nodes["monitor"].replayed > 0 and report.nodes["monitor"].divergent == 0
