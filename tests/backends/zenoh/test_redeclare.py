"""A starting worker that never hears its producer (worker/starts.py, REDECLARE_AFTER_S): it says
``unanswered``, the coordinator tells that producer to ``redeclare``, and the producer declares
its subscriptions and queryable anew. At 80 flows on 8 netns hosts, a worker linked to its
producer was never told of the producer's queryable, and the deployment never started.

The lost declaration itself is Zenoh's race and is not reproduced here; each piece of the
remedy is, on real Zenoh sessions, with no wait on the clock to make anything happen.
"""

from __future__ import annotations

import queue
import threading

import msgpack
import pytest

from retriever import Pipeline, Rate, Trigger
from retriever.backends.zenoh.hub import wait_for_answers
from retriever.backends.zenoh.node import CONTROL, DATA
from retriever.backends.zenoh.origin import new_key
from retriever.backends.zenoh.protocol import RUN_CONTROL, ControlOpener, ControlSigner, Start, Stop
from retriever.backends.zenoh.wire import WIRE_VERSION, KeySpace, WireEncoder, WireError, decode_progress
from retriever.backends.zenoh.worker.build import build_loop
from retriever.backends.zenoh.worker.waits import await_control

from .payload_flows import Camera, Viewer, frame
from .specs import run_spec


@pytest.fixture(scope="module")
def spec():
    with Pipeline("redeclare") as pipe:
        cam = Camera(size=1024).named("cam") @ Rate(20)
        cam.then(Viewer().named("viewer") @ Trigger("image"))
    return run_spec(pipe.compile().to_ir().doc, "redeclare-test")


def declarations(loop) -> list:
    """Everything the loop holds declared on its session: its control plane's and its transport's."""
    return [*loop.declared, *loop.transport.subscribers, *loop.transport.publishers]


def _answers(session, key: str) -> list:
    return [decode_progress(r.ok.payload.to_bytes()) for r in session.get(key, timeout=5.0) if r.ok is not None]


def test_a_redeclared_node_answers_and_receives_as_before_and_holds_one_of_each(session, spec):
    keys = KeySpace(spec.namespace)
    viewer = build_loop(spec, "viewer", session)
    key, signer = new_key(), ControlSigner()
    viewer.opener = ControlOpener(key)
    signer.add(viewer, key)
    viewer.declare()
    try:
        before = len(declarations(viewer))
        viewer.redeclare()
        assert len(declarations(viewer)) == before, "the old declarations were dropped, the new ones kept"
        assert viewer.counts["redeclared"] == 1
        assert [a.producer for a in _answers(session, keys.progress("viewer"))] == ["viewer"], \
            "one answer: one queryable"
        session.put(keys.data("cam", "image"), WireEncoder().data((0, 0), 0, (0, 0), "cam", "image",
                                                                  frame(1, 1024).reshape(-1, 1024)))
        # the control goes once the data came: a frame through shared memory may be delivered
        # after a later small message (2 of 4 CI runs saw the control first); a second data
        # subscriber's copy would still come before the control
        items = [viewer.inbox.get(timeout=30)]
        stop = Stop().encode()
        session.put(keys.run_control(), stop, attachment=signer.seal(keys.run_control(), stop))
        while items[-1][0] != CONTROL:
            items.append(viewer.inbox.get(timeout=30))
        assert [kind for kind, *_ in items] == [DATA, CONTROL], "each message once: one subscriber of each"
    finally:
        viewer.undeclare()


def test_a_waiting_worker_redeclares_when_the_coordinator_says_so_and_only_then(session, spec):
    cam = build_loop(spec, "cam", session)
    cam.declare()
    try:
        for op, args in (("redeclare", {"nodes": ["viewer"]}), ("redeclare", {"nodes": "cam"}),
                         ("redeclare", {"nodes": ["cam"]}), ("start", {"t0": 1, "end": 2, "values": True})):
            try:  # as the loop's subscriber queues it: decoded, or the WireError refusing it
                cam.inbox.put((CONTROL, None, RUN_CONTROL.decode(msgpack.packb([WIRE_VERSION, op, args]))))
            except WireError as e:
                cam.inbox.put((CONTROL, None, e))
        assert await_control(cam, Start, "cam") == Start(t0=1, end=2, values=True)
        assert cam.counts["redeclared"] == 1, "only the message that names it, as a list"
    finally:
        cam.undeclare()


def test_wait_for_answers_nudges_about_the_keys_that_did_not_answer(session):
    keys = KeySpace("nudge-test")
    answered = session.declare_queryable(keys.progress("here"), lambda q: q.reply(q.key_expr, b"x"))
    nudged: queue.SimpleQueue = queue.SimpleQueue()
    stop = threading.Event()

    def nudge(missing: set[str]) -> None:
        nudged.put(set(missing))
        stop.set()

    try:
        missing = wait_for_answers(session, {keys.progress("here"), keys.progress("gone")}, timeout=60,
                                   stop=stop.is_set, nudge=nudge, nudge_every=0.0)
    finally:
        answered.undeclare()
    assert missing == {keys.progress("gone")}
    assert nudged.get_nowait() == {keys.progress("gone")}
