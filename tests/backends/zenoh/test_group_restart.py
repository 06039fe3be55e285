"""A group's member with on_error="restart" restarts in place (node/in_place.py): a fresh flow,
set up again in the group's process, goes on in its loop; its neighbours step on untouched; the
coordinator counts the restart; the log replays; past its budget the run stops as a lone flow's."""

from __future__ import annotations

import re

import pytest

import retriever
from retriever import Latest, Pipeline, Rate, RestartLimitError, Trigger
from retriever.replay import replay

from .restart_flows import CountedSink, CountingSource, FailingMiddle, MadeOnce, SetUpOnce


def chain(fail_at: list, process: str | None = "chain", **budget) -> Pipeline:
    """src @ 20 Hz -> mid (raises on the inputs in ``fail_at``, on_error="restart") -> sink, all
    three in the process ``process`` (None: each alone)."""
    with Pipeline("group_restart") as pipe:
        src = CountingSource().configure(name="src", process=process) @ Rate(hz=20)
        mid = FailingMiddle(fail_at=fail_at).configure(name="mid", process=process, on_error="restart",
                                                       **budget) @ Trigger("x")
        sink = CountedSink().configure(name="sink", process=process) @ Trigger("x")
        src.then(mid, sync=Latest(), map={"value": "x"})
        mid.then(sink, sync=Latest(), map={"report": "x"})
    return pipe


def set_ups(trace, node: str) -> list[dict]:
    """What ``node``'s setups said (restart_flows.SetUpCounted), in order."""
    return [s.detail["flow"] for s in trace.steps_of(node) if s.detail and "flow" in s.detail]


def test_a_member_restarts_in_place_and_its_neighbours_step_on(tmp_path):
    pipe = chain(fail_at=[5])
    path = tmp_path / "run.mcap"
    trace = pipe.run(duration=2.0, backend="zenoh", log=path, quiet=True)
    pids = pipe.session.worker_pids()
    assert pids["src"] == pids["mid"] == pids["sink"], pids
    pid = pids["mid"]
    # mid was set up twice, in the group's process; its neighbours once
    assert set_ups(trace, "mid") == [{"set_ups": 1, "pid": pid}, {"set_ups": 2, "pid": pid}]
    assert set_ups(trace, "src") == [{"set_ups": 1, "pid": pid}]
    assert set_ups(trace, "sink") == [{"set_ups": 1, "pid": pid}]
    # the failed tick, then a fresh flow from the next tick on, with nothing skipped
    mid = trace.steps_of("mid")
    errors = [s for s in mid if s.status == "error"]
    assert [s.detail["error"] for s in errors] == ["ValueError: boom at x=5"]
    assert errors[0].detail["on_error"] == "restart"
    assert set_ups(trace, "mid")[1] == mid[mid.index(errors[0]) + 1].detail["flow"]
    reports = trace.values_of("mid", "report")
    xs = [r["x"] for r in reports]
    assert xs == [x for x in range(len(xs) + 1) if x != 5], xs
    assert [r["calls"] for r in reports[:6]] == [1, 2, 3, 4, 5, 1]  # (x=6: the fresh flow's first call)
    # the neighbours: every tick ran, every event of mid reached sink, in order
    src = trace.steps_of("src")
    assert len(src) == 40 and all(s.status == "ok" for s in src)
    assert [v for v in trace.values_of("src", "value")] == list(range(40))
    got = [s.consumed["x"][0] for s in trace.steps_of("sink") if s.consumed]
    produced = [e.id for e in trace.events_of("mid", "report")]
    assert got == produced[:len(got)] and len(got) >= len(produced) - 1, (got, produced)
    # counted as a lone flow's restart is
    assert pipe.counts()["restarts"] == 1
    assert pipe.stats()["mid"].counts.get("restarts") == 1
    assert "restarts" not in pipe.stats()["src"].counts and "restarts" not in pipe.stats()["sink"].counts
    report = replay(retriever.read_log(path))
    assert report.identical, report.divergences[:3]


def test_a_member_past_its_budget_stops_the_run_as_a_lone_flow_does(capfd):
    """mid fails at x=3 and x=6 with one restart allowed: the second failure stops the run with
    the RestartLimitError a lone flow's run raises (the same text but for the tick's tag), and
    the group's process ends on its own, as a lone flow's does: it waits for no `complete` of
    its failed member, which never comes (it was killed, its stacks on the terminal)."""
    messages = []
    for process in ("chain", None):
        pipe = chain(fail_at=[3, 6], process=process, max_restarts=1, restart_window=10.0)
        with pytest.raises(RestartLimitError, match=r"flow 'mid' failed again after 1 restart\(s\) within 10 s "
                                                    r"\(max_restarts=1, restart_window=10\): ValueError: boom at x=6 "
                                                    r"\(tick at ") as raised:
            pipe.run(duration=3.0, backend="zenoh", quiet=True)
        assert raised.value.node == "mid"
        messages.append(re.sub(r"\(tick at [^)]*\)", "(tick at …)", str(raised.value)))
        assert "did not stop" not in capfd.readouterr().err
    assert messages[0] == messages[1]


