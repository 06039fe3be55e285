"""Flows whose worker process dies, or whose step raises, again and again, for the tests of
restarts (test_sealed_for_live.py). Importable by worker processes (``tests.backends.zenoh.dying_flows``)."""

from __future__ import annotations

import os
import signal
import sys
from dataclasses import dataclass

from retriever import Flow, io


@io
@dataclass
class Step:
    n: int


class FailsTimes(Flow[None, Step]):
    """The ``at``-th step of each of its processes fails (``fail``), ``times`` times in all
    (``failures``: a directory that counts them across its processes); then that step ends the
    run (sys.exit(0))."""

    def __init__(self, failures: str, times: int, at: int = 3):
        self.failures, self.times, self.at = failures, times, at
        self.n = 0

    def reset(self) -> None:
        self.n = 0

    def step(self, inp: None) -> Step:
        self.n += 1
        if self.n == self.at:
            so_far = len(os.listdir(self.failures))
            if so_far >= self.times:
                sys.exit(0)
            open(os.path.join(self.failures, str(so_far)), "w").close()
            self.fail(so_far)
        return Step(n=self.n)

    def fail(self, so_far: int) -> None:
        raise NotImplementedError


class DiesTimes(FailsTimes):
    """Its process SIGKILLs itself (a crash: nothing said, no state handed over)."""

    def fail(self, so_far: int) -> None:
        os.kill(os.getpid(), signal.SIGKILL)


class RaisesTimes(FailsTimes):
    """Its step raises (a step error: its process hands its state over to a new one)."""

    def fail(self, so_far: int) -> None:
        raise RuntimeError(f"raised for the {so_far + 1}th time")
