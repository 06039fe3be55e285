"""Retriever's ROS 2 flows against zenoh-ros2-sdk (PyPI), an implementation of rmw_zenoh's
conventions that nobody on this team wrote: its type hashes (computed by its own code from .msg
text), its subscriber and publisher, and its graph discovery (its ``ros2 topic info``).

The SDK is not one of this project's dependencies: it runs in an interpreter of its own, named by
``RETRIEVER_ZENOH_ROS2_SDK_PYTHON`` (a venv with ``pip install zenoh-ros2-sdk``), as the program
zenoh_ros2_sdk_peer.py. Without it these tests skip and say so. The SDK's peer connects to the
test's own Zenoh router (conftest.py's ``router``, the stand-in for rmw_zenohd), in a ROS domain and
under topics no other test uses.
"""

from __future__ import annotations

import json
import os
import queue
import subprocess
import threading
from pathlib import Path

import pytest

from retriever import Pipeline, Queue, Rate, Trigger
from retriever.ros2 import Ros2Publisher, Ros2Subscriber, type_hash

from .helpers import until
from .test_flows import DOMAIN, NAMESPACE, Collect, Speed

SDK_PYTHON = os.environ.get("RETRIEVER_ZENOH_ROS2_SDK_PYTHON")
PEER = Path(__file__).with_name("zenoh_ros2_sdk_peer.py")

pytestmark = pytest.mark.skipif(
    not SDK_PYTHON, reason="zenoh-ros2-sdk is not one of this project's dependencies: set "
    "RETRIEVER_ZENOH_ROS2_SDK_PYTHON to a Python that has it (python -m venv v && v/bin/pip install zenoh-ros2-sdk)")


class SdkPeer:
    """zenoh_ros2_sdk_peer.py running under the SDK's interpreter; its JSON lines on ``lines``."""

    def __init__(self, msgs_dir: Path, *args: object):
        self.process = subprocess.Popen([SDK_PYTHON, str(PEER), str(msgs_dir), *map(str, args)],
                                        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        self.lines: queue.Queue = queue.Queue()
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()

    def _read(self) -> None:
        for line in self.process.stdout:
            self.lines.put(json.loads(line))

    def next(self, act=lambda: None) -> dict:
        """The peer's next line, ``act()`` while it waits; the test fails if none comes within the
        bound, or the peer ended without one (saying what it wrote on stderr)."""
        got: list[dict] = []

        def wait_a_little() -> None:
            act()
            try:
                got.append(self.lines.get(timeout=0.05))
            except queue.Empty:
                pass

        until(lambda: got or (self.process.poll() is not None and self.lines.empty()),
              "a line from the SDK's peer", wait_a_little)
        if not got:
            raise AssertionError(f"the SDK's peer said nothing more (exit {self.process.poll()}): "
                                 f"{self.process.stderr.read()}")
        return got[0]

    def stop(self) -> None:
        if self.process.poll() is None:
            self.process.terminate()
        self.process.wait(timeout=30)
        self._reader.join(timeout=30)
        self.process.stdout.close()
        self.process.stderr.close()


@pytest.fixture
def msgs_dir(tmp_path):
    return tmp_path / "msgs"


def test_the_sdk_computes_the_same_type_hashes(msgs_dir):
    names = ["std_msgs/msg/Header", "geometry_msgs/msg/Twist", "sensor_msgs/msg/JointState", "sensor_msgs/msg/Image"]
    peer = SdkPeer(msgs_dir, "hash", *names)
    try:
        theirs = {fact["type"]: fact["hash"] for fact in (peer.next() for _ in names)}
    finally:
        peer.stop()
    assert theirs == {name: type_hash(name) for name in names}


def test_the_sdks_subscriber_takes_what_a_ros2_publisher_flow_publishes(router, msgs_dir):
    _, at = router
    port = int(at.rsplit(":", 1)[1])
    peer = SdkPeer(msgs_dir, "subscribe", port, DOMAIN, f"{NAMESPACE}/sdk_cmd_vel", 3)
    with Pipeline("ros_to_sdk") as pipe:
        speed = Speed() @ Rate(hz=10)
        publisher = Ros2Publisher(f"{NAMESPACE}/sdk_cmd_vel", "geometry_msgs/msg/Twist", domain_id=DOMAIN,
                                  connect=[at], listen=[]) @ Trigger("msg")
        speed.then(publisher)
    try:
        assert peer.next() == {"ready": True}
        got = [peer.next(act=lambda: pipe.step(0.1)) for _ in range(3)]
    finally:
        pipe.reset()
        peer.stop()
    speeds = [fact["linear_x"] for fact in got]
    assert speeds == sorted(speeds) and all(abs(s * 10 - round(s * 10)) < 1e-9 for s in speeds)
    assert all(fact["angular_z"] == 0.0 for fact in got)


def test_a_ros2_subscriber_flow_takes_what_the_sdks_publisher_publishes(router, msgs_dir):
    _, at = router
    port = int(at.rsplit(":", 1)[1])
    peer = SdkPeer(msgs_dir, "publish", port, DOMAIN, f"{NAMESPACE}/sdk_joints")
    with Pipeline("sdk_to_ros") as pipe:
        subscriber = Ros2Subscriber(f"{NAMESPACE}/sdk_joints", "sensor_msgs/msg/JointState", domain_id=DOMAIN,
                                    connect=[at], listen=[]) @ Rate(hz=100)
        sink = Collect() @ Trigger("msg")
        subscriber.then(sink, sync=Queue(maxsize=1000))
    try:
        assert peer.next() == {"ready": True}
        until(lambda: len(sink.got) >= 3, "3 messages from the SDK's publisher", lambda: pipe.step(0.01))
        got = sink.got
    finally:
        pipe.reset()
        peer.stop()
    positions = [value["position"][0] for value in got]
    assert positions == sorted(positions) and all(p == int(p) for p in positions)
    assert all(value["name"] == ["a"] and value["frame_id"] == "sdk" and
               value["stamp"] == int(value["position"][0]) * 1_000_000_000 + 5 for value in got)


def test_the_sdks_discovery_sees_a_ros2_publisher_flow_and_its_node(router, msgs_dir):
    _, at = router
    port = int(at.rsplit(":", 1)[1])
    with Pipeline("ros_graph") as pipe:
        speed = Speed() @ Rate(hz=10)
        publisher = Ros2Publisher(f"{NAMESPACE}/seen", "geometry_msgs/msg/Twist", node="driver", domain_id=DOMAIN,
                                  connect=[at], listen=[]) @ Trigger("msg")
        speed.then(publisher)
    try:
        pipe.step(0.1)  # setup(): the publisher's tokens are declared
        peer = SdkPeer(msgs_dir, "topics", port, DOMAIN, f"{NAMESPACE}/seen")
        try:
            seen = peer.next()
        finally:
            peer.stop()
    finally:
        pipe.reset()
    assert seen == {"types": ["geometry_msgs/msg/Twist"], "publishers": 1, "subscribers": 0, "nodes": ["driver"]}
