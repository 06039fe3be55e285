"""Flows used by the Zenoh benchmarks (latency.py, control_jitter.py, idle_cpu.py, scale*.py, ...).

The zenoh backend rebuilds every flow in its own worker process from the IR (``module:Class`` +
constructor arguments), so benchmark flows live here, in an importable module, with
msgpack-serializable constructor arguments only. The benchmark scripts put ``benchmarks/`` on
``sys.path``; the coordinator hands its ``sys.path`` to the workers.
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass

import numpy as np

from retriever import Burst, Flow, io


# ---------------------------------------------------------------------------------------------
# latency.py, receive_cold.py
# ---------------------------------------------------------------------------------------------
@io
@dataclass
class Frame:
    frame: dict  # {"data": uint8 ndarray, "sent_ns": int}: one port, one message per step


@io
@dataclass
class Lat:
    lat: list  # [sent_ns, received_ns, size]


# Typed flows: they ran on the zenoh backend from the start (at e6109b6 an untyped flow with
# outputs crashed in its worker with a KeyError on the port; fixed since, in 0351d30).
class PayloadSource(Flow[None, Frame]):
    """Emits ``{"data": uint8[size], "sent_ns": wall ns}`` on port ``frame``.

    Each step emits a fresh array, as a camera driver hands over a fresh buffer (an emitted value
    is immutable: docs/semantics.md), copied from one allocated once before ``sent_ns`` is taken:
    the copy is not timed. Its first bytes change each step, so no layer could skip or dedupe
    anything. ``sent_ns`` is taken last, right before ``step`` returns."""

    def __init__(self, size: int):
        self.size = size
        self.data = np.zeros(size, dtype=np.uint8)
        self.k = 0

    def fresh(self) -> np.ndarray:
        """This step's array: the template's copy, its first bytes the step's count."""
        self.k += 1
        data = self.data.copy()
        data[: min(8, self.size)] = self.k % 256
        return data

    def step(self) -> Frame:
        data = self.fresh()
        return Frame(frame={"data": data, "sent_ns": time.time_ns()})


class LatencySink(Flow[Frame, Lat]):
    """Triggered by ``frame``: outputs ``lat`` = [sent_ns, received_ns, size] with
    ``received_ns`` = ``time.time_ns()`` first thing in ``step``. The events of ``lat`` are the
    measurement (one per received frame). With ``record`` (a file path), each is also appended to
    that file as a line ``sent_ns received_ns size``: a run that keeps no values (keep="records")
    has the measurement there."""

    def __init__(self, record: str | None = None):
        self.record = record

    def step(self, inp: Frame) -> Lat:
        received = time.time_ns()
        lat = [inp.frame["sent_ns"], received, int(inp.frame["data"].size)]
        if self.record is not None:
            with open(self.record, "a", encoding="ascii") as f:
                f.write(f"{lat[0]} {lat[1]} {lat[2]}\n")
        return Lat(lat=lat)


class StampedSink(LatencySink):
    """The latency sink, noting in ``starts`` (this process's) when each step starts, by
    ``time.perf_counter_ns()`` (receive_cold.py)."""

    starts: list[int] = []

    def step(self, inp: Frame) -> Lat:
        StampedSink.starts.append(time.perf_counter_ns())
        return super().step(inp)


# ---------------------------------------------------------------------------------------------
# control_jitter.py / idle_cpu.py
# ---------------------------------------------------------------------------------------------
class Idle(Flow):
    """Does nothing and outputs nothing (a step record per tick is what it leaves)."""

    def step(self):
        return None


class Burner(Flow):
    """Burns the CPU: each step spins in a Python loop for ``busy_s`` seconds, outputs nothing.

    On ``Rate(hz)`` with ``busy_s`` just under ``1/hz`` this keeps one core busy the whole run
    without overrunning its own period."""

    def __init__(self, busy_s: float):
        self.busy_s = busy_s

    def step(self):
        end = time.perf_counter() + self.busy_s
        n = 0
        while time.perf_counter() < end:
            n += 1


# ---------------------------------------------------------------------------------------------
# zenoh_drops.py
# ---------------------------------------------------------------------------------------------
@io
@dataclass
class Count:
    count: int


class Counter(Flow[None, Count]):
    """Outputs 1, 2, 3, ... (one small event per tick)."""

    def __init__(self):
        self.k = 0

    def step(self) -> Count:
        self.k += 1
        return Count(count=self.k)


