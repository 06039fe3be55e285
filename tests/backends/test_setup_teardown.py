"""A flow's lifecycle on every backend: ``setup()`` once per run in the process that steps the
flow, before its first tick; ``teardown()`` once in that process after its last; ``reset()``
keeps what setup made. ``__init__`` may run in many processes (on zenoh each worker imports the
script), so heavy work belongs in setup (issue 19, §1)."""

from __future__ import annotations

import os
from collections import defaultdict

import pytest

from retriever import Latest, Pipeline, Rate, SetupError, Trigger, read_log
from retriever.replay import replay

from .setup_flows import Camera, Policy

BACKENDS = ["inproc", "zenoh", "dora"]


def _pipeline(journal, **policy) -> Pipeline:
    with Pipeline("lifecycle") as pipe:
        cam = Camera(str(journal)).configure(name="camera") @ Rate(hz=10)
        settings = {"on_error": policy.pop("on_error")} if "on_error" in policy else {}
        pol = Policy(str(journal), **policy).configure(name="policy", **settings) @ Trigger()
        cam.then(pol, sync=Latest())
    return pipe


def _run(pipe: Pipeline, backend: str, duration: float = 1.0, **kw):
    if backend != "inproc":
        return pipe.run(duration=duration, backend=backend, quiet=True, **kw)
    trace = pipe.run(duration=duration, **kw)
    pipe.reset()  # in-process a run may go on: its flows are torn down when it is closed
    return trace


def _journal(path, threads: bool = False) -> dict[str, dict[int, list[str]]]:
    """node -> pid -> its events in order (with ``threads``: (event, thread id) pairs)"""
    events: dict = defaultdict(lambda: defaultdict(list))
    for line in path.read_text().splitlines():
        pid, event, node, thread = line.split()
        events[node][int(pid)].append((event, int(thread)) if threads else event)
    return events


def _lifecycle(events: list[str]) -> list[str]:
    """A process's events with runs of steps folded: ["setup", "step", "teardown"]."""
    folded = [e for e in events if e != "init"]
    return [e for i, e in enumerate(folded) if not (e == "step" and i and folded[i - 1] == "step")]


@pytest.mark.parametrize("backend", BACKENDS)
def test_setup_runs_once_in_the_stepping_process_before_the_first_tick_and_teardown_after_the_last(
        backend, tmp_path):
    journal = tmp_path / "journal"
    trace = _run(_pipeline(journal), backend)
    assert len(trace.steps_of("camera")) == 10 and len(trace.steps_of("policy")) == 10
    for node, by_pid in _journal(journal).items():
        stepping = [pid for pid, events in by_pid.items() if "step" in events]
        assert len(stepping) == 1, (node, dict(by_pid))
        assert _lifecycle(by_pid[stepping[0]]) == ["setup", "step", "teardown"], (node, by_pid[stepping[0]])
        others = [events for pid, events in by_pid.items() if pid != stepping[0]]
        assert all(set(events) == {"init"} for events in others), f"{node}: set up where it does not step"
        assert (stepping[0] == os.getpid()) == (backend == "inproc")


@pytest.mark.parametrize("backend", BACKENDS)
def test_a_flow_steps_on_the_thread_that_set_it_up(backend, tmp_path):
    """What setup() makes may belong to its thread (an EGL context: a render from another thread
    fails with EGL_BAD_ACCESS). On zenoh a short step of a node on no cycle used to run on the
    Zenoh thread that received its input; a flow with a setup() never does."""
    journal = tmp_path / "journal"
    with Pipeline("threads") as pipe:
        cam = Camera(str(journal)).configure(name="camera") @ Rate(hz=100)
        pol = Policy(str(journal)).configure(name="policy") @ Trigger()
        cam.then(pol, sync=Latest())
    trace = _run(pipe, backend)
    assert len(trace.steps_of("policy")) >= 90
    for node, by_pid in _journal(journal, threads=True).items():
        for pid, events in by_pid.items():
            threads = {thread for event, thread in events if event != "init"}
            assert len(threads) <= 1, f"{node} (pid {pid}) set up, stepped and tore down on {len(threads)} threads"


@pytest.mark.parametrize("backend", BACKENDS)
def test_a_restarted_flow_keeps_what_setup_made(backend, tmp_path):
    """In-process the flow is reset: its weights stay, setup does not run again. On zenoh a new
    process takes over: it sets up once, and the old one tears down once. On dora the flow
    restarts in place (dora starts its processes once): in its process the old flow tears down
    and a fresh one sets up."""
    journal = tmp_path / "journal"
    pipe = _pipeline(journal, fail_at=[3], on_error="restart")
    trace = _run(pipe, backend)
    statuses = [s.status for s in trace.steps_of("policy")]
    assert statuses.count("error") == 1 and statuses[-1] == "ok", statuses
    assert trace.values_of("policy", "n")[-1] == 2 * 10, "stepped with its weights after the restart"
    processes = _journal(journal)["policy"]
    lifecycles = [_lifecycle(events) for events in processes.values() if "step" in events]
    expected = {"inproc": [["setup", "step", "teardown"]], "zenoh": [["setup", "step", "teardown"]] * 2,
                "dora": [["setup", "step", "teardown"] * 2]}
    assert lifecycles == expected[backend], lifecycles


@pytest.mark.parametrize("backend", BACKENDS)
def test_a_setup_that_raises_stops_the_run_before_its_first_tick(backend, tmp_path):
    journal = tmp_path / "journal"
    pipe = _pipeline(journal, fail_setup=True)
    with pytest.raises(SetupError, match=r"^policy\.setup\(\) raised FileNotFoundError: weights\.pt, before its "
                                         r"first tick: the run did not start\n    hint: setup\(\) runs once"):
        _run(pipe, backend)
    pipe.reset()
    for node, by_pid in _journal(journal).items():
        assert all("step" not in events for events in by_pid.values()), node
        for events in by_pid.values():  # what was set up was torn down
            assert events.count("setup") == events.count("teardown"), (node, events)


def test_a_replay_sets_the_flows_up_and_tears_them_down(tmp_path):
    journal = tmp_path / "journal"
    _run(_pipeline(journal), "inproc", log=tmp_path / "run.mcap")
    journal.unlink()
    assert replay(read_log(tmp_path / "run.mcap")).identical
    assert _lifecycle(_journal(journal)["policy"][os.getpid()]) == ["setup", "step", "teardown"]
