"""After a run, a flow that skipped every tick for an input that never had an event is named,
with the port and the edge that should have fed it (issue 41: a misspelled port ran silently)."""

from __future__ import annotations

import re
import warnings

import pytest

from dataclasses import dataclass
from typing import Optional

from retriever import ActionChunking, Flow, LatestDistinct, Pipeline, Rate, StarvedFlowWarning, Trigger, io

from .starved_flows import Camera, MisspeltCamera, camera_policy_controller, stale_viewer
from .test_cli import ROOT, cli, write

POLICY_STARVED = (r"pipeline 'agent': policy stepped 0 of 5 ticks: input 'image' never had an event \(edge cam → "
                  r"policy, output 'image' was never produced; cam produced 'imgae', which no edge reads\)")
CONTROLLER_STARVED = (r"pipeline 'agent': controller stepped 0 of 20 ticks: input 'chunk' never had an event "
                      r"\(edge policy → controller, policy never stepped\)")


def _starved(record) -> list[str]:
    return [str(w.message) for w in record if issubclass(w.category, StarvedFlowWarning)]


@pytest.mark.parametrize("backend", ["inproc", "zenoh"])
def test_a_misspelled_output_port_is_named_at_the_end_of_the_run(backend):
    with pytest.warns(StarvedFlowWarning) as record:
        camera_policy_controller(MisspeltCamera()).run(duration=1.0, backend=backend, keep="counters")
    policy, controller = _starved(record)
    assert re.fullmatch(POLICY_STARVED, policy), policy
    assert re.fullmatch(CONTROLLER_STARVED, controller), controller


def test_a_pipeline_whose_flows_step_gets_no_warning():
    with warnings.catch_warnings():
        warnings.simplefilter("error", StarvedFlowWarning)
        trace = camera_policy_controller(Camera()).run(duration=1.0)
    assert trace.steps_of("controller")


def test_a_required_port_without_an_edge_is_named():
    class Lonely(Flow):
        def step(self, image):
            return None

    with Pipeline("p") as pipe:
        Lonely() @ Rate(hz=10)
    with pytest.warns(StarvedFlowWarning, match=r"lonely stepped 0 of 10 ticks: input 'image' has no incoming edge"):
        pipe.run(duration=1.0)


def test_a_flow_that_skips_every_tick_for_another_reason_is_named_with_where_to_look():
    class Late(Flow):
        def step(self):
            return {"x": 1.0}

    class Strict(Flow):
        def step(self, x):
            return None

    from retriever import Exact

    with Pipeline("p") as pipe:
        (Late() @ Rate(hz=10, offset=0.01)).then(Strict() @ Rate(hz=10), sync=Exact())
    with pytest.warns(StarvedFlowWarning, match=r"strict stepped 0 of 10 ticks: every tick was skipped, each for a "
                                                r"missing input\n    hint: its step records name the port"):
        pipe.run(duration=1.0)


def test_the_cli_prints_the_warning_under_the_run_table(tmp_path):
    script = write(tmp_path / "agent.py", "from tests.starved_flows import MisspeltCamera, camera_policy_controller\n"
                                          "pipe = camera_policy_controller(MisspeltCamera())\n")
    result = cli("run", str(script), "--duration", "1")
    assert result.returncode == 0, result.stderr
    lines = result.stderr.splitlines()
    assert re.fullmatch("warning: " + POLICY_STARVED, lines[0]), result.stderr
    assert re.fullmatch("warning: " + CONTROLLER_STARVED, lines[1]), result.stderr
    assert "policy " in result.stdout  # the table came first, on stdout


class _Misspelt(Flow):
    def step(self):
        out = {"imgae": 1.0}
        return out


class _Good(Flow):
    def step(self):
        out = {"image": 2.0}
        return out