# ---------------------------------------------------------------------------------------------
# control_jitter.py, idle_cpu.py: measure a run from outside while it goes
# ---------------------------------------------------------------------------------------------
class BackgroundRun:
    """``pipe.run(duration, backend="zenoh")`` in a thread; the constructor returns once the run
    has agreed its T0 (``.session``: the Coordinator, ``.t0``), ``finish()`` joins it and returns
    the trace (or re-raises the run's error)."""

    def __init__(self, pipe, duration: float):
        self._result: dict = {}

        def go() -> None:
            try:
                self._result["trace"] = pipe.run(duration=duration, backend="zenoh", quiet=True)
            except BaseException as e:  # noqa: BLE001 - re-raised by finish()
                self._result["error"] = e

        self._runner = threading.Thread(target=go)
        self._runner.start()
        session = None
        while self._runner.is_alive() and (session is None or session.t0 is None):
            session = pipe.session
            time.sleep(0.005)
        if "error" in self._result or session is None or session.t0 is None:
            self._runner.join()
            raise SystemExit(f"the run did not start: {self._result.get('error')}")
        self.session, self.t0 = session, session.t0

    def finish(self):
        self._runner.join()
        if "error" in self._result:
            raise self._result["error"]
        return self._result["trace"]


# ---------------------------------------------------------------------------------------------
# scale.py
# ---------------------------------------------------------------------------------------------
class Keep(Flow[Count, Count]):
    """Passes on the newest count it was given (a consumer of a camera-like source)."""

    def step(self, inp: Count) -> Count:
        return Count(count=inp.count)


class Join(Flow):
    """The end of a fan-in (scale_latency.py, determinism_cost.py): takes every count its
    producers sent since its last tick (a ``Queue``), outputs nothing (its step records are the
    measurement: which copies each step consumed, and when it started)."""

    def step(self, count):
        return None


# ---------------------------------------------------------------------------------------------
# memory.py: a camera, a policy and a controller, as on a robot
# ---------------------------------------------------------------------------------------------
@io
@dataclass
class CameraImage:
    k: int
    pixels: np.ndarray  # H×W×3 uint8


@io
@dataclass
class ActionChunk:
    k: int
    actions: np.ndarray  # horizon × joints


@io
@dataclass
class JointCommand:
    u: np.ndarray


class RGBCamera(Flow[None, CameraImage]):
    """A new 640×480 RGB frame each tick: noise (which the log's zstd cannot shrink, unlike a real
    image: the worst case for the log), one of 16 made in setup(), stamped with k."""

    def __init__(self, height: int = 480, width: int = 640):
        self.shape, self.k = (height, width, 3), 0

    def setup(self):
        self.bank = np.random.default_rng(0).integers(0, 256, (16, *self.shape), dtype=np.uint8)

    def step(self) -> CameraImage:
        self.k += 1
        pixels = self.bank[self.k % len(self.bank)].copy()
        pixels.flat[:8] = np.frombuffer(self.k.to_bytes(8, "little"), np.uint8)  # k, in the first bytes
        return CameraImage(self.k, pixels)


class ChunkPolicy(Flow[CameraImage, ActionChunk]):
    """Looks at a subsample of the newest frame and proposes a 20-step chunk of 7 joint targets."""

    def step(self, inp: CameraImage) -> ActionChunk:
        seen = float(inp.pixels[::48, ::64].mean())
        return ActionChunk(inp.k, np.full((20, 7), seen / 255.0))


class JointController(Flow[ActionChunk, JointCommand]):
    """Follows the newest chunk, one row per tick."""

    def __init__(self):
        self.row, self.last = 0, -1

    def step(self, inp: ActionChunk) -> JointCommand:
        self.row = 0 if inp.k != self.last else min(self.row + 1, len(inp.actions) - 1)
        self.last = inp.k
        return JointCommand(inp.actions[self.row].copy())


# ---------------------------------------------------------------------------------------------
# throughput.py: small messages, one flow to another, as fast as they go
# ---------------------------------------------------------------------------------------------
class SmallSource(Flow):
    """A 64-byte array each tick, its first 8 bytes the tick's number."""

    def __init__(self, size: int = 64):
        self.size, self.k = size, 0

    def step(self):
        data = np.zeros(self.size, np.uint8)
        data[:8] = np.frombuffer(self.k.to_bytes(8, "little"), np.uint8)
        self.k += 1
        return {"data": data}


class SmallBurst(Flow):
    """A ``Burst`` of ``n`` arrays of ``size`` bytes each tick, the first 8 bytes of each its
    number (counting on from burst to burst): ``n`` events per tick in one message."""

    def __init__(self, size: int = 64, n: int = 100):
        self.size, self.n, self.k = size, n, 0

    def step(self):
        first = self.k
        self.k += self.n
        data = np.zeros((self.n, self.size), np.uint8)
        data[:, :8] = np.arange(first, self.k, dtype="<u8").view(np.uint8).reshape(self.n, 8)
        return {"data": Burst(data)}  # its rows: n arrays of size bytes


class Tally(Flow):
    """Counts what it was given (a Queue's list) and the highest number seen."""

    def __init__(self):
        self.n, self.top = 0, -1

    def step(self, data):
        self.n += len(data)
        self.top = max(self.top, int.from_bytes(data[-1][:8].tobytes(), "little"))
        return {"n": self.n, "top": self.top}
