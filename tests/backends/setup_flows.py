"""Flows for tests/backends/test_setup_teardown.py (module level: workers rebuild them from the IR).

Each writes what happens to it, one line per event, ``PID EVENT NODE THREAD``, to a file named by
its ``journal`` argument: the test reads who called what, in which process and thread."""

from __future__ import annotations

import os
import threading
from dataclasses import dataclass

from retriever import Flow, io


def note(journal: str, event: str, name: str) -> None:
    with open(journal, "a", encoding="ascii") as f:
        f.write(f"{os.getpid()} {event} {name} {threading.get_ident()}\n")


@io
@dataclass
class Reading:
    n: int


class Camera(Flow[None, Reading]):
    """A source: its "device" is opened in setup() and closed in teardown()."""

    def __init__(self, journal: str):
        self.journal = journal
        self.k = 0
        note(journal, "init", "camera")

    def setup(self) -> None:
        self.device = "open"
        note(self.journal, "setup", "camera")

    def teardown(self) -> None:
        self.device = "closed"
        note(self.journal, "teardown", "camera")

    def step(self) -> Reading:
        assert self.device == "open"
        self.k += 1
        note(self.journal, "step", "camera")
        return Reading(n=self.k)


class Policy(Flow[Reading, Reading]):
    """Loads "weights" in setup(); raises in the step whose input is in ``fail_at`` (a restart
    resets it: the weights stay loaded)."""

    def __init__(self, journal: str, fail_at: list | None = None, fail_setup: bool = False):
        self.journal, self.fail_at, self.fail_setup = journal, list(fail_at or []), fail_setup
        self.steps = 0
        note(journal, "init", "policy")

    def setup(self) -> None:
        if self.fail_setup:
            raise FileNotFoundError("weights.pt")
        self.weights = [0.5] * 4
        note(self.journal, "setup", "policy")

    def teardown(self) -> None:
        note(self.journal, "teardown", "policy")

    def step(self, inp: Reading) -> Reading:
        note(self.journal, "step", "policy")
        self.steps += 1
        if inp.n in self.fail_at:
            raise ValueError(f"bad reading {inp.n}")
        return Reading(n=round(sum(self.weights) * inp.n))
