"""Flows for the event-log tests, in an importable module so a log's IR (``tests.log.log_flows:…``)
and its ``@io`` values (codec dataclass extension) can be rebuilt by ``read_log``, ``replay`` and
``resim``, in this process or in a ``retriever`` subprocess started from the repository root.

Everything is a pure function of inputs and flow state: no wall time, no randomness (the frames'
noise comes from a generator seeded with the tick's count).

- ``build_small()``: the pipeline the golden log pins. A typed source, a typed filter and an
  untyped Trigger sink; three data channels with ints, floats, strings, bytes, a small numpy
  array and a nested ``@io`` dataclass.
- ``build_timing()``: a graph with an edge ``delay=``, a LET ``latency=``, a ``Trigger`` clock
  and two cycles (one broken in time by the delay, one instantaneous, bounded by the values).
- ``build_deep()``: one instant of many microsteps (past 127, the envelope's fixint) whose
  events carry 0-d float64 arrays.
- ``build_frames()``: a camera of incompressible frames and a LET flow of their brightness: a log
  that grows by about a frame per event, for replay's memory (tests/log/test_replay_stream.py).
- ``build_port_named_late()``: a Queue port named ``late`` that drops (its step records' detail
  counts the drops under the port's name, which is also a detail key).
- ``Emit``: an untyped source that emits, one per tick, the values it was given as an attribute
  (the Hypothesis round trip drives it).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from retriever import Flow, Latest, Pipeline, Queue, Rate, Trigger, io


# ---------------------------------------------------------------------------------------------
# Value types (importable, so the codec can rebuild them)
# ---------------------------------------------------------------------------------------------
@io
@dataclass
class Point:
    x: float
    y: float
    tags: tuple = ()


@io
@dataclass
class Labelled:
    label: str
    point: Point
    extra: dict = field(default_factory=dict)


@io
class Reading:
    k: int
    level: float
    pose: Labelled


@io
class Summary:
    total: int
    window: np.ndarray


# ---------------------------------------------------------------------------------------------
# The golden pipeline
# ---------------------------------------------------------------------------------------------
class Counter(Flow[None, Reading]):
    """k = 1, 2, 3…; a level with an exact binary fraction and a nested @io pose."""

    def __init__(self, scale: float = 0.25):
        self.scale = scale
        self.k = 0

    def step(self, inp: None) -> Reading:
        self.k += 1
        pose = Labelled(label=f"p{self.k}", point=Point(self.k * self.scale, -self.k * self.scale, ("t", self.k)),
                        extra={"b": bytes([self.k % 256]), 7: [self.k, None, True]})
        return Reading(k=self.k, level=self.k * self.scale, pose=pose)


class Accumulate(Flow[Reading, Summary]):
    """A running total of k and a small int16 array of the last levels (×4)."""

    def __init__(self):
        self.total = 0
        self.levels: list[int] = []

    def step(self, inp: Reading) -> Summary:
        self.total += inp.k
        self.levels = (self.levels + [int(inp.level * 4)])[-3:]
        return Summary(total=self.total, window=np.array(self.levels, dtype=np.int16))


class Tally(Flow):
    """Untyped Trigger sink: counts totals; emits only on even totals (sparse output)."""

    def __init__(self):
        self.seen = 0

    def step(self, total):
        self.seen += len(total)
        return {"count": self.seen} if total[-1] % 2 == 0 else None


def build_small() -> Pipeline:
    """0.5 s of it: 5 readings, 3 summaries, a few tallies (fresh flows on every call)."""
    with Pipeline("small_log") as pipe:
        counter = Counter(scale=0.25) @ Rate(hz=10)
        acc = Accumulate() @ Rate(hz=5, offset=0.05)
        tally = Tally() @ Trigger("total")
        counter.then(acc, sync=Latest())
        acc.then(tally, sync=Queue(maxsize=4))
    return pipe


# ---------------------------------------------------------------------------------------------
# Delay, latency, Trigger and cycles
# ---------------------------------------------------------------------------------------------
class Ramp(Flow):
    """Untyped source: 0, 1, 2…"""

    def __init__(self):
        self.k = 0

    def step(self):
        self.k += 1
        return {"level": self.k}


class Mixer(Flow):
    """Level plus (delayed) feedback; runs with a logical execution time."""

    def step(self, level, feedback=None):
        fb = 0 if feedback is None else feedback
        return {"mix": level * 10 + fb, "bounce": level % 3 + 1}


class Echo(Flow):
    """Trigger-clocked; emits the sum of what it got, mod 7 (the feedback)."""

    def step(self, mix):
        return {"feedback": sum(mix) % 7}


class Ping(Flow):
    """One side of an instantaneous cycle: counts the newest hop (pong's, else mixer's bounce)
    down by one; stops at 0 (no event)."""

    def step(self, bounce=None, pong=None):
        n = pong[-1] if pong else bounce[-1] if bounce else None
        return {"ping": n - 1} if n is not None and n > 0 else None


class Pong(Flow):
    """The other side: passes a positive hop back to ping."""

    def step(self, ping):
        return {"pong": ping} if ping > 0 else None


def build_timing() -> Pipeline:
    """ramp → mixer (latency 0.05 s) → echo (Trigger) → mixer (delay 0.02 s): a cycle broken in
    time; mixer → ping ⇄ pong (both Trigger): an instantaneous cycle of a few microsteps."""
    with Pipeline("timing") as pipe:
        ramp = Ramp() @ Rate(hz=10)
        mixer = Mixer().configure(latency=0.05) @ Rate(hz=20)
        echo = Echo() @ Trigger("mix")
        ping = Ping() @ Trigger()
        pong = Pong() @ Trigger("ping")
        ramp.then(mixer, sync=Latest(), map={"level": "level"})
        mixer.then(echo, sync=Queue(maxsize=8), map={"mix": "mix"})
        echo.then(mixer, sync=Latest(), map={"feedback": "feedback"}, delay=0.02)
        mixer.then(ping, sync=Queue(maxsize=4), map={"bounce": "bounce"})
        ping.then(pong, sync=Latest(), map={"ping": "ping"})
        pong.then(ping, sync=Queue(maxsize=4), map={"pong": "pong"})
    return pipe


# ---------------------------------------------------------------------------------------------
# Hypothesis source
# ---------------------------------------------------------------------------------------------
class Emit(Flow):
    """Untyped source emitting ``self.values[k]`` on tick k (the test sets ``values``)."""

    def __init__(self):
        self.values: list = []
        self.k = 0

    def step(self):
        k, self.k = self.k, self.k + 1
        return {"value": self.values[k]} if k < len(self.values) else None


def build_emit(values: list) -> Pipeline:
    with Pipeline("emit") as pipe:
        emit = Emit() @ Rate(hz=10)
        emit.values = list(values)
    return pipe


# ---------------------------------------------------------------------------------------------
# Deep instants: events at microsteps beyond 127 (the writer's general envelope path)
# ---------------------------------------------------------------------------------------------
class Start(Flow):
    """Untyped source: at each tick, asks for ``hops`` hops."""

    def __init__(self, hops: int = 150):
        self.hops = hops

    def step(self):
        return {"n": self.hops}


class Hop(Flow):
    """Counts the newest ``n`` down and emits it with a 0-d float64 array (a 16-byte codec payload)."""

    def step(self, n):
        k = n[-1]
        return {"n": k - 1, "x": np.array(float(k))} if k > 0 else None


def build_deep(hops: int = 150) -> Pipeline:
    """start → a ⇄ b, both Trigger with Queue edges: one instant of ``hops`` + 1 microsteps."""
    with Pipeline("deep", max_microsteps=1000) as pipe:
        start = Start(hops) @ Rate(hz=1)
        a = Hop().named("a") @ Trigger("n")
        b = Hop().named("b") @ Trigger("n")
        start.then(a, sync=Queue(), map={"n": "n"})
        a.then(b, sync=Queue(), map={"n": "n"})
        b.then(a, sync=Queue(), map={"n": "n"})
    return pipe


# ---------------------------------------------------------------------------------------------
# Big frames: a log that grows fast for few steps (replay's memory)
# ---------------------------------------------------------------------------------------------
class Frames(Flow):
    """Untyped source: ``size`` bytes of noise a tick, seeded with the tick's count (zstd cannot
    shrink it: the log grows by about ``size`` an event)."""

    def __init__(self, size: int = 1 << 16):
        self.size = size
        self.k = 0

    def step(self):
        self.k += 1
        return {"frame": np.random.default_rng(self.k).integers(0, 256, self.size, dtype=np.uint8)}


class Brightness(Flow):
    """Untyped: the newest frame's mean, and how many it has seen."""

    def __init__(self):
        self.seen = 0

    def step(self, frame):
        self.seen += 1
        return {"mean": float(frame.mean()), "seen": self.seen}


def build_frames(size: int = 1 << 16) -> Pipeline:
    """camera @ 30 Hz → brightness @ 30 Hz (offset 10 ms, latency 0.1 s: its outputs are logged
    three ticks after it runs), ``Latest()``."""
    with Pipeline("frames") as pipe:
        camera = Frames(size).named("camera") @ Rate(hz=30)
        brightness = Brightness().named("brightness").configure(latency=0.1) @ Rate(hz=30, offset=0.01)
        camera.then(brightness, sync=Latest())
    return pipe
