"""The dora transport's receiving thread (backends/dora/link.py) under a real NodeLoop, its dora
node dora's own stand-in (dora.testing.MockNode: the events a node would be handed, with no
dataflow), since a real one cannot be made to fail on demand. No test here waits on time but
for that thread's end."""

from __future__ import annotations

import threading

import numpy as np
import pyarrow as pa
import pytest
import zenoh
from dora.testing import MockNode

from retriever import Latest, Pipeline, Rate, Trigger
from retriever.backends.dora.dataflow import DoraNames
from retriever.backends.dora.link import RECEIVE_TIMEOUT_S, DoraLink, DoraTransport
from retriever.backends.zenoh.hub import peer_config
from retriever.backends.zenoh.node import DATA, PROGRESS, WARM_AFTER_IDLE_NS, WARM_AHEAD_NS
from retriever.backends.zenoh.wire import WireEncoder, decode_events
from retriever.backends.zenoh.worker.build import build_loop

from ..zenoh.semantics_flows import Ticker, WhereRun
from ..zenoh.specs import run_spec

BOUND_S = 60.0  # a bound on any wait: a loaded 2-core machine


@pytest.fixture
def session():
    with zenoh.open(peer_config()) as s:
        yield s


def _loop_fed_by(session, events: list[dict]):
    """The loop of ``where`` (Trigger on counter's values), its dora node handing over ``events``."""
    with Pipeline("link") as pipe:
        src = Ticker().configure(name="counter") @ Rate(hz=10)
        src.then(WhereRun().configure(name="where") @ Trigger("x"), sync=Latest(), map={"value": "x"})
    ir = pipe.compile().to_ir().doc
    link = DoraLink()
    link.dora_node = MockNode(events)
    return build_loop(run_spec(ir, "link-test"), "where", session, transport=DoraTransport(link, DoraNames.of(ir),
                                                                                         "where")), link


def test_a_receiving_thread_that_dies_fails_its_loop_and_the_wait_for_greetings(session):
    """An input event with no value stands for any error on that thread (dora's next() raising):
    the node would never hear, nor step, again. Its loop raises the error at its next pass, and
    the wait for the producers' greetings (before the node says ready) ends with it."""
    loop, link = _loop_fed_by(session, [{"type": "INPUT", "id": "counter__value", "value": None}])
    loop.declare()
    try:
        link.receiver.join(BOUND_S)
        with pytest.raises(TypeError, match="NoneType"):
            loop.drain()
        with pytest.raises(TypeError, match="NoneType"):
            loop.await_routes(timeout=BOUND_S)
    finally:
        loop.undeclare()


def test_a_stream_dora_ends_after_its_stop_ends_the_thread_quietly(session):
    loop, link = _loop_fed_by(session, [{"type": "INPUT_CLOSED", "id": "counter__value"}])
    loop.declare()
    try:
        link.receiver.join(BOUND_S)
        assert not link.receiver.is_alive() and link.failure is None
        loop.drain()
    finally:
        loop.undeclare()


class _Held:
    """A dora node whose events wait until ``gate`` is set (so that every listener is in first)."""

    def __init__(self, node: MockNode, gate: threading.Event):
        self.node, self.gate = node, gate

    def next(self, timeout=None):
        assert self.gate.wait(BOUND_S)
        return self.node.next(timeout=timeout)


def test_one_receiving_thread_hands_a_stream_two_members_consume_to_each_until_the_last_leaves():
    """A group's members share their process's dora node (one DoraLink): a stream both consume
    is one dora input, and each of its events reaches both; the thread serves them until the
    last one undeclares."""
    with Pipeline("shared") as pipe:
        src = Ticker().configure(name="src") @ Rate(hz=10)
        src.then(WhereRun().configure(name="a", process="both") @ Trigger("x"), sync=Latest(), map={"value": "x"})
        src.then(WhereRun().configure(name="b", process="both") @ Trigger("x"), sync=Latest(), map={"value": "x"})
    names = DoraNames.of(pipe.compile().to_ir().doc, {"both": ["a", "b"]})
    assert names.inputs["a"] == names.inputs["b"] == {"src__value": ["src", "value"], "src__progress": ["src", None]}
    gate, link = threading.Event(), DoraLink()
    link.dora_node = _Held(MockNode([("src__value", pa.array([], type=pa.uint8())),  # a greeting
                                     ("src__value", pa.array(np.frombuffer(b"event", np.uint8))),
                                     ("src__progress", pa.array(np.frombuffer(b"progress", np.uint8)))]), gate)
    got: dict[str, list] = {"a": [], "b": []}
    members = {node: DoraTransport(link, names, node) for node in got}
    for node, transport in members.items():
        transport.declare_inputs([], [], None, got[node].append)
    gate.set()
    link.receiver.join(BOUND_S)
    assert link.greeted == {"src__value"}
    for node in got:
        assert [(kind, source, bytes(data)) for kind, source, data in got[node]] == [
            (DATA, ("src", "value"), b"event"), (PROGRESS, "src", b"progress")], node
    members["a"].undeclare()
    assert link.receiver is not None and list(link.listeners) == ["src__value", "src__progress"]
    members["b"].undeclare()
    assert link.receiver is None and link.listeners == {}


