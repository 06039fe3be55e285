"""One process per flow (docs/deploy.md): a flow burning CPU does not hold up the others' ticks.

In one process, a 90 ms pure-Python step would hold the GIL and every other flow's tick would
wait for it. On the zenoh backend the steady flow runs in its own process: it makes every tick,
skips none, and its ticks start late by far less than the burner's step — the bound is the
burner's own step time, a generous one, not a speed threshold.
"""

from __future__ import annotations

import statistics
import time
from dataclasses import dataclass

from retriever import Flow, Pipeline, Rate, io

BURN_S = 0.09


@io
@dataclass
class Beat:
    n: int


class Burner(Flow[None, Beat]):
    """Spins the CPU in pure Python for most of its 100 ms period."""

    def __init__(self, seconds: float = BURN_S):
        self.seconds = seconds
        self.n = 0

    def step(self, inp: None) -> Beat:
        end = time.perf_counter() + self.seconds
        x = 0
        while time.perf_counter() < end:
            x += 1
        self.n += 1
        return Beat(self.n)


class Steady(Flow[None, Beat]):
    def __init__(self):
        self.n = 0

    def step(self, inp: None) -> Beat:
        self.n += 1
        return Beat(self.n)


def lateness_ms(pipe, trace, node: str) -> list[float]:
    t0 = pipe.session.t0
    return [(s.wall_start_ns - (t0 + s.tag[0])) / 1e6 for s in trace.steps_of(node)]


def test_a_cpu_bound_flow_does_not_delay_another_flows_ticks():
    with Pipeline("isolation") as pipe:
        Burner().named("burner") @ Rate(10)
        Steady().named("steady") @ Rate(50)
    trace = pipe.run(duration=2.0, backend="zenoh", quiet=True)
    steady = trace.steps_of("steady")
    assert [s.tag[0] for s in steady] == [k * 20_000_000 for k in range(100)]
    assert all(s.status == "ok" and not s.detail for s in steady), [s for s in steady if s.detail][:3]
    assert "overrun" not in pipe.counts(), pipe.counts()
    late = lateness_ms(pipe, trace, "steady")
    assert statistics.median(late) < BURN_S * 1000 / 3, f"median lateness {statistics.median(late):.1f} ms"
    assert len(trace.steps_of("burner")) >= 15  # the burner really ran alongside
