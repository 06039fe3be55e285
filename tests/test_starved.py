"""After a run, a flow that skipped every tick for an input that never had an event is named,
with the port and the edge that should have fed it (issue 41: a misspelled port ran silently)."""

from __future__ import annotations

import re
import warnings

import pytest

from dataclasses import dataclass
from typing import Optional

from retriever import ActionChunking, Flow, LatestDistinct, Pipeline, Rate, StarvedFlowWarning, Trigger, io

from .starved_flows import Camera, MisspeltCamera, camera_policy_controller
from .test_cli import cli, write

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
