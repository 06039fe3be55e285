"""node/group.py: the loops of several nodes in one process, stepped by one thread, their events
handed over by reference (no encode, no copy, no Zenoh between them)."""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass
from typing import Any

import numpy as np
import pytest

from retriever import Flow, Latest, Pipeline, Rate, RetrieverWarning, Trigger, io
from retriever.backends.zenoh.node import NodeLoop
from retriever.backends.zenoh.node.group import GroupLoop, GroupTransport, LocalBus
from retriever.backends.zenoh.node.transport import ZenohTransport
from retriever.backends.zenoh.protocol import RunSpec
from retriever.backends.zenoh.wire import KeySpace
from retriever.errors import BackendError
from retriever.backends.zenoh.worker.build import build_loop

from .specs import run_spec


@io
@dataclass
class Frame:
    frame: Any = None


@io
@dataclass
class FrameIn:
    frame: Any


class Frames(Flow[None, Frame]):
    """A source of arrays; it keeps each one it emitted."""

    def __init__(self):
        self.sent: list = []

    def step(self, inp: None) -> Frame:
        frame = np.full(4, len(self.sent))
        self.sent.append(frame)
        return Frame(frame)


class Relay(Flow[FrameIn, Frame]):
    """Passes each array it got on, as it is."""

    def step(self, inp: FrameIn) -> Frame:
        return Frame(inp.frame)


class Keep(Flow[FrameIn, None]):
    """Keeps each array it got."""

    def __init__(self):
        self.got: list = []

    def step(self, inp: FrameIn) -> None:
        self.got.append(inp.frame)


def grouped(spec: RunSpec, session, members: list[str], consumers_elsewhere: dict[str, set[str]]) -> list[NodeLoop]:
    """The loops of ``members`` built as one process builds them, their events between them on one bus."""
    bus, keys = LocalBus(set(members)), KeySpace(spec.namespace)
    loops = []
    for node in members:
        remote = consumers_elsewhere.get(node, set())
        transport = GroupTransport(bus, ZenohTransport(session, keys, node), node, remote, bool(remote))
        loops.append(build_loop(spec, node, session, transport=transport))
    return loops


def chain() -> RunSpec:
    with Pipeline("grouped") as pipe:
        frames = Frames().configure(name="frames") @ Rate(hz=100)
        relay = Relay().configure(name="relay") @ Trigger("frame")
        keep = Keep().configure(name="keep") @ Trigger("frame")
        frames.then(relay, sync=Latest())
        relay.then(keep, sync=Latest())
    return run_spec(pipe.compile().to_ir().doc, f"grouped-{time.monotonic_ns()}")


def run_group(loops: list[NodeLoop], seconds: float) -> GroupLoop:
    group = GroupLoop(loops)
    for loop in loops:
        loop.declare()
    t0 = time.time_ns() + 20_000_000
    runner = threading.Thread(target=group.run, args=(t0, int(seconds * 1e9)))
    runner.start()
    runner.join(timeout=seconds + 30)
    assert not runner.is_alive(), "the group did not end"
    for loop in loops:
        loop.undeclare()
    return group


def test_a_group_hands_each_event_over_by_reference_and_ticks_on_every_one(session):
    loops = grouped(chain(), session, ["frames", "relay", "keep"], {})
    frames, relay, keep = (loop.flow for loop in loops)
    run_group(loops, 0.5)
    sent, got = frames.sent, keep.got
    assert len(sent) == 50
    # each array reached keep through relay as the very object frames made: nothing copied
    assert len(got) >= len(sent) - 2, (len(got), len(sent))  # (the last may be stamped past the end)
    assert all(g is s for g, s in zip(got, sent))
    assert [loop.reports.recorded for loop in loops] == [50, len(got), len(got)]
    assert all(loop.counts.get("garbage", 0) == 0 for loop in loops)


def test_a_port_consumed_outside_the_group_goes_on_zenoh_too(session):
    """frames and relay grouped, keep a loop of its own (as in another process): relay's events
    reach keep through Zenoh, decoded (equal, not the same objects), and relay's by reference."""
    spec = chain()
    loops = grouped(spec, session, ["frames", "relay"], {"relay": {"frame"}})
    alone = build_loop(spec, "keep", session)
    frames, keep = loops[0].flow, alone.flow
    alone.declare()
    t0 = time.time_ns() + 50_000_000
    lone = threading.Thread(target=alone.run, args=(t0, 500_000_000))
    lone.start()
    group = GroupLoop(loops)
    for loop in loops:
        loop.declare()
    group.run(t0, 500_000_000)
    lone.join(timeout=30)
    assert not lone.is_alive()
    for loop in [*loops, alone]:
        loop.undeclare()
    sent, got = frames.sent, keep.got
    assert len(got) >= len(sent) - 2, (len(got), len(sent))
    assert all(g is not s and np.array_equal(g, s) for g, s in zip(got, sent))
    assert all(loop.counts.get("garbage", 0) == 0 for loop in [*loops, alone])


def test_a_grouped_loop_needs_its_loops_undeclared(session):
    loops = grouped(chain(), session, ["frames"], {"frames": {"frame"}})
    loops[0].declare()
    try:
        with pytest.raises(RuntimeError, match="before they declare"):
            GroupLoop(loops)
    finally:
        loops[0].undeclare()


