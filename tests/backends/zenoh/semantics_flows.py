"""Flows for tests/backends/zenoh/test_realtime_semantics.py.

The Zenoh backend runs each flow in its own worker process, rebuilt from the IR (``type`` +
``params``), so these are module-level classes whose constructor arguments are msgpack-able.
They report what the tests need (their process id, their call count since ``reset()``, the
value they got) through their outputs, never through shared objects.
"""

from __future__ import annotations

import os
import sys
import signal
import subprocess
import threading
import time
from dataclasses import dataclass
from typing import Any

import numpy as np

from retriever import Flow, io

from ..test_conformance import ABIn, PairSource  # noqa: F401  (re-exported for the tests)


@io
@dataclass
class Value:
    value: Any = None


@io
@dataclass
class XIn:
    x: Any


@io
@dataclass
class OptXIn:
    x: Any | None


@io
@dataclass
class Report:
    report: Any = None


class Ticker(Flow[None, Value]):
    """A source: emits its tick index k = 0, 1, 2, …"""

    def __init__(self):
        self.k = 0

    def step(self, inp: None) -> Value:
        self.k += 1
        return Value(self.k - 1)


class FailingTicker(Flow[None, Value]):
    """A source: emits its call index k = 0, 1, 2, …, but raises ``ValueError`` on the calls in
    ``fail_at``, or outputs nothing on those in ``quiet_at``."""

    def __init__(self, fail_at: list, quiet_at: list = ()):
        self.fail_at, self.quiet_at = list(fail_at), list(quiet_at)
        self.k = 0

    def step(self, inp: None) -> Value | None:
        self.k += 1
        if self.k - 1 in self.fail_at:
            raise ValueError(f"source failed at k={self.k - 1}")
        return None if self.k - 1 in self.quiet_at else Value(self.k - 1)


class QuietSource(Flow[None, Value]):
    """A source that outputs nothing but on the calls in ``emit_at`` (its call index k), raises
    ``ValueError`` on those in ``fail_at`` and sleeps ``sleep_at[k]`` seconds on those in it."""

    def __init__(self, emit_at: list, fail_at: list = (), sleep_at: dict | None = None):
        self.emit_at, self.fail_at, self.sleep_at = list(emit_at), list(fail_at), dict(sleep_at or {})
        self.k = 0

    def step(self, inp: None) -> Value | None:
        k = self.k
        self.k += 1
        if k in self.sleep_at:
            time.sleep(self.sleep_at[k])
        if k in self.fail_at:
            raise ValueError(f"quiet source failed at k={k}")
        return Value(k) if k in self.emit_at else None


class TimerSlack(Flow[None, Value]):
    """A source: emits the timer slack (ns) of the thread that runs its step (Linux prctl)."""

    def step(self, inp: None) -> Value:
        return Value(timer_slack_ns())


def timer_slack_ns() -> int:
    import ctypes

    return ctypes.CDLL(None).prctl(30, 0, 0, 0, 0)  # PR_GET_TIMERSLACK


class Unsendable(Flow[None, Value]):
    """A source whose third output is a value no process boundary can carry (an ``object()``)."""

    def __init__(self):
        self.k = 0

    def step(self, inp: None) -> Value:
        self.k += 1
        return Value(object() if self.k == 3 else self.k)


class HoldsItself(Flow[None, Value]):
    """A source whose second output is a list that holds itself (and an array)."""

    def __init__(self):
        self.k = 0

    def step(self, inp: None) -> Value:
        self.k += 1
        if self.k != 2:
            return Value(self.k)
        value = [np.zeros(2)]
        value.append(value)
        return Value(value)


class Faulty(Flow[XIn, Report]):
    """Raises ``ValueError(f"{message} at x={x}")`` when its input ``x`` is in ``fail_at``; else
    reports ``{"pid": os.getpid(), "calls": calls since reset, "x": x}`` (without the pid when
    ``with_pid`` is false: a replay runs in another process). The call counter lives in
    ``reset()``, the state a restart must renew."""

    def __init__(self, fail_at: list, message: str = "boom", with_pid: bool = True, exit_code: int | None = None):
        self.fail_at = list(fail_at)
        self.message = message
        self.with_pid = with_pid
        self.exit_code = exit_code  # sys.exit(exit_code) instead of raising, when set
        self.calls = 0

    def reset(self) -> None:
        self.calls = 0

    def step(self, inp: XIn) -> Report:
        self.calls += 1
        if inp.x in self.fail_at:
            if self.exit_code is not None:
                sys.exit(self.exit_code)
            raise ValueError(f"{self.message} at x={inp.x}")
        report = {"calls": self.calls, "x": inp.x}
        return Report({"pid": os.getpid(), **report} if self.with_pid else report)


class Sleepy(Flow[None, Value]):
    """A source whose step sleeps ``sleep`` seconds at the ticks (call indices) in ``at``
    (every tick when ``at`` is None); emits the call index."""

    def __init__(self, sleep: float, at: list | None = None):
        self.sleep = sleep
        self.at = at
        self.k = 0

    def step(self, inp: None) -> Value:
        k = self.k
        self.k += 1
        if self.at is None or k in self.at:
            time.sleep(self.sleep)
        return Value(k)


