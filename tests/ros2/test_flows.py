"""Ros2Subscriber and Ros2Publisher against a Zenoh session built by hand on the key expressions
rmw_zenoh documents (written out literally below, not computed by retriever.ros2), with CDR
encoded and decoded by rosbags alone.

The test's own session is a Zenoh router, as rmw_zenoh's rmw_zenohd is: it listens on a free loopback port and
the flows connect to it, in a ROS domain and under a topic no other test uses. Waiting is polling
with a bound: the pipeline steps until what is expected arrives, or the bound fails the test.
"""

from __future__ import annotations

import os
import re
import subprocess
import sys
import threading
import time
import warnings
from pathlib import Path

import numpy as np
import pytest
import zenoh
import zenoh.ext as zext
from rosbags.typesys import Stores, get_typestore

from retriever import Flow, Pipeline, Queue, Rate, Trigger, read_log
from retriever.backends.zenoh.hub import endpoint, free_port
from retriever.errors import RetrieverWarning
from retriever.ros2 import Ros2Publisher, Ros2Subscriber
from retriever.ros2.node import Ros2Node
from tests.ros2.helpers import BOUND_S, until

DOMAIN = 117
NAMESPACE = f"/retriever_test_{os.getpid()}"
JOINT_STATE = ("sensor_msgs::msg::dds_::JointState_/"
               "RIHS01_a13ee3a330e346c9d87b5aa18d24e11690752bd33a0350f11c5882bc9179260e")
TWIST = "geometry_msgs::msg::dds_::Twist_/RIHS01_9c45bf16fe0983d80e3cfe750d6835843d265a9a6c46bd2e609fcddde6fb8d2a"
ROOT = Path(__file__).resolve().parents[2]

_jazzy = get_typestore(Stores.ROS2_JAZZY)


class Collect(Flow):
    def __init__(self):
        self.got = []

    def step(self, msg):
        self.got.extend(msg)


def _joint_state_cdr(i: int) -> bytes:
    JointState, Header = _jazzy.types["sensor_msgs/msg/JointState"], _jazzy.types["std_msgs/msg/Header"]
    Time = _jazzy.types["builtin_interfaces/msg/Time"]
    message = JointState(header=Header(stamp=Time(sec=100 + i, nanosec=7), frame_id="base"), name=["j0", "j1"],
                         position=np.array([i, -i], dtype=np.float64), velocity=np.zeros(0), effort=np.zeros(0))
    return bytes(_jazzy.serialize_cdr(message, "sensor_msgs/msg/JointState"))


#: the messages sent once the subscription reached the publisher
LINKED = range(1000, 1005)


def test_a_subscriber_takes_what_a_plain_zenoh_publisher_puts_on_the_documented_key(router):
    session, at = router
    key = f"{DOMAIN}/{NAMESPACE.strip('/')}/joints/{JOINT_STATE}"
    gid = bytes(range(16))
    with Pipeline("ros_in") as pipe:
        subscriber = Ros2Subscriber(f"{NAMESPACE}/joints", "sensor_msgs/msg/JointState", domain_id=DOMAIN,
                                    connect=[at], listen=[]) @ Rate(hz=100)
        sink = Collect() @ Trigger("msg")
        subscriber.then(sink, sync=Queue(maxsize=1000))
    try:
        pipe.step(0.01)  # the subscriber's setup(): its session, tokens and subscription
        publisher = session.declare_publisher(key)
        sent = iter(range(1, LINKED[0]))

        def put(i: int) -> None:
            publisher.put(_joint_state_cdr(i), attachment=zext.z_serialize(
                (zext.Int64(i), zext.Int64(time.time_ns()), gid)).to_bytes())

        until(lambda: sink.got, "a message on the documented key", lambda: (put(next(sent)), pipe.step(0.01)))
        for i in LINKED:  # now linked: every message arrives, in order
            put(i)
        until(lambda: sink.got[-1]["position"][0] == LINKED[-1], "the messages sent once linked",
              lambda: pipe.step(0.01))
        publisher.undeclare()
        got, undecodable = sink.got, subscriber.undecodable
    finally:
        pipe.reset()  # (which resets the flows: what they hold is read before)
    assert [value["position"][0] for value in got if value["position"][0] in LINKED] == list(LINKED)
    value = got[-1]
    assert value["name"] == ["j0", "j1"] and value["frame_id"] == "base"
    assert value["stamp"] == (100 + int(value["position"][0])) * 1_000_000_000 + 7
    assert undecodable == 0


