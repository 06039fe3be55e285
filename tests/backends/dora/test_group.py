"""Flows that share a process (``configure(process=NAME)``) on the dora backend: the group is one
dora node, with its members' inputs and outputs from and to nodes outside it; between members,
events stay in the process (backends/zenoh/node/group.py), as on the zenoh backend
(tests/backends/zenoh/test_group.py). The conformance suite's real-time part runs grouped on dora
too (test_let_conformance.py, "dora-grouped")."""

from __future__ import annotations

import pytest
import yaml

from retriever import Latest, Pipeline, Rate, StepError, Trigger, read_log
from retriever.backends.dora.dataflow import PROGRESS, QUEUE_SIZE, WARM, DoraNames, dataflow_yaml
from retriever.replay import replay

from ..test_conformance import Echo, EchoOpt, Source
from ..zenoh.lifecycle_flows import Counter
from ..zenoh.test_group import grouped_pipeline
from .dora_flows import Raises
from .test_dora import _nothing_left

QUEUE = {"queue_size": QUEUE_SIZE, "queue_policy": "backpressure"}


def _grouped(name: str = "grouped") -> Pipeline:
    """src ──value──▶ echo, hyb; echo ──saw──▶ slow ──saw──▶ sink: LET everywhere (its trace is
    inproc's), echo, hyb and slow in the process "mid", src and sink each in its own."""
    with Pipeline(name, deadline=5.0) as pipe:
        src = Source().named("src").configure(latency=0.01) @ Rate(20)
        echo = Echo().named("echo").configure(latency=0.005, process="mid") @ Trigger("x")
        hyb = EchoOpt().named("hyb").configure(latency=0.02, process="mid") @ Rate(10, offset=0.005)
        slow = EchoOpt().named("slow").configure(latency=0.02, process="mid") @ Rate(10, offset=0.015)
        sink = EchoOpt().named("sink").configure(latency=0.005) @ Trigger("x")
        src.then(echo, sync=Latest(), map={"value": "x"})
        src.then(hyb, sync=Latest(), map={"value": "x"})
        echo.then(slow, sync=Latest(), map={"saw": "x"})
        slow.then(sink, sync=Latest(), map={"saw": "x"})
    return pipe


GROUPS = {"mid": ["echo", "hyb", "slow"]}


# ---------------------------------------------------------------------------------------------
# The dataflow
# ---------------------------------------------------------------------------------------------
def test_a_group_is_one_dora_node_with_its_members_inputs_and_outputs_but_none_between_them():
    names = DoraNames.of(_grouped().compile().to_ir().doc, GROUPS)
    assert names.nodes == {"src": "src", "echo": "mid", "hyb": "mid", "slow": "mid", "sink": "sink"}
    assert names.members("mid") == ["echo", "hyb", "slow"] and names.members("src") == ["src"]
    assert names.processes(GROUPS) == {"src": "src", "sink": "sink", "mid": "mid"}
    # echo's events go to slow only, in the process: no dora output; slow's go to sink over dora
    assert names.outputs["echo"] == {} and names.outputs["slow"] == {"saw": "slow__saw"}
    assert names.progress == {"src": PROGRESS, "slow": f"slow__{PROGRESS}"}
    assert names.inputs["slow"] == {} and names.inputs["echo"] == names.inputs["hyb"] == {
        "src__value": ["src", "value"], "src__progress": ["src", None]}
    doc = yaml.safe_load(dataflow_yaml("grouped", names, "/venv/bin/python", "/run/spec.json", "/src"))
    nodes = {n["id"]: n for n in doc["nodes"]}
    assert sorted(nodes) == ["mid", "sink", "src"]
    assert nodes["mid"]["args"] == "-m retriever.backends.dora.node /run/spec.json mid"
    assert nodes["mid"]["outputs"] == ["slow__saw", f"slow__{PROGRESS}", WARM]
    # one input for the stream two members consume
    assert nodes["mid"]["inputs"] == {"src__value": {"source": "src/value", **QUEUE},
                                      "src__progress": {"source": "src/progress", **QUEUE},
                                      "src__warm": {"source": "src/warm", **QUEUE}}
    assert nodes["sink"]["inputs"] == {"mid__slow__saw": {"source": "mid/slow__saw", **QUEUE},
                                       "mid__slow__progress": {"source": "mid/slow__progress", **QUEUE},
                                       "mid__warm": {"source": "mid/warm", **QUEUE}}
    # a group's warm-up output brings the warm-ups of the members the consumer hears
    assert names.warm_inputs("mid") == {"src__warm": ["src"]} and names.warm_inputs("sink") == {"mid__warm": ["slow"]}


def test_names_dora_would_refuse_in_a_group_are_renamed():
    doc = {"nodes": [{"id": "cam.left", "outputs": {"img": {}}}, {"id": "b", "outputs": {"progress": {}}},
                     {"id": "c", "outputs": {}}],
           "edges": [{"source": {"node": "cam.left", "port": "img"}, "destination": {"node": "c", "port": "x"}},
                     {"source": {"node": "b", "port": "progress"}, "destination": {"node": "c", "port": "y"}}]}
    names = DoraNames.of(doc, {"front.left": ["cam.left", "b"]})
    assert names.nodes == {"cam.left": "n0", "b": "n0", "c": "c"}
    assert names.outputs == {"cam.left": {"img": "n0__img"}, "b": {"progress": "b__o0"}, "c": {}}
    assert names.progress == {"cam.left": "n0__progress", "b": "b__progress"}
    assert names.processes({"front.left": ["cam.left", "b"]}) == {"c": "c", "front.left": "n0"}


