"""Quickstart: a camera, a slow policy emitting action chunks, a fast controller, feedback.

    camera @ 30 Hz ──frame──▶ policy @ 2 Hz (latency 0.3 s) ──chunk──▶ controller @ 200 Hz
                                  ▲                                          │
                                  └────────────── state (Latest) ────────────┘

Run it:  retriever run examples/quickstart.py --duration 5
IR:      retriever ir examples/quickstart.py --format mermaid
"""

from dataclasses import dataclass

import numpy as np

from retriever import ActionChunking, Flow, Latest, Pipeline, Rate, io

CHUNK_STEPS = 100  # 0.5 s of actions at 200 Hz: one chunk covers the policy's period


@io
@dataclass
class Frame:
    frame: np.ndarray


@io
@dataclass
class PolicyIn:
    frame: np.ndarray
    state: np.ndarray | None = None  # feedback; None until the controller has run


@io
@dataclass
class Chunk:
    chunk: np.ndarray  # (CHUNK_STEPS, 2) joint targets


@io
@dataclass
class ControlIn:
    chunk: np.ndarray  # one row of the current chunk, chosen by ActionChunking


@io
@dataclass
class State:
    state: np.ndarray


class Camera(Flow[None, Frame]):
    """A synthetic 8×8 grey image whose brightness ramps with time."""

    def __init__(self):
        self.k = 0

    def step(self, inp: None) -> Frame:
        self.k += 1
        return Frame(frame=np.full((8, 8), self.k % 256, dtype=np.uint8))


class Policy(Flow[PolicyIn, Chunk]):
    """A stand-in VLA: aims the joints at the image brightness, starting from the measured state.

    Its "weights" (a fixed projection) are made in ``setup()``, where a real policy loads its
    checkpoint: once, in the process that steps it, before its first tick."""

    def setup(self) -> None:
        self.weights = np.array([1.0, -1.0]) / 255.0

    def step(self, inp: PolicyIn) -> Chunk:
        start = np.zeros(2) if inp.state is None else inp.state
        goal = inp.frame.mean() * self.weights
        alphas = np.linspace(0.0, 1.0, CHUNK_STEPS)[:, None]
        return Chunk(chunk=start + alphas * (goal - start))


class Controller(Flow[ControlIn, State]):
    """A first-order joint servo tracking the current chunk row."""

    def __init__(self, gain: float = 0.2):
        self.gain = gain
        self.q = np.zeros(2)

    def step(self, inp: ControlIn) -> State:
        self.q = self.q + self.gain * (inp.chunk - self.q)
        return State(state=self.q.copy())


with Pipeline("quickstart") as pipe:
    camera = Camera() @ Rate(hz=30)
    policy = Policy().configure(latency=0.3) @ Rate(hz=2)
    controller = Controller(gain=0.2) @ Rate(hz=200)
    camera.then(policy, sync=Latest(staleness=0.1))
    policy.then(controller, sync=ActionChunking(control_hz=200, chunk_steps=CHUNK_STEPS))
    controller.then(policy, sync=Latest())

if __name__ == "__main__":
    trace = pipe.run(duration=5.0)
    print(f"{len(trace.events)} events, {len(trace.steps)} steps, digest {trace.digest()[:16]}")