# ---------------------------------------------------------------------------------------------
# Runs: configure(process=) on the zenoh backend
# ---------------------------------------------------------------------------------------------
def grouped_pipeline(fail_at: list | None = None, with_pid: bool = True) -> Pipeline:
    """counter -> faulty -> sink, counter and faulty in process "front", sink alone."""
    from .semantics_flows import Faulty, Probe, Ticker

    with Pipeline("grouped_run") as pipe:
        counter = Ticker().configure(name="counter", process="front") @ Rate(hz=20)
        faulty = Faulty(fail_at=fail_at or [], with_pid=with_pid).configure(
            name="faulty", process="front", on_error="restart" if fail_at else "stop") @ Trigger("x")
        sink = Probe().configure(name="sink") @ Trigger("x")
        counter.then(faulty, sync=Latest(), map={"value": "x"})
        faulty.then(sink, sync=Latest(), map={"report": "x"})
    return pipe


def test_a_grouped_run_in_virtual_time_is_the_in_process_run():
    pipe = grouped_pipeline(with_pid=False)
    reference = pipe.run(duration=1.0, backend="inproc")
    pipe.reset()
    trace = pipe.run(duration=1.0, backend="zenoh", virtual_time=True, quiet=True)
    pids = pipe.session.worker_pids()
    assert pids["counter"] == pids["faulty"] != pids["sink"], pids
    assert trace.first_difference(reference) is None
    assert trace.digest() == reference.digest()


def test_a_flow_that_restarts_is_grouped_and_restarts_in_its_groups_process(tmp_path, recwarn):
    """faulty (on_error="restart") shares process "front" with counter, with no warning; its step
    raises at x=5 and it restarts in place (test_group_restart.py has the rest); counter, in
    "front", runs on; the log replays."""
    pipe = grouped_pipeline(fail_at=[5], with_pid=False)
    session = pipe.open("zenoh", quiet=True)
    assert not [w for w in recwarn if issubclass(w.category, RetrieverWarning)]
    first = session.worker_pids()
    assert first["counter"] == first["faulty"] != first["sink"], first
    path = tmp_path / "run.mcap"
    trace = pipe.run(duration=2.0, backend="zenoh", log=path)
    assert pipe.stats()["faulty"].counts.get("restarts") == 1
    assert pipe.session.worker_pids() == first
    assert len([s for s in trace.steps if s.node == "counter"]) == 40
    import retriever
    from retriever.replay import replay

    report = replay(retriever.read_log(path))
    assert report.identical, report.divergences[:3]


def test_a_mixed_run_in_real_time_logs_and_replays_identically(tmp_path):
    """counter and faulty share a process, sink runs alone; in real time, with a log: the run's
    control reaches both members (the group hears it once), every tick is recorded, and the log
    replays identically."""
    pipe = grouped_pipeline(with_pid=False)
    path = tmp_path / "run.mcap"
    trace = pipe.run(duration=2.0, backend="zenoh", log=path, quiet=True)
    pids = pipe.session.worker_pids()
    assert pids["counter"] == pids["faulty"] != pids["sink"], pids
    counter = [s for s in trace.steps if s.node == "counter"]
    assert len(counter) == 40 and all(s.status == "ok" for s in counter)
    assert len([s for s in trace.steps if s.node == "sink" and s.consumed]) >= 35
    import retriever
    from retriever.replay import replay

    report = replay(retriever.read_log(path))
    assert report.identical, report.divergences[:3]


def test_names_a_hosting_gives_win_over_the_flows():
    """A deployment's placement file names processes too (Hosting.process_names): its name wins
    over configure(process=); a flow with on_error="restart" is grouped as any other."""
    from retriever.backends.zenoh.coordinator.spec import process_groups

    graph = grouped_pipeline(fail_at=[5], with_pid=False).compile()  # faulty restarts
    assert process_groups(graph) == {"front": ["counter", "faulty"]}
    assert process_groups(graph, {"sink": "front"}) == {"front": ["counter", "faulty", "sink"]}
    assert process_groups(graph, {"counter": "back", "faulty": "solo", "sink": "front"}) == {}
    assert process_groups(grouped_pipeline().compile(), {"faulty": "solo"}) == {}  # a name of its own: alone


def test_a_process_with_the_name_of_a_node_outside_it_is_refused_naming_both():
    """What a group's process prints is told under its name, as a node's under its id: a process
    named as another node would show its lines as that node's (a member's own id is fine)."""
    from retriever.backends.zenoh.coordinator.spec import process_groups

    graph = grouped_pipeline(with_pid=False).compile()
    assert process_groups(graph, {"counter": "faulty", "faulty": "faulty"}) == {"faulty": ["counter", "faulty"]}
    with pytest.raises(BackendError, match=r"process 'sink' \(flows 'counter', 'faulty'\) has the name of node 'sink', "
                                           r"which is not one of them: .*\n    hint: give the process another "
                                           r"name \(configure\(process=\), or process = \"NAME\" in a placement file\)"):
        process_groups(graph, {"counter": "sink", "faulty": "sink"})