class _Paced:
    """A dora node handing ``node``'s events ``gap_ns`` apart on a logical clock (``now``): a
    ``next(timeout)`` shorter than the wait for the next event returns a timeout (an ERROR
    event, as dora's does) ``timeout`` later. It notes each ``next()``'s timeout, in ns."""

    def __init__(self, node: MockNode, gap_ns: int):
        self.node, self.gap_ns, self.now, self.comes, self.timeouts = node, gap_ns, 0, gap_ns, []

    def clock(self) -> int:
        return self.now

    def next(self, timeout=None):
        self.timeouts.append(round(timeout * 1e9))
        if self.now + self.timeouts[-1] < self.comes:
            self.now += self.timeouts[-1]
            return {"type": "ERROR", "error": "timeout"}
        self.now, self.comes = self.comes, self.comes + self.gap_ns
        return self.node.next(timeout=timeout)


def test_the_receiving_thread_warms_up_before_an_input_event_it_foresees_and_hands_on_only_events():
    """Events 50 ms apart: after the second (the first gap), the thread waits only until
    WARM_AHEAD_NS before the third, takes the second's bytes once more there (results unused),
    then waits for the third; it hands on each event once, as it came (a slice of a bigger
    buffer too), and nothing at its warm-ups. Events closer than WARM_AFTER_IDLE_NS: no warm-up."""
    with Pipeline("paced") as pipe:
        src = Ticker().configure(name="src") @ Rate(hz=20)
        src.then(WhereRun().configure(name="where") @ Trigger("x"), sync=Latest(), map={"value": "x"})
    names = DoraNames.of(pipe.compile().to_ir().doc)
    for gap_ns, warmed in ((50_000_000, True), (WARM_AFTER_IDLE_NS - 1, False)):
        events = [("src__value", pa.array(np.frombuffer(b"one", np.uint8))),
                  ("src__value", pa.array(np.frombuffer(b"..two", np.uint8)).slice(2)),
                  ("src__value", pa.array(np.frombuffer(b"three", np.uint8)))]
        node, link, got = _Paced(MockNode(events), gap_ns), DoraLink(), []
        link.dora_node, link.clock = node, node.clock
        transport = DoraTransport(link, names, "where")
        transport.declare_inputs([], [], None, got.append)
        link.receiver.join(BOUND_S)
        assert link.failure is None
        assert [(kind, source, bytes(data)) for kind, source, data in got] == [
            (DATA, ("src", "value"), b"one"), (DATA, ("src", "value"), b"two"), (DATA, ("src", "value"), b"three")]
        timeout = round(RECEIVE_TIMEOUT_S * 1e9)
        # after the second event, the wait for the third ends WARM_AHEAD_NS before it (then a warm-up)
        assert node.timeouts[:3] == [timeout, timeout, gap_ns - WARM_AHEAD_NS if warmed else timeout]
        assert (gap_ns - WARM_AHEAD_NS in node.timeouts) is warmed
        transport.undeclare()