def test_garbage_on_the_key_is_counted_and_never_handed_on(router):
    session, at = router
    key = f"{DOMAIN}/{NAMESPACE.strip('/')}/noise/{JOINT_STATE}"
    with Pipeline("ros_noise") as pipe:
        subscriber = Ros2Subscriber(f"{NAMESPACE}/noise", "sensor_msgs/msg/JointState", domain_id=DOMAIN,
                                    connect=[at], listen=[]) @ Rate(hz=100)
        sink = Collect() @ Trigger("msg")
        subscriber.then(sink, sync=Queue(maxsize=1000))
    try:
        trace = pipe.step(0.01)  # the trace so far

        def put_both() -> None:
            nonlocal trace
            session.put(key, b"\x00\x01\x00\x00garbage")
            session.put(key, _joint_state_cdr(1))
            trace = pipe.step(0.01)

        # until both came: one round's garbage may be lost while the subscription reaches the
        # router and its valid message not (this test failed about every other run on that)
        until(lambda: sink.got and subscriber.undecodable, "a message and garbage", put_both)
        got, undecodable = sink.got, subscriber.undecodable
        said = [s.detail["flow"] for s in trace.steps if s.node == "ros2_subscriber" and s.detail
                and "flow" in s.detail]
    finally:
        with pytest.warns(RetrieverWarning, match=r"could not decode [1-9]\d* \(not CDR of sensor_msgs/msg/JointState"):
            pipe.reset()
    assert got and all(value["name"] == ["j0", "j1"] for value in got)
    assert undecodable >= 1
    assert sum(detail["undecodable"] for detail in said) == undecodable


class Speed(Flow):
    """A source of Twist values: forward at 0.1 m/s more each tick."""

    def __init__(self):
        self.k = 0

    def step(self):
        self.k += 1
        return {"msg": {"linear": [0.1 * self.k, 0, 0]}}


def test_a_publisher_puts_cdr_with_rmw_zenohs_attachment_and_announces_itself(router):
    session, at = router
    key = f"{DOMAIN}/{NAMESPACE.strip('/')}/cmd_vel/{TWIST}"
    received, arrived = [], threading.Event()

    def on_sample(sample):
        received.append((sample.payload.to_bytes(), sample.attachment.to_bytes()))
        arrived.set()

    subscriber = session.declare_subscriber(key, on_sample)
    with Pipeline("ros_out") as pipe:
        speed = Speed() @ Rate(hz=10)
        publisher = Ros2Publisher(f"{NAMESPACE}/cmd_vel", "geometry_msgs/msg/Twist", node="driver",
                                  domain_id=DOMAIN, connect=[at], listen=[]) @ Trigger("msg")
        speed.then(publisher)
    try:
        until(lambda: arrived.wait(0.05), "a Twist on the documented key", lambda: pipe.step(0.1))
        tokens = [str(reply.ok.key_expr) for reply in session.liveliness().get(f"@ros2_lv/{DOMAIN}/**")]
        published = publisher.published
    finally:
        pipe.reset()
        subscriber.undeclare()
    assert received, f"nothing arrived in {BOUND_S} s"
    samples = list(received)
    sequences, gids = [], set()
    for payload, attachment in samples:  # the k-th tick's speed is 0.1 k, published as the k-th message
        twist = _jazzy.deserialize_cdr(payload, "geometry_msgs/msg/Twist")
        sequence, stamp, gid = zext.z_deserialize(tuple[zext.Int64, zext.Int64, bytes], zenoh.ZBytes(attachment))
        assert twist.linear.x == pytest.approx(0.1 * sequence) and twist.angular.z == 0.0
        assert abs(stamp - time.time_ns()) < 60 * 1_000_000_000
        sequences.append(sequence)
        gids.add(gid)
    assert sequences == list(range(sequences[0], sequences[0] + len(sequences))) and sequences[-1] <= published
    assert len(gids) == 1 and len(gids.pop()) == 16
    nodes = [t for t in tokens if "/NN/" in t]
    publishers = [t for t in tokens if "/MP/" in t]
    assert len(nodes) == 1 and nodes[0].endswith("/NN/%/%/driver")
    assert len(publishers) == 1 and publishers[0].endswith(
        f"/MP/%/%/driver/{NAMESPACE.replace('/', '%')}%cmd_vel/{TWIST}/:2:,10:,:,:,,")