def test_a_member_restarts_in_place_in_virtual_time_as_in_process():
    """In lockstep virtual time the trace is the in-process backend's, restart and all (flows
    whose records say nothing of their setups: inproc sets each up once)."""
    from .semantics_flows import Faulty, Probe, Ticker

    with Pipeline("group_restart_virtual") as pipe:
        src = Ticker().configure(name="src", process="chain") @ Rate(hz=20)
        mid = Faulty(fail_at=[5, 9], with_pid=False).configure(name="mid", process="chain",
                                                               on_error="restart") @ Trigger("x")
        sink = Probe().configure(name="sink", process="chain") @ Trigger("x")
        src.then(mid, sync=Latest(), map={"value": "x"})
        mid.then(sink, sync=Latest(), map={"report": "x"})
    reference = pipe.run(duration=1.0, backend="inproc")
    pipe.reset()
    trace = pipe.run(duration=1.0, backend="zenoh", virtual_time=True, quiet=True)
    assert len(set(pipe.session.worker_pids().values())) == 1
    assert [s.detail["error"] for s in trace.steps_of("mid") if s.status == "error"] == [
        "ValueError: boom at x=5", "ValueError: boom at x=9"]
    assert pipe.counts()["restarts"] == 2
    assert trace.first_difference(reference) is None
    assert trace.digest() == reference.digest()


def test_a_fresh_flow_whose_setup_raises_stops_the_run_saying_so():
    with Pipeline("group_restart_setup") as pipe:
        src = CountingSource().configure(name="src", process="chain") @ Rate(hz=20)
        mid = SetUpOnce(fail_at=[3]).configure(name="mid", process="chain", on_error="restart") @ Trigger("x")
        src.then(mid, sync=Latest(), map={"value": "x"})
    with pytest.raises(retriever.BackendError, match=r"zenoh run stopped: mid\.setup\(\) raised RuntimeError: the "
                                                     r"device is taken, as the flow restarted after its step failed"):
        pipe.run(duration=2.0, backend="zenoh", quiet=True)


def test_a_fresh_flow_that_cannot_be_made_stops_the_run_saying_so():
    """Its constructor (or reset()) raises as the flow is rebuilt from the IR: the run stops saying
    which flow and why, as when its setup() raises, not as a crash of the group's process."""
    with Pipeline("group_restart_made") as pipe:
        src = CountingSource().configure(name="src", process="chain") @ Rate(hz=20)
        mid = MadeOnce(fail_at=[3]).configure(name="mid", process="chain", on_error="restart") @ Trigger("x")
        src.then(mid, sync=Latest(), map={"value": "x"})
    with pytest.raises(retriever.BackendError, match=r"zenoh run stopped: mid: its fresh flow could not be made: "
                                                     r"RuntimeError: node 'mid': .*MadeOnce.* raised RuntimeError: the "
                                                     r"device is taken, as the flow restarted after its step "
                                                     r"failed") as raised:
        pipe.run(duration=2.0, backend="zenoh", quiet=True)
    assert "crashed" not in str(raised.value)


def test_a_member_whose_process_dies_takes_the_group_down_whatever_its_on_error(tmp_path):
    """A segfault ends the group's process: no member is started afresh on its own (the others
    died with it), and the run fails naming the process that died, by all the members it ran."""
    from .lifecycle_flows import Counter, SegfaultOnce

    with Pipeline("group_segfault") as pipe:  # (crash first: the coordinator looks at its process first)
        crash = SegfaultOnce(str(tmp_path / "crashed")).configure(name="crash", process="g",
                                                                  on_error="restart") @ Trigger()
        counter = Counter().configure(name="counter", process="g") @ Rate(hz=50)
        counter.then(crash, sync=Latest())
    with pytest.raises(retriever.BackendError, match=r"worker process of 'counter', 'crash' \(pid \d+\) was killed "
                                                     r"by SIGSEGV before it finished"):
        pipe.run(duration=3.0, backend="zenoh", quiet=True)
    assert (tmp_path / "crashed").exists()
    assert "crash_restarts" not in pipe.stats()["crash"].counts


def test_a_group_process_that_dies_logs_a_fault_for_every_member_it_ran(tmp_path):
    """Every member went with the group's process: the log's fault records must say so of each,
    as a lost host's do (processes.host_lost), or a replay refuses a member's event whose step
    record the process took with it ("no step record of counter says it produced it":
    replay/steps.py's _died_with_its_record lets it go only for a node a fault names), and misses
    a member's lost_events. Only the member the coordinator looked at first got one."""
    from retriever.log import read_log

    from .lifecycle_flows import Counter, SegfaultOnce

    with Pipeline("group_segfault") as pipe:
        crash = SegfaultOnce(str(tmp_path / "crashed")).configure(name="crash", process="g",
                                                                  on_error="restart") @ Trigger()
        counter = Counter().configure(name="counter", process="g") @ Rate(hz=50)
        counter.then(crash, sync=Latest())
    with pytest.raises(retriever.BackendError, match=r"worker process of 'counter', 'crash' \(pid \d+\) was killed"):
        pipe.run(duration=3.0, backend="zenoh", quiet=True, log=tmp_path / "run.mcap")
    faults = read_log(tmp_path / "run.mcap").faults
    assert sorted(fault["node"] for fault in faults) == ["counter", "crash"]