def test_a_trigger_clocked_consumer_that_never_ticked_for_a_misspelled_port_is_named():
    class Viewer(Flow):
        def step(self, image):
            return None

    with Pipeline("p") as pipe:
        (_Misspelt().configure(name="cam") @ Rate(hz=10)).then(Viewer() @ Trigger("image"))
    with pytest.warns(StarvedFlowWarning, match=r"^pipeline 'p': viewer never ticked: its trigger input 'image' never "
                                                r"had an event \(edge cam → viewer, output 'image' was never produced; "
                                                r"cam produced 'imgae', which no edge reads\)$"):
        pipe.run(duration=1.0)


def test_an_edge_a_typo_left_empty_is_named_in_a_fan_in_and_into_an_optional_port():
    class Fuser(Flow):
        def step(self, image):
            return None

    class Optional_(Flow):
        def step(self, image: Optional[float] = None):
            return None

    with Pipeline("p") as pipe:
        bad, good = _Misspelt().configure(name="bad") @ Rate(hz=10), _Good().configure(name="good") @ Rate(hz=10)
        fuser = Fuser() @ Rate(hz=10)
        bad.then(fuser)
        good.then(fuser)
        bad.then(Optional_().configure(name="optional") @ Rate(hz=10))
    with pytest.warns(StarvedFlowWarning) as record:
        pipe.run(duration=1.0)
    assert _starved(record) == [
        "pipeline 'p': edge bad → fuser carried no event: bad never produced 'image', and produced 'imgae', which no "
        "edge reads",
        "pipeline 'p': edge bad → optional carried no event: bad never produced 'image', and produced 'imgae', which "
        "no edge reads"]


def test_no_warning_for_a_short_run_a_sparse_output_or_a_consumer_that_skips_by_design():
    class Camera(Flow):
        def step(self):
            return {"image": 1.0}

    class Alarm(Flow):
        def step(self, image):
            return None if image < 2 else {"alarm": True}  # never fires in this run

    class Siren(Flow):
        def step(self, alarm):
            return None

    class Policy(Flow):
        def step(self, image):
            return {"chunk": [image]}

    class Controller(Flow):
        def step(self, chunk):
            return None

    with Pipeline("p") as pipe:
        cam = Camera() @ Rate(hz=30)
        cam.then(Alarm() @ Rate(hz=30)).then(Siren() @ Rate(hz=10), sync=LatestDistinct())
        cam.then(Policy().configure(latency=0.3) @ Rate(hz=2)).then(Controller() @ Rate(hz=200),
                                                                      sync=ActionChunking())
    with warnings.catch_warnings():
        warnings.simplefilter("error", StarvedFlowWarning)
        pipe.run(duration=0.5)  # the policy's one tick came before any frame: nothing to say yet
        pipe.run(duration=2.0)


def test_no_warning_for_a_sparse_output_beside_a_port_no_edge_reads():
    """A typed (or dict-literal) producer's ports are known before the run: one that never fired
    beside a logged-only port is a sparse output, not a typo."""
    @io
    @dataclass
    class Detection:
        debug: float
        alarm: Optional[int] = None

    class Detector(Flow[None, Detection]):
        def step(self, inp):
            return Detection(debug=1.0)

    class Literal(Flow):
        def step(self):
            if self is None:  # never: its keys are read from its returns, both dict literals
                return {"alarm": 1}
            return {"debug": 1.0}

    class OnAlarm(Flow):
        def step(self, alarm):
            return None

    for producer in (Detector, Literal):
        with Pipeline("p") as pipe:
            source = producer() @ Rate(hz=10)
            source.then(OnAlarm() @ Rate(hz=10))
            source.then(OnAlarm().configure(name="on_trigger") @ Trigger("alarm"))
        with warnings.catch_warnings():
            warnings.simplefilter("error", StarvedFlowWarning)
            pipe.run(duration=2.0)


