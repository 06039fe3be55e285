"""Flows for tests/backends/zenoh/test_restart_bursts.py: a producer of big bursts and an untyped
consumer that raises once, rebuilt in each worker process from the IR (module-level classes,
msgpack-able arguments)."""

from __future__ import annotations

from retriever import Burst, Flow


class Bursts(Flow):
    """A source: at its k-th tick a burst of ``size`` ints, k * size to (k + 1) * size - 1; after
    ``count`` bursts (when given), nothing."""

    def __init__(self, size: int, count: int | None = None):
        self.size, self.count, self.k = size, count, 0

    def step(self):
        if self.k == self.count:
            return {}
        first = self.k * self.size
        self.k += 1
        return {"value": Burst(range(first, first + self.size))}


class FailAt(Flow):
    """Untyped: raises ``ValueError`` when what it got on ``x`` is ``fail_at`` (once: a value comes
    once), else reports how many values it got (a list of them from a Queue or a Window) and the
    newest, with its calls since ``reset()``."""

    def __init__(self, fail_at):
        self.fail_at, self.calls = fail_at, 0

    def reset(self) -> None:
        self.calls = 0

    def step(self, x):
        self.calls += 1
        got = x if type(x) is list else [x]
        if got and got[-1] == self.fail_at:
            raise ValueError(f"failed at x={self.fail_at}")
        return {"report": {"calls": self.calls, "got": len(got), "newest": got[-1] if got else None}}
