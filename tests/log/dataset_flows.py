"""Flows for the dataset-export tests (tests/log/test_dataset.py), importable so a log's IR and
its ``@io`` values can be rebuilt: a camera source and a policy that consumes its image, its
joint angles and a pose, all pure functions of the tick count.

- ``build_camera(...)``: ``camera @ Rate(20)`` → ``policy @ Rate(10)`` (Latest on every port);
  with ``note=True`` the camera also sends a text port the policy consumes; with
  ``trigger=True`` the policy ticks on each image instead; ``latency`` gives both flows a LET
  (a real-time run then re-simulates exactly); ``pause=(a, b)``: the camera sends nothing on its
  ticks a to b, and the policy's Latest goes stale after 0.1 s (its ticks skip there).
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
    flag: float | None = None  # now and then: when the camera's count is a multiple of 8


def picture(k: int) -> np.ndarray:
    """A uint8 SIZE×SIZE×3 image that differs in every pixel from tick to tick."""
    base = np.arange(SIZE * SIZE * 3, dtype=np.int64).reshape(SIZE, SIZE, 3)
    return ((base * 7 + k * 13) % 256).astype(np.uint8)


class Camera(Flow[None, Shot]):
    """Sends nothing on its ticks ``pause_from`` to ``pause_to`` (counted from 1), when given."""

    def __init__(self, pause_from: int = 0, pause_to: int = 0):
        self.pause_from, self.pause_to = pause_from, pause_to
        self.k = 0

    def step(self, inp: None) -> Shot | None:
        self.k += 1
        k = self.k
        if self.pause_from <= k <= self.pause_to:
            return None
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
    return Command(action=np.array([joints[0] * 2 + pose.x, float(image[0, 0, 0])], dtype=np.float32),
                   flag=1.0 if joints[0] % 8 == 0 else None)


class Policy(Flow[Seen, Command]):
    def step(self, inp: Seen) -> Command:
        return _act(inp.image, inp.joints, inp.pose)


class NotedPolicy(Flow[NotedSeen, Command]):
    def step(self, inp: NotedSeen) -> Command:
        return _act(inp.image, inp.joints, inp.pose)


def build_camera(note: bool = False, trigger: bool = False, latency: float = 0.0, camera_hz: int = 20,
                 policy_hz: int = 10, pause: tuple[int, int] = (0, 0)) -> Pipeline:
    with Pipeline("pick cube") as pipe:
        camera = (NotedCamera() if note else Camera(*pause)).named("camera") @ Rate(camera_hz)
        policy = (NotedPolicy() if note else Policy()).named("policy") @ (Trigger("image") if trigger
                                                                          else Rate(policy_hz))
        if latency:
            camera.configure(latency=latency)
            policy.configure(latency=latency)
        camera.then(policy, sync=Latest(staleness=0.1) if pause != (0, 0) else Latest())
    return pipe


# -- untyped flows: a value of any kind, and an output no edge reads -----------------------------
#: the values a ``Sender`` sends, by name (each a function of its tick count k, from 1)
VALUES = {
    "float": lambda k: np.array([k, k / 2], dtype=np.float64),
    "nan_at_3": lambda k: np.array([np.nan if k == 3 else k, 1.0]),
    "big_int": lambda k: 2**70 + k,
    "empty": lambda k: np.zeros((0,)),
    "complex": lambda k: np.array([k + 1j]),
    "wide": lambda k: np.full(5000, k, dtype=np.float32),
}


class Sender(Flow):
    def __init__(self, kind: str = "float"):
        self.kind, self.k = kind, 0

    def step(self):
        self.k += 1
        return {"v": VALUES[self.kind](self.k)}


class Pol(Flow):
    """Its output ``a`` goes to no flow: the IR names no output port of it."""

    def step(self, v):
        return {"a": np.array([2.0])}


def build_untyped(kind: str = "float") -> Pipeline:
    with Pipeline("untyped") as pipe:
        sender = Sender(kind).named("sender") @ Rate(10)
        sender.then(Pol().named("pol") @ Rate(10), sync=Latest())
    return pipe