def test_the_warm_up_decodes_the_last_event_on_the_thread_its_loop_takes_it_on():
    """A listener that may step on the receiving thread (its handler is not its queue's put:
    NodeLoop.receive) has each event decoded there: at the warm-up before the third event, the
    thread decodes the second once more (results unused), as its stream's (and the third before
    a fourth that never comes: the stream then ends); a listener that
    only queues (its loop decodes on its own thread) gets no decoding from it. Garbage at a
    warm-up (its loop refused it when it came) leaves the thread running. Each event is handed
    on once, as it came."""
    with Pipeline("paced") as pipe:
        src = Ticker().configure(name="src") @ Rate(hz=20)
        src.then(WhereRun().configure(name="where") @ Trigger("x"), sync=Latest(), map={"value": "x"})
    names = DoraNames.of(pipe.compile().to_ir().doc)
    messages = [WireEncoder().data((k * 50_000_000, 0), k, (k * 50_000_000 + 1, 0), "src", "value", k) for k in range(3)]
    decoding = decode_events.__code__
    stream = ("src", "value")
    for second, inline, decoded in ((messages[1], True, [(messages[1], stream), (messages[2], stream)]),
                                    (messages[1], False, []),
                                    (b"garbage", True, [(b"garbage", stream), (messages[2], stream)])):
        sent = [messages[0], second, messages[2]]
        node, link, got, queued = _Paced(MockNode([("src__value", pa.array(np.frombuffer(m, np.uint8))) for m in sent]),
                                         50_000_000), DoraLink(), [], []
        link.dora_node, link.clock = node, node.clock
        calls = []

        def profile(frame, event, arg):
            if event == "call" and frame.f_code is decoding:
                calls.append((bytes(frame.f_locals["data"]), frame.f_locals["expected"]))

        transport = DoraTransport(link, names, "where")
        threading.setprofile(profile)  # (the receiving thread starts in declare_inputs)
        try:
            transport.declare_inputs([], [], got.append if inline else None, queued.append)
        finally:
            threading.setprofile(None)
        link.receiver.join(BOUND_S)
        assert link.failure is None
        assert [bytes(data) for _, _, data in (got if inline else queued)] == sent
        assert (queued if inline else got) == []
        assert calls == decoded
        transport.undeclare()


def test_a_producers_warm_up_message_has_the_receiving_thread_rehearse_and_is_no_event():
    """The producer's warm-up messages come on a dora input of their own (DoraNames.warm_inputs),
    over the route its events take: each has the receiving thread call the loop's
    ``warmed(producer)`` (NodeLoop.warmed: it rehearses the producer's last message there), and
    is handed to no listener nor taken for a greeting. One came since the stream's last event:
    the thread leaves its own warm-up before the next event (its foresight) to the producer's.
    Without them, the same events 50 ms apart have the thread warm up before the third."""
    with Pipeline("heralded") as pipe:
        src = Ticker().configure(name="src") @ Rate(hz=20)
        src.then(WhereRun().configure(name="where") @ Trigger("x"), sync=Latest(), map={"value": "x"})
    names = DoraNames.of(pipe.compile().to_ir().doc)
    assert names.warm_inputs("where") == {"src__warm": ["src"]}
    warm = ("src__warm", pa.array([], type=pa.uint8()))
    gap_ns, timeout = 50_000_000, round(RECEIVE_TIMEOUT_S * 1e9)
    for heralded in (True, False):
        values = [("src__value", pa.array(np.frombuffer(m, np.uint8))) for m in (b"one", b"two", b"three")]
        events = [values[0], warm, values[1], warm, values[2]] if heralded else values
        gate, node, link, got, warmed = threading.Event(), _Paced(MockNode(events), gap_ns), DoraLink(), [], []
        link.dora_node, link.clock = _Held(node, gate), node.clock
        transport = DoraTransport(link, names, "where")
        transport.declare_inputs([("src", "value")], ["src"], got.append, got.append)
        transport.declare_warm(["src"], lambda producer: warmed.append((producer, threading.current_thread())))
        gate.set()
        link.receiver.join(BOUND_S)
        assert link.failure is None
        assert [(kind, source, bytes(data)) for kind, source, data in got] == [
            (DATA, ("src", "value"), b"one"), (DATA, ("src", "value"), b"two"), (DATA, ("src", "value"), b"three")]
        assert warmed == ([("src", link.receiver)] * 2 if heralded else [])
        assert "src__warm" not in link.greeted
        # the wait for the next event: shortened to warm up before it only where no warm-up message came
        assert (gap_ns - WARM_AHEAD_NS in node.timeouts) is not heralded
        transport.undeclare()
        assert link.heralds == {} and link.listeners == {}
