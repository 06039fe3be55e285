"""Flows for the IR tests, in an importable module so the IR's ``type`` fields
(``tests.ir_flows:Camera``) resolve when a pipeline is rebuilt from the IR alone.

``build()`` makes the small pipeline the golden file pins: a source, a LET planner fed by a
Window, a Rate controller fed by ActionChunking with a delayed feedback edge back to the planner,
and an untyped Trigger logger fed by a Queue.
"""

from __future__ import annotations

from retriever import ActionChunking, Flow, Latest, Pipeline, Queue, Rate, Trigger, Window, io


@io
class Frame:
    brightness: float
    k: int


@io
class PlanIn:
    recent: list[float]
    feedback: float | None = None


@io
class Plan:
    chunk: list[float]


@io
class ControlIn:
    chunk: float


@io
class ControlOut:
    position: float


class Camera(Flow[None, Frame]):
    """A brightness ramp with a period of ``period`` frames."""

    def __init__(self, period: int = 7, label: str = "cam"):
        self.period = period
        self.label = label
        self.k = 0

    def step(self, inp: None) -> Frame:
        self.k += 1
        return Frame(brightness=(self.k % self.period) / self.period, k=self.k)


class Planner(Flow[PlanIn, Plan]):
    """A chunk of ``steps`` targets ramping from the measured position to the mean brightness."""

    def __init__(self, steps: int = 5, *, gains: tuple = (0.5, 0.25)):
        self.steps = steps
        self.gains = list(gains)

    def step(self, inp: PlanIn) -> Plan:
        start = 0.0 if inp.feedback is None else inp.feedback
        goal = sum(inp.recent) / len(inp.recent) if inp.recent else 0.0
        g = self.gains[0]
        return Plan(chunk=[start + g * (goal - start) * (i + 1) / self.steps for i in range(self.steps)])


class Controller(Flow[ControlIn, ControlOut]):
    """A first-order servo on the current chunk row."""

    def __init__(self, gain: float = 0.5):
        self.gain = gain
        self.q = 0.0

    def step(self, inp: ControlIn) -> ControlOut:
        self.q += self.gain * (inp.chunk - self.q)
        return ControlOut(position=self.q)


class Logger(Flow):
    """Untyped: counts the positions it has seen (the paper's Listing-1 style)."""

    def __init__(self):
        self.seen = 0

    def step(self, position):
        self.seen += len(position)
        return {"seen": self.seen}


class Tool(Flow[None, Frame]):
    """A flow whose constructor argument is an arbitrary object: it runs, but cannot be rebuilt."""

    def __init__(self, model, steps: int = 3):
        self.model = model
        self.steps = steps

    def step(self, inp: None) -> Frame:
        return Frame(brightness=0.0, k=self.steps)


def build() -> Pipeline:
    """The small pipeline the golden IR file pins (fresh flows on every call)."""
    with Pipeline("small") as pipe:
        camera = Camera(period=5) @ Rate(hz=20)
        planner = Planner(4, gains=(0.5, 0.25)).configure(latency=0.25, on_error="skip_tick") @ Rate(hz=2)
        controller = Controller(gain=0.4) @ Rate(hz=50, offset=0.01)
        logger = Logger() @ Trigger("position")
        camera.then(planner, sync=Window(buffer_size=3), map={"brightness": "recent"})
        planner.then(controller, sync=ActionChunking(chunk_steps=4))
        controller.then(planner, sync=Latest(staleness=0.5), map={"position": "feedback"}, delay=0.02)
        controller.then(logger, sync=Queue(maxsize=4), qsize=32)
    return pipe