def test_on_the_realtime_backend_a_subscriber_in_its_worker_process_takes_the_topic(router):
    """The flows as they are deployed: rebuilt from the IR in a worker process of their own,
    whose setup() opens the ROS session there; the run's trace holds what arrived."""
    session, at = router
    key = f"{DOMAIN}/{NAMESPACE.strip('/')}/rt_joints/{JOINT_STATE}"
    with Pipeline("ros_realtime") as pipe:
        Ros2Subscriber(f"{NAMESPACE}/rt_joints", "sensor_msgs/msg/JointState", domain_id=DOMAIN,
                       connect=[at], listen=[]) @ Rate(hz=50)
    publisher, run_over = session.declare_publisher(key), threading.Event()

    def publish_until_the_run_is_over():
        i = 0
        while not run_over.wait(0.02):  # a ROS node's 50 Hz, for as long as the run lasts
            i += 1
            publisher.put(_joint_state_cdr(i), attachment=zext.z_serialize(
                (zext.Int64(i), zext.Int64(time.time_ns()), bytes(16))).to_bytes())

    talker = threading.Thread(target=publish_until_the_run_is_over)
    talker.start()
    try:
        trace = pipe.run(duration=5.0, backend="zenoh")
    finally:
        run_over.set()
        talker.join()
        publisher.undeclare()
        pipe.reset()
    values = trace.values_of("ros2_subscriber", "msg")
    assert values, "the subscriber's worker took nothing in a 5 s run"
    positions = [value["position"][0] for value in values]
    assert positions == sorted(positions) and len(set(positions)) == len(positions)
    assert all(value["stamp"] == (100 + int(value["position"][0])) * 1_000_000_000 + 7 for value in values)


def test_a_relative_topic_resolves_in_the_nodes_namespace_on_the_key_and_in_the_token():
    publisher = Ros2Publisher("image", "sensor_msgs/msg/Image", namespace="/robot1", domain_id=3)
    assert publisher.topic == "/robot1/image"
    assert publisher.key.startswith("3/robot1/image/sensor_msgs::msg::dds_::Image_/RIHS01_")


#: an in-process run of a subscriber, in a program of its own: it must end when the run has
ENDS = """
import sys
from retriever import Flow, Pipeline, Queue, Rate
from retriever.ros2 import Ros2Subscriber

class Take(Flow):
    def step(self, msg):
        return None

with Pipeline("ends") as pipe:
    subscriber = Ros2Subscriber("/ends", "std_msgs/msg/String", domain_id=117, connect=[sys.argv[1]], listen=[])
    (subscriber @ Rate(hz=10)).then(Take() @ Rate(hz=10), sync=Queue())
pipe.run(duration=0.5)
print("ran")
"""


def test_a_program_that_ran_a_subscriber_in_process_ends(router, tmp_path):
    """The subscription's callback runs on Zenoh's thread, not on a Python thread Zenoh starts:
    an in-process run tears its flows down at the interpreter's exit, which first waits for every
    Python thread, so the program hung there for good."""
    _, at = router
    done = subprocess.run([sys.executable, "-c", ENDS, at], capture_output=True, text=True, timeout=60,
                          cwd=tmp_path, env={**os.environ, "PYTHONPATH": str(ROOT)})
    assert done.returncode == 0 and done.stdout.strip() == "ran", done.stdout + done.stderr


def test_a_node_with_no_router_where_it_connects_warns_naming_the_endpoint_and_rmw_zenohd(router):
    """A node whose router is not running (rmw_zenohd not started) saw no topic and said nothing:
    a subscriber's flow just never emitted."""
    nowhere = endpoint(free_port())
    with pytest.warns(RetrieverWarning, match=r"(?s)linked to nothing.*" + re.escape(nowhere) + ".*rmw_zenohd"):
        node = Ros2Node("lonely", connect=[nowhere])
    node.close()
    with warnings.catch_warnings():
        warnings.simplefilter("error", RetrieverWarning)
        Ros2Node("linked", connect=[router[1]]).close()


STRING = "std_msgs::msg::dds_::String_/RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18"


def _string_cdr(text: str) -> bytes:
    return bytes(_jazzy.serialize_cdr(_jazzy.types["std_msgs/msg/String"](data=text), "std_msgs/msg/String"))


