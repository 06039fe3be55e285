"""Flows of the dora backend's tests: importable, so that each worker process rebuilds them."""

from __future__ import annotations

from retriever import Flow, Pipeline, Rate

from ..zenoh.lifecycle_flows import Count


class Extra(Flow):
    """Untyped: emits ``x`` and ``note``; no edge takes ``note``."""

    def __init__(self):
        super().__init__()
        self.i = 0

    def step(self):
        self.i += 1
        return {"x": self.i, "note": f"tick {self.i - 1}"}


class Raises(Flow[Count, Count]):
    """Raises ValueError at its ``at``-th step."""

    def __init__(self, at: int):
        super().__init__()
        self.at, self.i = at, 0

    def step(self, inp: Count) -> Count:
        self.i += 1
        if self.i == self.at:
            raise ValueError("third time")
        return inp


class NeverReady(Flow):
    """A flow whose ``setup()`` never returns (a model that never loads): its run never starts."""

    def setup(self) -> None:
        import threading

        threading.Event().wait()

    def step(self):
        return {"x": 0}


with Pipeline("never_ready") as never_ready:
    Extra().named("ok") @ Rate(hz=20)
    NeverReady().named("stuck") @ Rate(hz=20)


class Frames(Flow):
    """Untyped: a 64 KiB frame a tick, on ``x`` (dora's daemon route: over its 4 KiB threshold);
    says so on stdout and stderr at its first step."""

    def __init__(self):
        super().__init__()
        self.said = False

    def step(self):
        import sys

        import numpy as np

        if not self.said:
            self.said = True
            print("frames: first frame", flush=True)
            print("frames: first frame, on stderr", file=sys.stderr, flush=True)
        return {"x": np.zeros(64 << 10, np.uint8)}
