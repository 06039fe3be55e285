"""Flows for the dataset-export tests (tests/log/test_dataset.py), importable so a log's IR and
its ``@io`` values can be rebuilt: a camera source and a policy that consumes its image, its
joint angles and a pose, all pure functions of the tick count.

- ``build_camera(...)``: ``camera @ Rate(20)`` → ``policy @ Rate(10)`` (Latest on every port);
  with ``note=True`` the camera also sends a text port the policy consumes; with
  ``trigger=True`` the policy ticks on each image instead; ``latency`` gives both flows a LET
  (a real-time run then re-simulates exactly).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from retriever import Flow, Latest, Pipeline, Rate, Trigger, io

SIZE = 8  # image side, pixels


@io
@dataclass
class Pose:
    x: float
    y: float
    q: np.ndarray
    label: str


@io
class Shot:
    image: np.ndarray
    joints: np.ndarray
    pose: Pose


@io
class NotedShot:
    image: np.ndarray
    joints: np.ndarray
    pose: Pose
    note: str


@io
class Command:
    action: np.ndarray


def picture(k: int) -> np.ndarray:
    """A uint8 SIZE×SIZE×3 image that differs in every pixel from tick to tick."""
    base = np.arange(SIZE * SIZE * 3, dtype=np.int64).reshape(SIZE, SIZE, 3)
    return ((base * 7 + k * 13) % 256).astype(np.uint8)


class Camera(Flow[None, Shot]):
    def __init__(self):
        self.k = 0

    def step(self, inp: None) -> Shot:
        self.k += 1
        k = self.k
        return Shot(image=picture(k), joints=np.array([k, -k, k / 4], dtype=np.float32),
                    pose=Pose(x=k * 0.5, y=-k * 0.25, q=np.array([k, k + 1], dtype=np.float64), label=f"p{k}"))


class NotedCamera(Flow[None, NotedShot]):
    def __init__(self):
        self.k = 0

    def step(self, inp: None) -> NotedShot:
        self.k += 1
        k = self.k
        return NotedShot(image=picture(k), joints=np.array([k, -k, k / 4], dtype=np.float32),
                         pose=Pose(x=k * 0.5, y=-k * 0.25, q=np.array([k, k + 1], dtype=np.float64), label=f"p{k}"),
                         note=f"pick the cube {k % 2}")


@io
class Seen:
    image: np.ndarray
    joints: np.ndarray
    pose: Pose


@io
class NotedSeen:
    image: np.ndarray
    joints: np.ndarray
    pose: Pose
    note: str


def _act(image: np.ndarray, joints: np.ndarray, pose: Pose) -> Command:
    return Command(action=np.array([joints[0] * 2 + pose.x, float(image[0, 0, 0])], dtype=np.float32))


class Policy(Flow[Seen, Command]):
    def step(self, inp: Seen) -> Command:
        return _act(inp.image, inp.joints, inp.pose)


class NotedPolicy(Flow[NotedSeen, Command]):
    def step(self, inp: NotedSeen) -> Command:
        return _act(inp.image, inp.joints, inp.pose)


def build_camera(note: bool = False, trigger: bool = False, latency: float = 0.0,
                 camera_hz: int = 20, policy_hz: int = 10) -> Pipeline:
    with Pipeline("pick cube") as pipe:
        camera = (NotedCamera() if note else Camera()) @ Rate(camera_hz)
        policy = (NotedPolicy() if note else Policy()) @ (Trigger("image") if trigger else Rate(policy_hz))
        if latency:
            camera.configure(latency=latency)
            policy.configure(latency=latency)
        camera.then(policy, sync=Latest())
    return pipe