def test_a_burst_relayed_through_a_queue_is_published_a_message_each_in_order(router):
    """A subscriber's Burst, delivered by a Queue() as a list, went out as one String: the list's
    repr ("['m0', 'm1', ...]"), not one message per event."""
    session, at = router
    in_key = f"{DOMAIN}/{NAMESPACE.strip('/')}/relay_in/{STRING}"
    out_key = f"{DOMAIN}/{NAMESPACE.strip('/')}/relay_out/{STRING}"
    received = []
    listener = session.declare_subscriber(out_key, lambda sample: received.append(
        (_jazzy.deserialize_cdr(sample.payload.to_bytes(), "std_msgs/msg/String").data,
         zext.z_deserialize(tuple[zext.Int64, zext.Int64, bytes], zenoh.ZBytes(sample.attachment.to_bytes()))[0])))
    with Pipeline("ros_relay") as pipe:
        subscriber = Ros2Subscriber(f"{NAMESPACE}/relay_in", "std_msgs/msg/String", domain_id=DOMAIN,
                                    connect=[at], listen=[]) @ Rate(hz=100)
        publisher = Ros2Publisher(f"{NAMESPACE}/relay_out", "std_msgs/msg/String", domain_id=DOMAIN,
                                  connect=[at], listen=[]) @ Trigger("msg")
        subscriber.then(publisher, sync=Queue())
    try:
        pipe.step(0.01)
        publisher_in = session.declare_publisher(in_key)

        def warm_up():
            publisher_in.put(_string_cdr("warm-up"))
            pipe.step(0.01)

        until(lambda: received, "a message relayed (both ends linked)", warm_up)
        # warm-ups put before the subscriber was linked went nowhere, and later ones may still be on
        # their way: one last marked warm-up, relayed after all of them (one publisher, one path:
        # in order), says none is left to join the batch
        publisher_in.put(_string_cdr("last warm-up"))
        until(lambda: received[-1][0] == "last warm-up", "the last warm-up relayed", lambda: pipe.step(0.01))
        assert subscriber.pending == 0
        batch = [f"m{i}" for i in range(5)]
        for text in batch:
            publisher_in.put(_string_cdr(text))
        until(lambda: subscriber.pending >= len(batch), "all 5 waiting for one tick")
        assert subscriber.pending == len(batch)
        pipe.step(0.01)  # the subscriber's burst of 5, a list of 5 to the publisher at the same tick
        until(lambda: received and received[-1][0] == batch[-1], "the burst relayed")
        publisher_in.undeclare()
    finally:
        pipe.reset()
        listener.undeclare()
    texts = [text for text, _ in received]
    assert texts[texts.index("m0"):] == batch, texts
    sequences = [sequence for _, sequence in received]  # the publisher's: one per message, none skipped
    assert sequences == list(range(sequences[0], sequences[0] + len(sequences)))


class Numbers(Flow):
    def step(self):
        return {"msg": [1.5, 2.5, 3.5]}


def test_a_list_of_numbers_for_a_multi_array_is_one_message(router):
    """A list of numbers is one value of a MultiArray (or a Vector3, Point, Quaternion), not a
    Queue's events: no number could be a message of such a type."""
    session, at = router
    key = f"{DOMAIN}/{NAMESPACE.strip('/')}/commands/std_msgs::msg::dds_::Float64MultiArray_/"
    received = []
    listener = session.declare_subscriber(key + "*", lambda sample: received.append(
        _jazzy.deserialize_cdr(sample.payload.to_bytes(), "std_msgs/msg/Float64MultiArray").data.tolist()))
    with Pipeline("ros_commands") as pipe:
        publisher = Ros2Publisher(f"{NAMESPACE}/commands", "std_msgs/msg/Float64MultiArray", domain_id=DOMAIN,
                                  connect=[at], listen=[]) @ Trigger("msg")
        (Numbers() @ Rate(hz=10)).then(publisher)
    try:
        until(lambda: received, "a Float64MultiArray", lambda: pipe.step(0.1))
    finally:
        pipe.reset()
        listener.undeclare()
    assert all(data == [1.5, 2.5, 3.5] for data in received)


class Frames(Flow):
    def step(self):
        return {"msg": np.full((2, 3, 3), 7, dtype=np.uint8)}


@pytest.mark.parametrize("frame_id, expected", [(None, "camera_node"), ("camera_optical", "camera_optical")])
def test_an_image_published_from_an_array_names_its_frame(router, frame_id, expected):
    """An image array alone says no frame: its Header's frame_id is the publisher's ``frame_id=``,
    by default its ROS node's name (it was '', which no subscriber can place)."""
    session, at = router
    key = f"{DOMAIN}/{NAMESPACE.strip('/')}/image_frames/sensor_msgs::msg::dds_::Image_/"
    received = []
    listener = session.declare_subscriber(key + "*", lambda sample: received.append(
        _jazzy.deserialize_cdr(sample.payload.to_bytes(), "sensor_msgs/msg/Image")))
    with Pipeline("ros_frames") as pipe:
        publisher = Ros2Publisher(f"{NAMESPACE}/image_frames", "sensor_msgs/msg/Image", node="camera_node",
                                  domain_id=DOMAIN, connect=[at], listen=[], frame_id=frame_id) @ Trigger("msg")
        (Frames() @ Rate(hz=10)).then(publisher)
    try:
        until(lambda: received, "an Image", lambda: pipe.step(0.1))
    finally:
        pipe.reset()
        listener.undeclare()
    assert all(m.header.frame_id == expected and (m.width, m.height) == (3, 2) for m in received)


