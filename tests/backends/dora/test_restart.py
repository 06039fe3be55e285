"""on_error="restart" on dora: dora starts a dataflow's processes once, so a flow restarts in
place, in its process, as a group's member does on zenoh (zenoh/node/in_place.py,
tests/backends/zenoh/test_group_restart.py): a group's member in its group's dora node, and a flow
alone as a group of one (DoraHosting.groups_of_one), whose dora node, outputs, pid and log are a
lone flow's. (Lockstep virtual time, where the zenoh tests compare with inproc, is not dora's.)"""

from __future__ import annotations

import re

import pytest
import yaml

from retriever import Latest, Pipeline, Rate, RestartLimitError, Trigger, read_log
from retriever.backends.dora.dataflow import DoraNames, dataflow_yaml
from retriever.replay import replay

from ..zenoh.restart_flows import CountedSink, CountingSource, FailingMiddle
from ..zenoh.test_group_restart import chain, set_ups
from .test_dora import _nothing_left


def _restarted_once(trace, pid: int) -> None:
    """mid failed at x=5 and a fresh flow, set up again in the process ``pid``, went on from the
    next tick, nothing skipped; counted as one restart."""
    assert set_ups(trace, "mid") == [{"set_ups": 1, "pid": pid}, {"set_ups": 2, "pid": pid}]
    mid = trace.steps_of("mid")
    errors = [s for s in mid if s.status == "error"]
    assert [s.detail["error"] for s in errors] == ["ValueError: boom at x=5"]
    assert errors[0].detail["on_error"] == "restart"
    assert set_ups(trace, "mid")[1] == mid[mid.index(errors[0]) + 1].detail["flow"]
    reports = trace.values_of("mid", "report")
    xs = [r["x"] for r in reports]
    assert xs == [x for x in range(len(xs) + 1) if x != 5], xs
    assert [r["calls"] for r in reports[:6]] == [1, 2, 3, 4, 5, 1]  # (x=6: the fresh flow's first call)


def test_a_lone_flow_is_a_group_of_one_whose_dataflow_is_a_lone_flows():
    """Its dora node, outputs and inputs, named as a lone flow's: the dataflow is the same."""
    ir = chain(fail_at=[5], process=None).compile().to_ir().doc
    alone, of_one = DoraNames.of(ir), DoraNames.of(ir, {"mid": ["mid"]})
    assert of_one == alone
    assert of_one.processes({"mid": ["mid"]}) == alone.processes({}) == {"src": "src", "mid": "mid", "sink": "sink"}
    assert (dataflow_yaml("c", of_one, "/venv/bin/python", "/run/spec.json", "/src")
            == dataflow_yaml("c", alone, "/venv/bin/python", "/run/spec.json", "/src"))
    doc = yaml.safe_load(dataflow_yaml("c", of_one, "/venv/bin/python", "/run/spec.json", "/src"))
    mid = next(n for n in doc["nodes"] if n["id"] == "mid")
    assert mid["outputs"] == ["report", "progress", "warm"]
    assert sorted(mid["inputs"]) == ["src__progress", "src__value", "src__warm"]


def test_a_lone_flow_restarts_in_place_in_its_own_process(tmp_path):
    pipe = chain(fail_at=[5], process=None)
    path = tmp_path / "run.mcap"
    pipe.run(duration=2.0, backend="dora", log=path, quiet=True)
    pids = pipe.session.worker_pids()
    assert len(set(pids.values())) == 3, pids  # each flow in its own process: mid's alone
    log = read_log(path)
    trace = log.trace()  # (the set-ups, as the log says them)
    _restarted_once(trace, pids["mid"])
    assert set_ups(trace, "src") == [{"set_ups": 1, "pid": pids["src"]}]
    assert set_ups(trace, "sink") == [{"set_ups": 1, "pid": pids["sink"]}]
    # the neighbours: every tick ran, every event of mid reached sink, in order
    src = trace.steps_of("src")
    assert len(src) == 40 and all(s.status == "ok" for s in src)
    got = [s.consumed["x"][0] for s in trace.steps_of("sink") if s.consumed]
    produced = [e.id for e in trace.events_of("mid", "report")]
    assert got == produced[:len(got)] and len(got) >= len(produced) - 1, (got, produced)
    # counted as a restart is; no process was lost (none started afresh)
    assert pipe.counts()["restarts"] == 1
    assert pipe.stats()["mid"].counts.get("restarts") == 1
    assert log.faults == []
    assert {s.node for s in trace.steps} == {"src", "mid", "sink"}
    report = replay(log)
    assert report.identical, report.divergences[:3]
    _nothing_left(pipe.session)


def test_a_group_member_restarts_in_place_and_its_neighbour_steps_on(tmp_path):
    """src alone; mid (on_error="restart") and sink in the process "g": mid restarts there,
    sink, its neighbour in the process, is set up once and steps on."""
    with Pipeline("dora_group_restart") as pipe:
        src = CountingSource().configure(name="src") @ Rate(hz=20)
        mid = FailingMiddle(fail_at=[5]).configure(name="mid", process="g", on_error="restart") @ Trigger("x")
        sink = CountedSink().configure(name="sink", process="g") @ Trigger("x")
        src.then(mid, sync=Latest(), map={"value": "x"})
        mid.then(sink, sync=Latest(), map={"report": "x"})
    path = tmp_path / "run.mcap"
    pipe.run(duration=2.0, backend="dora", log=path, quiet=True)
    pids = pipe.session.worker_pids()
    assert pids["mid"] == pids["sink"] != pids["src"], pids
    log = read_log(path)
    trace = log.trace()
    _restarted_once(trace, pids["mid"])
    assert set_ups(trace, "sink") == [{"set_ups": 1, "pid": pids["mid"]}]
    assert all(s.status == "ok" for s in trace.steps_of("sink"))
    got = [s.consumed["x"][0] for s in trace.steps_of("sink") if s.consumed]
    produced = [e.id for e in trace.events_of("mid", "report")]
    assert got == produced[:len(got)] and len(got) >= len(produced) - 1, (got, produced)
    assert pipe.counts()["restarts"] == 1
    assert "restarts" not in pipe.stats()["sink"].counts and "restarts" not in pipe.stats()["src"].counts
    report = replay(log)
    assert report.identical, report.divergences[:3]
    _nothing_left(pipe.session)


def test_past_its_budget_the_run_stops_as_on_zenoh():
    """mid fails at x=3 and x=6 with one restart allowed: alone or in a group, on dora, the run
    stops with the RestartLimitError zenoh's does (the same text but for the tick's tag)."""
    messages = []
    for backend, process in (("dora", None), ("dora", "chain"), ("zenoh", None)):
        pipe = chain(fail_at=[3, 6], process=process, max_restarts=1, restart_window=10.0)
        with pytest.raises(RestartLimitError, match=r"^flow 'mid' failed again after 1 restart\(s\) within 10 s "
                                                    r"\(max_restarts=1, restart_window=10\): ValueError: boom at x=6 "
                                                    r"\(tick at ") as raised:
            pipe.run(duration=3.0, backend=backend, quiet=True)
        assert raised.value.node == "mid"
        assert pipe.stats()["mid"].counts.get("restarts") == 1
        messages.append(re.sub(r"\(tick at [^)]*\)", "(tick at …)", str(raised.value)))
        if backend == "dora":
            _nothing_left(pipe.session)
    assert messages[0] == messages[1] == messages[2], messages
