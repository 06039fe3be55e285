"""Flows for the Zenoh lifecycle tests (tests/backends/zenoh/test_lifecycle.py).

Importable by worker processes (``tests.backends.zenoh.lifecycle_flows``), small, cheap and
slow-rated: the tests are about processes, not speed. ``retriever run`` loads this file as a
script too (``lifecycle_flows.py:pipe`` and ``lifecycle_flows.py:napping``).
"""

from __future__ import annotations

import ctypes
import os
import time
from dataclasses import dataclass

from retriever import Flow, Latest, Pipeline, Rate, io

SOURCE_HZ = 20
SINK_HZ = 10


@io
@dataclass
class Count:
    n: int


class Counter(Flow[None, Count]):
    """A source: 1, 2, 3, … one per tick."""

    def __init__(self, start: int = 0):
        self.start = start
        self.k = start

    def reset(self) -> None:
        self.k = self.start

    def step(self, inp: None) -> Count:
        self.k += 1
        return Count(n=self.k)


class Total(Flow[Count, Count]):
    """A sink that keeps the newest count it saw (and passes it on)."""

    def __init__(self):
        self.last = 0

    def reset(self) -> None:
        self.last = 0

    def step(self, inp: Count) -> Count:
        self.last = inp.n
        return Count(n=inp.n)


@io
@dataclass
class MaybeCount:
    n: int = 0  # a default: the sink steps on every tick, input or not (no skips)


class Sink(Flow[MaybeCount, Count]):
    """A sink that never skips: its step count is its tick count."""

    def step(self, inp: MaybeCount) -> Count:
        return Count(n=inp.n)


class GatedSink(Sink):
    """A :class:`Sink` that holds its first step until the file ``gate/subscribed`` exists and its
    third until ``gate/granted`` does: a test's other process says when it is in place, so a run
    in virtual time (done in a fraction of a second) cannot finish before it (the test's gates)."""

    def __init__(self, gate: str):
        self.gate = gate
        self.k = 0

    def step(self, inp: MaybeCount) -> Count:
        self.k += 1
        for tick, name in ((1, "subscribed"), (3, "granted")):
            if self.k == tick:
                _await_file(os.path.join(self.gate, name))
        return super().step(inp)


def _await_file(path: str, bound_s: float = 60.0) -> None:
    """Until ``path`` exists (another process makes it), at most ``bound_s``: then the step goes on,
    and the test that forgot its gate fails on what it sees, not by hanging."""
    until = time.monotonic() + bound_s
    while not os.path.exists(path) and time.monotonic() < until:
        time.sleep(0.01)


class Scaled(Flow[None, Count]):
    """A source whose constructor takes any object (a callable scales the count): fine
    in-process, but the IR cannot carry a lambda, a set or a plain object."""

    def __init__(self, fn=None):
        self.fn = fn
        self.k = 0

    def step(self, inp: None) -> Count:
        self.k += 1
        return Count(n=self.fn(self.k) if callable(self.fn) else self.k)


class Nap(Flow[None, Count]):
    """A source whose step takes ``nap`` seconds of wall time (a slow model)."""

    def __init__(self, nap: float = 2.0):
        self.nap = nap

    def step(self, inp: None) -> Count:
        time.sleep(self.nap)
        return Count(n=1)


#: how long a SlowToCollect's finalizer takes: longer than the coordinator's STOP_GRACE_S
SLOW_FINALIZER_S = 5.0


class SlowToCollect:
    """What a big model is to a process's exit: its finalizer takes SLOW_FINALIZER_S (Python's
    teardown collected a torch policy's tensors for seconds)."""

    def __del__(self) -> None:
        time.sleep(SLOW_FINALIZER_S)


class Heavy(Flow[Count, None]):
    """A sink that holds, from its setup() to the end, something slow to collect."""

    def setup(self) -> None:
        self.model = SlowToCollect()

    def step(self, inp: Count) -> None:
        pass


class Looped(Flow):
    """Counts its ticks on ``n``, which is fed back to it (``feedback``, optional: untyped with a default)."""

    def __init__(self):
        self.k = 0

    def reset(self) -> None:
        self.k = 0

    def step(self, feedback=None):
        self.k += 1
        return {"n": self.k}


class SegfaultOnce(Flow[Count, Count]):
    """Passes its input on; its first step ever (in any process: ``marker`` is a file that says
    it happened) crashes the process with a segmentation fault, as a bad native extension would."""

    def __init__(self, marker: str):
        self.marker = marker

    def step(self, inp: Count) -> Count:
        if not os.path.exists(self.marker):
            open(self.marker, "w").close()
            ctypes.string_at(0)  # SIGSEGV
        return Count(n=inp.n)


class ExitOnce(Flow[Count, Count]):
    """Passes its input on; its first step ever (``marker``: a file that says it happened) ends
    its process with os._exit(0), a clean exit code, without a word to the coordinator."""

    def __init__(self, marker: str):
        self.marker = marker

    def step(self, inp: Count) -> Count:
        if not os.path.exists(self.marker):
            open(self.marker, "w").close()
            os._exit(0)
        return Count(n=inp.n)


def two_node_pipeline(name: str = "lifecycle", source_hz: float = SOURCE_HZ, sink_hz: float = SINK_HZ,
                      sink: type[Flow] = Total) -> Pipeline:
    """counter @ source_hz ──n (Latest)──▶ total @ sink_hz (a ``sink`` flow, node id "total")"""
    with Pipeline(name) as p:
        counter = Counter() @ Rate(hz=source_hz)
        total = sink().configure(name="total") @ Rate(hz=sink_hz)
        counter.then(total, sync=Latest())
    return p


# `retriever run tests/backends/zenoh/lifecycle_flows.py:pipe --backend zenoh ...` runs this one.
pipe = two_node_pipeline()

# counter @ 20 Hz beside nap @ 0.25 Hz, whose first step (at T0) lasts 1 s: stopped within that
# second, nap's last step record reaches the coordinator after counter's later ones (a worker has
# session.STOP_GRACE_S to finish its step and report after `stop`).
with Pipeline("napping") as napping:
    Counter() @ Rate(hz=SOURCE_HZ)
    Nap(nap=1.0) @ Rate(hz=0.25)

# counter @ 20 Hz beside nap, whose first step (at T0) does not return within any test
with Pipeline("hung") as hung:
    Counter() @ Rate(hz=SOURCE_HZ)
    Nap(nap=600.0) @ Rate(hz=1)
