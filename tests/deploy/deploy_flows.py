"""Flows deployed on worker daemons in the netns lab (test_deploy.py): importable by a worker
from its ``--path`` (this folder) as the module ``deploy_flows``, which is how the coordinator
loads this file too (``retriever deploy tests/deploy/deploy_flows.py:pipe``)."""

from __future__ import annotations

from dataclasses import dataclass

from retriever import Flow, Latest, Pipeline, Rate, Trigger, io


@io
@dataclass
class Count:
    n: int


class Counter(Flow[None, Count]):
    """A source: 1, 2, 3, …"""

    def __init__(self):
        self.k = 0

    def reset(self) -> None:
        self.k = 0

    def step(self, inp: None) -> Count:
        self.k += 1
        return Count(n=self.k)


class Relay(Flow[Count, Count]):
    """Passes the count on."""

    def step(self, inp: Count) -> Count:
        return Count(n=inp.n)


with Pipeline("lab") as pipe:
    counter = Counter().configure(name="counter") @ Rate(hz=20)
    relay = Relay().configure(name="relay") @ Trigger()
    sink = Relay().configure(name="sink") @ Trigger()
    counter.then(relay, sync=Latest()).then(sink, sync=Latest())



#: a frame's bytes: at 50 Hz, enough to fill a link's queue within about a second once its far end is cut off
FRAME_BYTES = 32 << 10


@io
@dataclass
class Frame:
    n: int
    pixels: bytes


class Camera(Flow[None, Frame]):
    """A source of frames: 1, 2, 3, …, each with FRAME_BYTES of pixels."""

    def __init__(self):
        self.k = 0

    def reset(self) -> None:
        self.k = 0

    def step(self, inp: None) -> Frame:
        self.k += 1
        return Frame(n=self.k, pixels=bytes(FRAME_BYTES))


class Viewer(Flow[Frame, None]):
    """Looks at each frame, on a clock of its own: a tick whose frame has not come by its deadline is skipped."""

    def step(self, inp: Frame) -> None:
        return None


with Pipeline("lab-watch") as watched:
    camera = Camera().configure(name="camera") @ Rate(hz=50)
    viewer = Viewer().configure(name="viewer") @ Rate(hz=50)
    camera.then(viewer, sync=Latest())


with Pipeline("lab-grouped") as grouped:
    # counter and relay share the process "front" (the placement file adds tap: test_deploy.py);
    # echo and sink run alone
    source = Counter().configure(name="counter", process="front") @ Rate(hz=20)
    middle = Relay().configure(name="relay", process="front") @ Trigger()
    source.then(middle, sync=Latest()).then(Relay().configure(name="sink") @ Trigger(), sync=Latest())
    source.then(Relay().configure(name="tap") @ Trigger(), sync=Latest())
    middle.then(Relay().configure(name="echo") @ Trigger(), sync=Latest())


@io
@dataclass
class Command:
    a: int


@io
@dataclass
class ControlIn:
    n: int  # the camera's count, from beside it
    a: int | None = None  # the policy's command, from another machine; None until one came


class Policy(Flow[Count, Command]):
    """Commands the count it was shown."""

    def step(self, inp: Count) -> Command:
        return Command(a=inp.n)


class Controller(Flow[ControlIn, None]):
    """Acts on the newest frame count and command, on a clock of its own."""

    def step(self, inp: ControlIn) -> None:
        return None


#: how long the controller's tick waits for the policy's command before it runs without it
POLICY_DEADLINE_S = 0.03


with Pipeline("lab-local") as local:
    # camera and controller on the robot, the policy on another machine (test_run_router_deploy.py)
    frames = Counter().configure(name="camera") @ Rate(hz=20)
    controller = Controller().configure(name="controller") @ Rate(hz=20)
    frames.then(controller, sync=Latest())
    frames.then(Policy().configure(name="policy") @ Trigger(), sync=Latest()).then(
        controller, sync=Latest(), deadline=POLICY_DEADLINE_S)
