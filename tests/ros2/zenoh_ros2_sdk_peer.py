"""A ROS 2 peer written with zenoh-ros2-sdk (PyPI), a second implementation of rmw_zenoh's
conventions that nobody on this team wrote: test_zenoh_ros2_sdk.py runs it with an interpreter
that has the SDK (never this project's), and reads what it prints, one JSON line per fact.

    python zenoh_ros2_sdk_peer.py MSGS_DIR hash TYPE...             the SDK's RIHS01 hash of each type
    python zenoh_ros2_sdk_peer.py MSGS_DIR subscribe PORT DOMAIN TOPIC N   N Twist messages, then exit
    python zenoh_ros2_sdk_peer.py MSGS_DIR publish PORT DOMAIN TOPIC       JointState at 50 Hz until killed
    python zenoh_ros2_sdk_peer.py MSGS_DIR topics PORT DOMAIN TOPIC        the topic's endpoints, as the SDK sees them

MSGS_DIR holds the .msg files the SDK reads (``<pkg>/msg/<Name>.msg``); an empty one is filled
from rosbags' Jazzy definitions, so the SDK never clones anything.
"""

import json
import os
import sys
import threading
import time
from pathlib import Path

import numpy as np

SEPARATOR = "=" * 80
TYPES = ("builtin_interfaces/msg/Time", "std_msgs/msg/Header", "geometry_msgs/msg/Vector3",
         "geometry_msgs/msg/Twist", "sensor_msgs/msg/JointState", "sensor_msgs/msg/Image")


def fill(msgs_dir: Path) -> None:
    from rosbags.typesys import Stores, get_typestore

    store = get_typestore(Stores.ROS2_JAZZY)
    for name in TYPES:
        path = msgs_dir / (name + ".msg")
        if not path.exists():
            text = store.generate_msgdef(name, ros_version=2)[0].split(SEPARATOR)[0]
            path.parent.mkdir(parents=True, exist_ok=True)
            path.write_text(text)


def say(**fact) -> None:
    print(json.dumps(fact), flush=True)


def main(msgs_dir: str, command: str, *args: str) -> None:
    os.environ["ZENOH_CONFIG_OVERRIDE"] = "scouting/multicast/enabled=false"
    fill(Path(msgs_dir))
    from zenoh_ros2_sdk import message_registry

    message_registry.get_registry(msgs_dir)
    if command == "hash":
        for name in args:
            say(type=name, hash=_hash(name))
        return
    port, domain, topic = int(args[0]), int(args[1]), args[2]
    where = {"router_ip": "127.0.0.1", "router_port": port, "domain_id": domain}
    if command == "subscribe":
        subscribe(topic, int(args[3]), where)
    elif command == "publish":
        publish(topic, where)
    elif command == "topics":
        from zenoh_ros2_sdk import discovery

        deadline, info = time.monotonic() + 20, None
        while info is None and time.monotonic() < deadline:  # a session's first query may see nothing yet
            info = discovery.get_topic_info(topic, timeout=0.5, verbose=True, **where)
        say(types=info.topic_types, publishers=info.publisher_count, subscribers=info.subscriber_count,
            nodes=sorted(e.node_name for e in info.publishers + info.subscribers))


def _hash(name: str) -> str:
    """The hash the SDK's publishers put in their keys, computed as they compute it."""
    from zenoh_ros2_sdk.message_registry import get_registry
    from zenoh_ros2_sdk.utils import get_type_hash, load_dependencies_recursive

    text = get_registry().get_msg_file_path(name).read_text()
    return get_type_hash(name, msg_definition=text,
                         dependencies=load_dependencies_recursive(name, text, get_registry()))


def subscribe(topic: str, n: int, where: dict) -> None:
    from zenoh_ros2_sdk import ROS2Subscriber

    done, count = threading.Event(), [0]

    def got(msg):
        say(linear_x=msg.linear.x, angular_z=msg.angular.z)
        count[0] += 1
        if count[0] >= n:
            done.set()

    subscriber = ROS2Subscriber(topic, "geometry_msgs/msg/Twist", got, node_name="sdk_listener", **where)
    say(ready=True)
    done.wait(120)
    subscriber.close()


def publish(topic: str, where: dict) -> None:
    from zenoh_ros2_sdk import ROS2Publisher, get_message_class

    publisher = ROS2Publisher(topic, "sensor_msgs/msg/JointState", node_name="sdk_talker", **where)
    Header, Time = get_message_class("std_msgs/msg/Header"), get_message_class("builtin_interfaces/msg/Time")
    say(ready=True)
    k = 0
    while True:
        k += 1
        publisher.publish(header=Header(stamp=Time(sec=k, nanosec=5), frame_id="sdk"), name=["a"],
                          position=np.array([float(k)]), velocity=np.zeros(0), effort=np.zeros(0))
        time.sleep(0.02)


if __name__ == "__main__":
    main(*sys.argv[1:])
