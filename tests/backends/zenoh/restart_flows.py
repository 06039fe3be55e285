"""Flows for tests/backends/zenoh/test_group_restart.py: a chain whose middle raises on the
inputs it is told, each flow saying in its step records (never in its outputs: a replay sets each
flow up once) how often ``setup()`` ran for its node in this process and where (``set_ups``,
``pid``, said with the record after each setup)."""

from __future__ import annotations

import os
from collections import Counter

from retriever import Flow

from .semantics_flows import OptXIn, Report, Value, XIn

#: per flow class (one node each in the tests' pipelines), the setups this process ran
SET_UPS: Counter = Counter()


class SetUpCounted:
    """A Flow's setup() that counts: the record after each says ``set_ups`` (in this process, for
    its class) and ``pid``."""

    def setup(self) -> None:
        SET_UPS[type(self).__name__] += 1
        self.add_step_detail(set_ups=SET_UPS[type(self).__name__], pid=os.getpid())


class CountingSource(SetUpCounted, Flow[None, Value]):
    """Emits its tick index k = 0, 1, 2, …"""

    def __init__(self):
        self.k = 0

    def step(self, inp: None) -> Value:
        self.k += 1
        return Value(self.k - 1)


class FailingMiddle(SetUpCounted, Flow[XIn, Report]):
    """Raises ``ValueError`` when its input is in ``fail_at``; else reports ``{"calls": calls
    since it was made, "x": x}``: a fresh flow counts from 1 again."""

    def __init__(self, fail_at: list):
        self.fail_at = list(fail_at)
        self.calls = 0

    def step(self, inp: XIn) -> Report:
        self.calls += 1
        if inp.x in self.fail_at:
            raise ValueError(f"boom at x={inp.x}")
        return Report({"calls": self.calls, "x": inp.x})


class CountedSink(SetUpCounted, Flow[OptXIn, Report]):
    """Reports what it got (None when MISSING)."""

    def step(self, inp: OptXIn) -> Report:
        return Report(inp.x)


class SetUpOnce(FailingMiddle):
    """A FailingMiddle whose setup() raises once it ran in this process before (a device one
    process may open only once)."""

    def setup(self) -> None:
        super().setup()
        if SET_UPS[type(self).__name__] > 1:
            raise RuntimeError("the device is taken")


#: per flow class, the flows this process made (``__init__`` ran)
MADE: Counter = Counter()


class MadeOnce(FailingMiddle):
    """A FailingMiddle whose ``__init__`` raises once one was made in this process before (a
    device its constructor opens, which one process may open only once)."""

    def __init__(self, fail_at: list):
        MADE[type(self).__name__] += 1
        if MADE[type(self).__name__] > 1:
            raise RuntimeError("the device is taken")
        super().__init__(fail_at)