def test_on_the_realtime_backend_a_flood_and_garbage_are_counted_in_the_log(router, tmp_path):
    """A subscriber's received, dropped and undecodable counts lived in its worker process, seen
    by nobody: now each tick that lost messages says so in its step record, which the log keeps."""
    session, at = router
    key = f"{DOMAIN}/{NAMESPACE.strip('/')}/flood/{JOINT_STATE}"
    with Pipeline("ros_flood") as pipe:
        Ros2Subscriber(f"{NAMESPACE}/flood", "sensor_msgs/msg/JointState", domain_id=DOMAIN, connect=[at],
                       listen=[], max_pending=4) @ Rate(hz=2)
    publisher, run_over, flooded = session.declare_publisher(key), threading.Event(), []

    def flood_once_subscribed():
        while not publisher.matching_status.matching:  # the worker's subscription reached the router
            if run_over.wait(0.01):
                return
        for i in range(50):  # within a ms: at most two of the 2 Hz ticks between them
            publisher.put(_joint_state_cdr(i))
        publisher.put(b"\x00\x01\x00\x00garbage")  # last: the oldest are the ones dropped
        flooded.append(True)

    flooder = threading.Thread(target=flood_once_subscribed)
    flooder.start()
    log = tmp_path / "flood.mcap"
    try:
        pipe.run(duration=8.0, backend="zenoh", log=log)
    finally:
        run_over.set()
        flooder.join()
        publisher.undeclare()
        pipe.reset()
    assert flooded, "the subscription never reached the router in an 8 s run"
    steps = [s for s in read_log(log).iter_steps() if s.node == "ros2_subscriber"]
    said = [s.detail["flow"] for s in steps if s.detail and "flow" in s.detail]
    dropped, undecodable = sum(d["dropped"] for d in said), sum(d["undecodable"] for d in said)
    assert undecodable == 1, said
    assert 51 - 2 * 4 <= dropped <= 51 - 4, said  # 4 kept for each tick the flood came before
    assert sum(d["received"] for d in said) == 51 - dropped - undecodable


def test_a_subscribers_backlog_is_bounded_in_bytes_too_dropping_the_oldest(router):
    """The backlog was bounded by count alone (1024 messages): of 6 MB frames, 6 GB."""
    session, at = router
    key = f"{DOMAIN}/{NAMESPACE.strip('/')}/frames/{STRING}"
    frames = [_string_cdr(f"{i:02d}" + "x" * 998) for i in range(10)]  # each the same size
    size = len(frames[0])
    with Pipeline("ros_frames") as pipe:
        subscriber = Ros2Subscriber(f"{NAMESPACE}/frames", "std_msgs/msg/String", domain_id=DOMAIN, connect=[at],
                                    listen=[], max_pending=100, max_pending_bytes=3 * size + size // 2) @ Rate(hz=100)
        sink = Collect() @ Trigger("msg")
        subscriber.then(sink, sync=Queue())
    try:
        pipe.step(0.01)
        publisher = session.declare_publisher(key)
        until(lambda: publisher.matching_status.matching, "the subscription reaching the router")
        for frame in frames:
            publisher.put(frame)
        publisher.put(_string_cdr("y" * 4 * size))  # bigger than the bound on its own: never kept
        until(lambda: subscriber.dropped + subscriber.pending >= len(frames) + 1, "every frame taken or dropped")
        trace = pipe.step(0.01)
        got, dropped = list(sink.got), subscriber.dropped
        said = [s.detail["flow"] for s in trace.steps if s.node == "ros2_subscriber" and s.detail
                and "flow" in s.detail]
        publisher.undeclare()
    finally:
        with pytest.warns(RetrieverWarning, match=r"dropped 8 \(past max_pending=100 messages or max_pending_bytes="):
            pipe.reset()
    assert [text[:2] for text in got] == ["07", "08", "09"]  # the newest 3 that fit: the oldest went
    assert dropped == len(frames) - 3 + 1
    assert said == [{"received": 3, "dropped": 8, "undecodable": 0}]