class SlowEcho(Flow[XIn, Value]):
    """Forwards its input; sleeps ``sleep`` seconds first when the input is in ``at``."""

    def __init__(self, sleep: float, at: list):
        self.sleep = sleep
        self.at = list(at)

    def step(self, inp: XIn) -> Value:
        if inp.x in self.at:
            time.sleep(self.sleep)
        return Value(inp.x)


def freeze_now() -> None:
    """Stop this whole process (SIGSTOP) before returning. Sent to the calling thread, so that
    this thread starts the stop itself: a SIGSTOP sent to the process is taken by its main
    thread, and a step running on another thread (a Zenoh receiving thread, see
    loop.INLINE_STEP_NS) would go on for as long as the main thread takes to be scheduled."""
    signal.pthread_kill(threading.get_ident(), signal.SIGSTOP)


class Stall(Flow[XIn, Value]):
    """Forwards its input; when the input is in ``at``, freezes its whole process (SIGSTOP) for
    ``seconds`` — its Zenoh threads too, as a machine hiccup or a GC pause would — so it can
    neither publish nor answer progress queries. A helper process sends SIGCONT."""

    def __init__(self, seconds: float, at: list):
        self.seconds = seconds
        self.at = list(at)

    def step(self, inp: XIn) -> Value:
        if inp.x in self.at:
            subprocess.Popen(["/bin/sh", "-c", f"sleep {self.seconds}; kill -CONT {os.getpid()}"],
                             stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
            freeze_now()
        return Value(inp.x)


class Probe(Flow[OptXIn, Report]):
    """Reports what its optional input ``x`` got (None when MISSING)."""

    def step(self, inp: OptXIn) -> Report:
        return Report(inp.x)


class Echo(Flow[XIn, Value]):
    """Required input ``x``; forwards it."""

    def step(self, inp: XIn) -> Value:
        return Value(inp.x)


@io
@dataclass
class WinIn:
    x: list


class WindowProbe(Flow[WinIn, Report]):
    """Reports the list a Window/Queue edge handed it."""

    def step(self, inp: WinIn) -> Report:
        return Report(list(inp.x))


class PairProbe(Flow[ABIn, Report]):
    """Reports ``[a, b]`` as it got them (None when MISSING)."""

    def step(self, inp: ABIn) -> Report:
        return Report([inp.a, inp.b])


class BigTicker(Flow[None, Value]):
    """A source emitting ``[k, size bytes]`` at each tick k (a camera frame's worth)."""

    def __init__(self, size: int):
        self.size = size
        self.k = 0

    def step(self, inp: None) -> Value:
        self.k += 1
        return Value([self.k - 1, bytes([self.k % 256]) * self.size])


class BigStall(Flow[XIn, Value]):
    """Takes ``[k, blob]`` and emits k; when k is in ``at``, freezes its whole process (SIGSTOP)
    for ``seconds``, as ``Stall`` does: it reads nothing from the network meanwhile."""

    def __init__(self, seconds: float, at: list):
        self.seconds = seconds
        self.at = list(at)

    def step(self, inp: XIn) -> Value:
        k = inp.x[0]
        if k in self.at:
            subprocess.Popen(["/bin/sh", "-c", f"sleep {self.seconds}; kill -CONT {os.getpid()}"],
                             stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
            freeze_now()
        return Value(k)


class WhereRun(Flow[XIn, Report]):
    """Reports its input and whether its step ran on its process's main thread; sleeps ``sleep``
    seconds first when given (a step that is slow on purpose)."""

    def __init__(self, sleep: float = 0.0):
        self.sleep = sleep

    def step(self, inp: XIn) -> Report:
        if self.sleep:
            time.sleep(self.sleep)
        # the native thread (its id and name), and how many steps it ran before this one as its
        # Python thread state remembers them (a threading.local)
        before = getattr(_THREAD_STEPS, "n", 0)
        _THREAD_STEPS.n = before + 1
        tid = threading.get_native_id()
        with open(f"/proc/self/task/{tid}/comm") as f:
            name = f.read().strip()
        return Report({"x": inp.x, "main": threading.current_thread() is threading.main_thread(),
                       "tid": tid, "thread": name, "before": before})


#: WhereRun's steps per thread
_THREAD_STEPS = threading.local()


class Counter(Flow[OptXIn, Value]):
    """Emits its tick index k = 0, 1, 2, …, whatever its optional input holds."""

    def __init__(self):
        self.k = 0

    def step(self, inp: OptXIn) -> Value:
        self.k += 1
        return Value(self.k - 1)


class EndsAt(Flow[None, Value]):
    """A source that ends the run (sys.exit(0)) at its ``at``-th step; before, it emits k."""

    def __init__(self, at: int):
        self.at, self.k = at, 0

    def step(self, inp: None) -> Value:
        self.k += 1
        if self.k == self.at:
            sys.exit(0)
        return Value(self.k)