def test_no_two_nodes_outputs_or_inputs_get_one_dora_id():
    """A renamed node's fallback id (n1) taken by a node of that name already, a renamed port's
    (o0) by a port of that name, and two streams one consumer hears named alike (node a's output
    b__c and node a__b's c, both a__b__c): each gets an id of its own, or two flows would be one
    dora node (the run failed to start) or one stream would be lost with no error."""
    def node(nid, outputs):
        return {"id": nid, "outputs": dict.fromkeys(outputs, {})}

    def edge(src, port, dst, to):
        return {"source": {"node": src, "port": port}, "destination": {"node": dst, "port": to}}

    doc = {"nodes": [node("n1", ["v"]), node("_cam", ["v"]), node("a", ["b__c", "_x", "o1"]), node("a__b", ["c"]),
                     node("c", [])],
           "edges": [edge("n1", "v", "c", "x"), edge("_cam", "v", "c", "x"), edge("a", "b__c", "c", "x"),
                     edge("a__b", "c", "c", "x"), edge("a", "_x", "c", "y"), edge("a", "o1", "c", "z")]}
    names = DoraNames.of(doc)
    assert len(set(names.nodes.values())) == 5, names.nodes
    assert len(set(names.outputs["a"].values())) == 3, names.outputs["a"]
    streams = [tuple(s) for s in names.inputs["c"].values()]
    assert len(streams) == 10 and set(streams) == {("n1", "v"), ("n1", None), ("_cam", "v"), ("_cam", None),
                                                    ("a", "b__c"), ("a", "_x"), ("a", "o1"), ("a", None),
                                                    ("a__b", "c"), ("a__b", None)}
    # a warm-up input named as a stream's (node a__b's warm output, a__b__warm, and node a's port b__warm)
    doc = {"nodes": [node("a", ["b__warm"]), node("a__b", ["c"]), node("c", [])],
           "edges": [edge("a", "b__warm", "c", "x"), edge("a__b", "c", "c", "y")]}
    names = DoraNames.of(doc)
    warm = names.warm_inputs("c")
    assert "a__b__warm" in names.inputs["c"] and sorted(warm.values()) == [["a"], ["a__b"]]
    assert len(warm) == 2 and not set(warm) & set(names.inputs["c"]), warm
    flow = {n["id"]: n for n in yaml.safe_load(dataflow_yaml("w", names, "/py", "/spec.json", "/src"))["nodes"]}
    assert len(flow["c"]["inputs"]) == 6
    # in a group's dora node too: member x's output y (g__x__y) and a lone node g__x's y
    doc = {"nodes": [node("x", ["y"]), node("w", []), node("g__x", ["y"]), node("c", [])],
           "edges": [edge("x", "y", "c", "a"), edge("g__x", "y", "c", "b")]}
    names = DoraNames.of(doc, {"g": ["x", "w"]})
    streams = [tuple(s) for s in names.inputs["c"].values()]
    assert len(streams) == 4 and set(streams) == {("g__x", None), ("g__x", "y"), ("x", None), ("x", "y")}


# ---------------------------------------------------------------------------------------------
# Runs
# ---------------------------------------------------------------------------------------------
def test_a_grouped_run_is_one_process_per_group_inprocs_trace_and_replays_identically(tmp_path):
    path = tmp_path / "run.mcap"
    pipe = _grouped()
    trace = pipe.run(duration=1.0, backend="dora", quiet=True, log=path)
    pids = pipe.session.worker_pids()
    assert pids["echo"] == pids["hyb"] == pids["slow"] and len(set(pids.values())) == 3, pids
    reference = _grouped().run(duration=1.0, backend="inproc")
    assert trace.first_difference(reference) is None and trace.digest() == reference.digest()
    assert len(trace.steps_of("sink")) == 10
    log = read_log(path)
    assert log.end["status"] == "finished" and log.run["backend"] == "dora"
    assert replay(log).identical
    _nothing_left(pipe.session)


def test_a_mixed_run_in_real_time_logs_and_replays_identically(tmp_path):
    """counter and faulty share a process, sink runs alone, no LET (outputs stamped when the step
    ends): as on zenoh (tests/backends/zenoh/test_group.py), every tick of the group's source is
    recorded, sink hears faulty's reports over dora, and the log replays identically."""
    pipe = grouped_pipeline(with_pid=False)
    path = tmp_path / "run.mcap"
    trace = pipe.run(duration=2.0, backend="dora", log=path, quiet=True)
    pids = pipe.session.worker_pids()
    assert pids["counter"] == pids["faulty"] != pids["sink"], pids
    counter = [s for s in trace.steps if s.node == "counter"]
    assert len(counter) == 40 and all(s.status == "ok" for s in counter)
    assert len([s for s in trace.steps if s.node == "sink" and s.consumed]) >= 35
    report = replay(read_log(path))
    assert report.identical, report.divergences[:3]
    _nothing_left(pipe.session)


def test_a_member_whose_step_raises_stops_the_run_with_its_traceback():
    with Pipeline("raises") as pipe:
        src = Counter().configure(process="both") @ Rate(hz=20)
        bad = Raises(at=3).named("bad").configure(process="both") @ Trigger()
        src.then(bad, sync=Latest())
    with pytest.raises(StepError, match=r"bad\.step\(\) raised RemoteError: ValueError: third time(.|\n)*"
                                        r"worker traceback:(.|\n)*dora_flows\.py"):
        pipe.run(duration=5.0, backend="dora", quiet=True)
    _nothing_left(pipe.session)
