"""After a run, a flow that skipped every tick for an input that never had an event is named,
with the port and the edge that should have fed it (issue 41: a misspelled port ran silently)."""

from __future__ import annotations

import re
import warnings

import pytest

from retriever import Flow, Pipeline, Rate, StarvedFlowWarning

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
