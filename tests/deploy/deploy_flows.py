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
