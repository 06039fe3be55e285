"""ROS 2's own tools against Retriever: ``ros2 topic echo`` (rmw_zenoh's subscription, its CDR
and attachment checks) and ``ros2 topic list`` (its graph cache, from the liveliness tokens) on
a Ros2Publisher's topic. Where ROS 2 with rmw_zenoh is not installed this test skips and says so.

ROS's session is pointed at the test's own Zenoh router (conftest.py) by a session config file
(``ZENOH_SESSION_CONFIG_URI``), in a ROS domain and under a topic no other test uses.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess

import pytest

from retriever import Flow, Pipeline, Rate, Trigger
from retriever.ros2 import Ros2Publisher

from .helpers import BOUND_S, until
from .test_flows import DOMAIN, NAMESPACE


def _ros2_with_rmw_zenoh() -> str | None:
    """Why this test cannot run here, or None when it can."""
    if shutil.which("ros2") is None:
        return "ROS 2 is not installed here (no ros2 on PATH): source a ROS 2 Jazzy install with rmw_zenoh_cpp"
    found = subprocess.run(["ros2", "pkg", "prefix", "rmw_zenoh_cpp"], capture_output=True, text=True, timeout=60)
    if found.returncode != 0:
        return "ROS 2 is installed but rmw_zenoh_cpp is not (apt install ros-<distro>-rmw-zenoh-cpp)"
    return None


class Greeter(Flow):
    def __init__(self):
        self.k = 0

    def step(self):
        self.k += 1
        return {"msg": f"hello from retriever {self.k}"}


def test_ros2_topic_echo_and_list_see_a_ros2_publisher_flow(router, tmp_path):
    why_not = _ros2_with_rmw_zenoh()
    if why_not:
        pytest.skip(why_not)
    _, at = router
    config = tmp_path / "session.json5"
    config.write_text(json.dumps({"mode": "peer", "connect": {"endpoints": [at]},
                                  "listen": {"endpoints": ["tcp/127.0.0.1:0"]},
                                  "scouting": {"multicast": {"enabled": False}}}))
    env = {**os.environ, "RMW_IMPLEMENTATION": "rmw_zenoh_cpp", "ROS_DOMAIN_ID": str(DOMAIN),
           "ZENOH_SESSION_CONFIG_URI": str(config)}
    topic = f"{NAMESPACE}/greeting"
    with Pipeline("ros_cli") as pipe:
        greeter = Greeter() @ Rate(hz=10)
        publisher = Ros2Publisher(topic, "std_msgs/msg/String", node="greeter", domain_id=DOMAIN,
                                  connect=[at], listen=[]) @ Trigger("msg")
        greeter.then(publisher)
    echo = subprocess.Popen(["ros2", "topic", "echo", "--once", topic, "std_msgs/msg/String"], env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        def step_and_wait() -> None:
            pipe.step(0.1)
            try:
                echo.wait(timeout=0.05)
            except subprocess.TimeoutExpired:
                pass

        until(lambda: echo.poll() is not None, "ros2 topic echo's message", step_and_wait,
              timeout=BOUND_S * 3)  # ros2's own start-up is slow
        listed = subprocess.run(["ros2", "topic", "list", "--no-daemon", "-t"], env=env, capture_output=True,
                                text=True, timeout=BOUND_S * 3)
    finally:
        if echo.poll() is None:
            echo.terminate()
        out, err = echo.communicate(timeout=30)
        pipe.reset()
    assert echo.returncode == 0, f"ros2 topic echo: {err}"
    assert "data: hello from retriever" in out
    assert f"{topic} [std_msgs/msg/String]" in listed.stdout