def test_the_cli_names_a_starved_flow_of_a_run_that_was_interrupted(tmp_path):
    # the interrupt comes from a step (at the camera's 21st tick), where a test can place it
    script = write(tmp_path / "agent.py", "from tests.starved_flows import InterruptedCamera, camera_policy_controller\n"
                                          "pipe = camera_policy_controller(InterruptedCamera())\n")
    result = cli("run", str(script), "--duration", "inf")
    assert result.returncode == 130, result.stderr
    assert "interrupted" in result.stderr
    assert re.search("^warning: " + POLICY_STARVED.replace("0 of 5", "0 of 11"), result.stderr, re.M), result.stderr


# ---------------------------------------------------------------------------------------------
# During a run: an input that had no event for long while its producer made events (issue 40)
# ---------------------------------------------------------------------------------------------
MS = 1_000_000


def _watched_pair():
    from retriever.starved import StarvationWatch

    pipe = stale_viewer(1.0)
    return StarvationWatch(pipe.compile())


def _feed(watch, start_ms: int, end_ms: int, viewer_detail, camera_makes: bool = True, seq0: int = 0) -> int:
    """20 Hz ticks of both from ``start_ms`` to ``end_ms``, the camera's first; the next seq."""
    seq = seq0
    for t in range(start_ms, end_ms, 50):
        watch.step("cam", (t * MS, 0), (("cam", "image", seq),) if camera_makes else (), None)
        seq += camera_makes
        watch.step("viewer", (t * MS, 0), (), viewer_detail)
    return seq


def test_an_input_without_events_while_its_producer_makes_them_is_starved_after_a_while_then_fed():
    from retriever.starved import STARVED_AFTER_NS

    watch = _watched_pair()
    seq = _feed(watch, 0, 1000, None)
    assert watch.news == [] and watch.episodes == []
    # from 1 s, no event; the first tick after that sees the camera's next one made (1.05 s)
    seq = _feed(watch, 1000, 1050 + STARVED_AFTER_NS // MS, {"incomplete": ["image"], "missing": ["image"]},
                seq0=seq)
    assert watch.news == []  # a tick short of STARVED_AFTER_NS: not yet
    seq = _feed(watch, 4050, 4100, {"incomplete": ["image"]}, seq0=seq)
    (what, episode), = watch.news
    assert what == "starved" and episode == {"node": "viewer", "port": "image", "producers": ["cam.image"],
                                             "since_ns": 1000 * MS, "until_ns": None, "ticks": 62, "produced": 62}
    watch.news.clear()
    seq = _feed(watch, 4100, 6000, {"missing": ["image"]}, seq0=seq)
    assert watch.news == [] and episode["ticks"] == 100 and episode["produced"] == 100
    _feed(watch, 6000, 6100, None, seq0=seq)
    assert watch.news == [("fed", episode)] and episode["until_ns"] == 6000 * MS
    assert watch.episodes == [episode]


def test_no_input_starves_while_its_producer_makes_nothing_or_for_less_than_the_while():
    watch = _watched_pair()
    _feed(watch, 0, 10_000, {"missing": ["image"]}, camera_makes=False)  # a quiet producer: a sparse output
    seq = _feed(watch, 10_000, 12_900, {"incomplete": ["image"]})  # 2.9 s, then an event
    _feed(watch, 12_900, 13_000, None, seq0=seq)
    _feed(watch, 13_000, 20_000, {"incomplete": "image", "missing": [7]}, seq0=seq)  # garbage: no port named
    assert watch.news == [] and watch.episodes == []


def test_a_flow_starved_in_a_real_time_run_is_warned_of_during_it_marked_in_the_table_and_logged(tmp_path):
    """On zenoh: the viewer's frames are always older than its policy takes, the camera makes
    one every tick. The coordinator says so while the run goes on; the log keeps the span, the
    CLI's table marks the viewer, and `retriever log info` shows it."""
    import os
    import subprocess
    import sys

    from retriever import read_log

    log = tmp_path / "run.mcap"
    script = write(tmp_path / "stale.py", "from tests.starved_flows import stale_viewer\npipe = stale_viewer(0.001)\n")
    env = {k: v for k, v in os.environ.items() if k not in ("FORCE_COLOR", "PYTHONPATH")}
    env.update(NO_COLOR="1", TERM="dumb", COLUMNS="200", PYTHONIOENCODING="utf-8", PYTHONPATH=str(ROOT))
    proc = subprocess.Popen([sys.executable, "-m", "retriever.cli", "run", f"{script}:pipe", "--backend", "zenoh",
                             "--duration", "6", "--log", str(log)], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True, cwd=str(ROOT), env=env)
    try:
        warned = None
        for line in proc.stderr:
            if "is starved" in line:
                warned = line
                break
        running_when_warned = proc.poll() is None and not log_finished(log)
        out, err = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert warned is not None and warned.startswith(
        "retriever: warning: node 'viewer' is starved: its input 'image' has had no event since t=0.000 s"), err
    assert running_when_warned, "the warning came only once the run was over"
    assert proc.returncode == 0, err
    row = next(line for line in out.splitlines() if "│ viewer" in line)
    assert "image from 0 s" in row, out
    (episode,) = read_log(log).starved
    assert episode["node"] == "viewer" and episode["port"] == "image" and episode["producers"] == ["cam.image"]
    # to the end of the 6 s run: past the 3 s it takes to be named (a loaded machine may skip a few ticks)
    assert episode["since_ns"] == 0 and episode["until_ns"] is None and episode["ticks"] >= 80
    assert episode["produced"] >= 80
    info = cli("log", "info", str(log))
    assert "starved  viewer: input 'image' had no event from t=0 s to the end" in info.stdout, info.stdout


def log_finished(path) -> bool:
    from retriever import read_log

    try:
        return read_log(path).end is not None
    except Exception:  # not written to its end yet
        return False


class SwitchingSource(Flow):
    """Untyped: ``x`` for its first 20 ticks, then ``y`` (a dict built in a variable: no port is
    known before the run)."""

    def __init__(self):
        self.k = 0

    def step(self):
        self.k += 1
        out = {}
        out["x" if self.k <= 20 else "y"] = self.k
        return out


class ExactSink(Flow):
    def step(self, x):
        return None


def test_an_output_that_was_produced_is_not_said_never_produced():
    """src made 'x' 20 times (then 'y'); sink, half a period off src's ticks with Exact(), never had
    one. The warning said "output 'x' was never produced; src produced 'y'": false."""
    from retriever import Exact

    with Pipeline("switching") as pipe:
        src = SwitchingSource() @ Rate(hz=10)
        sink = ExactSink() @ Rate(hz=10, offset=0.05)
        src.then(sink, sync=Exact(), map={"x": "x"})
    with pytest.warns(StarvedFlowWarning) as record:
        pipe.run(duration=10.0, keep="counters")
    (message,) = _starved(record)
    assert "never produced" not in message and "exact_sink stepped 0 of 100 ticks: every tick was skipped" in message, \
        message


def test_a_starved_inputs_producers_events_are_counted_by_their_tags_not_as_they_arrived():
    """The producer's first second of records (its events from t=0) arrives before the consumer's
    first record: its events still count as made while the input had none (it said 10 of 20)."""
    from retriever.starved import STARVED_AFTER_NS

    watch = _watched_pair()
    for t in range(0, 1000, 50):
        watch.step("cam", (t * MS, 0), (("cam", "image", t // 50),), None)
    for t in range(0, 1000 + STARVED_AFTER_NS // MS + 100, 50):
        if t >= 1000:
            watch.step("cam", (t * MS, 0), (("cam", "image", t // 50),), None)
        watch.step("viewer", (t * MS, 0), (), {"missing": ["image"]})
    (what, episode), = watch.news
    assert what == "starved" and episode["since_ns"] == 0 and episode["produced"] == episode["ticks"] == 82, episode
