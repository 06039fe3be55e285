"""Clocks: exact Rate tick times (docs/semantics.md), trigger ports, and the errors for impossible clocks.

The reference tick time is written from §3 alone: ``t_k = T0 + offset_ns + floor(k * 1e9 / hz)``
with a float ``hz`` taken as the rational number its decimal ``repr`` denotes and the offset
converted by ``round(offset * 1e9)``.
"""

from __future__ import annotations

import math
import re
from fractions import Fraction

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from retriever import ClockError, Flow, Hybrid, Pipeline, Rate, Trigger
from retriever.clocks import clock_from_ir

NS = 10**9
MS = 10**6
SETTINGS = settings(max_examples=300, deadline=None)


def exact_hz(hz) -> Fraction:
    """§3: a float hz is the rational its decimal repr denotes (33.3 → 333/10, not the binary double)."""
    return Fraction(repr(hz)) if isinstance(hz, float) else Fraction(hz)


def ref_tick(hz, k: int, offset=0.0, t0: int = 0) -> int:
    return t0 + round(offset * 1e9) + math.floor(k * NS / exact_hz(hz))


RATES = st.one_of(
    st.sampled_from([7, 10, 30, 33.3, 200, 0.5, 29.97, 59.94, 1 / 3, 0.1, 1e-3, 2.5e6, 999_999_937]),
    st.integers(1, 10**7),
    st.floats(min_value=1e-3, max_value=1e8, allow_nan=False, allow_infinity=False),
)
OFFSETS = st.one_of(st.just(0.0), st.integers(0, 5000).map(lambda ms: ms / 1000), st.floats(0, 100))


# ---------------------------------------------------------------------------------------------
# Tick times
# ---------------------------------------------------------------------------------------------
@SETTINGS
@given(hz=RATES, k=st.integers(0, 10**13), offset=OFFSETS, t0=st.integers(0, 2 * 10**18))
def test_rate_tick_time_is_exact(hz, k, offset, t0):
    """Rate(hz, offset).tick_time(k, t0) == t0 + round(offset·1e9) + floor(k·1e9/hz), exactly, for huge k."""
    clock = Rate(hz, offset=offset)
    got = clock.tick_time(k, t0)
    assert type(got) is int
    assert got == ref_tick(hz, k, offset, t0)


@SETTINGS
@given(hz=RATES, k=st.integers(1, 10**15))
def test_rate_has_no_drift(hz, k):
    """Tick k stays within 1 ns below k·1e9/hz however large k is, and every period is floor or ceil of 1e9/hz."""
    clock = Rate(hz)
    ideal = k * NS / exact_hz(hz)
    assert 0 <= ideal - clock.tick_time(k) < 1
    period = NS / exact_hz(hz)
    assert clock.tick_time(k) - clock.tick_time(k - 1) in (math.floor(period), math.ceil(period))


@SETTINGS
@given(hz=RATES, k=st.integers(0, 10**13), offset=OFFSETS)
def test_schedule_spells_out_tick_time(hz, k, offset):
    """``schedule`` is what the inproc backend groups clocks by and ticks with, inline."""
    offset_ns, num, den = Rate(hz, offset=offset).schedule
    assert offset_ns + k * num // den == Rate(hz, offset=offset).tick_time(k)


def test_equal_schedules_tick_together():
    assert Rate(30).schedule == Hybrid(30, trigger=["x"]).schedule == Rate(30.0, offset=0.0).schedule
    assert Rate(30).schedule != Rate(30, offset=0.01).schedule
    assert Rate(30).schedule != Rate(31).schedule


@pytest.mark.parametrize("hz, period_ns", [(10, 100 * MS), (200, 5 * MS), (1000, MS), (0.5, 2 * NS), (4, 250 * MS)])
def test_rate_with_exact_period_is_a_lattice(hz, period_ns):
    """A rate whose period is a whole number of ns ticks at exactly k·period, even at k = 10^12."""
    clock = Rate(hz)
    for k in (0, 1, 2, 3, 10**6 + 7, 10**12):
        assert clock.tick_time(k) == k * period_ns


def test_rate_30_matches_design_example():
    """§10: cam @ Rate(30) ticks at 0, 33.333333, 66.666666, 100 ms (floor(k·1e9/30) ns)."""
    assert [Rate(30).tick_time(k) for k in range(4)] == [0, 33_333_333, 66_666_666, 100_000_000]


def test_rate_float_hz_is_its_decimal_not_its_binary_double():
    """33.3 Hz is 333/10 Hz: tick 333 lands on exactly 10 s; the binary double 33.29999… would not."""
    assert Rate(33.3).tick_time(333) == 10 * NS
    assert Rate(33.3).tick_time(333 * 10**6) == 10**7 * NS
    assert Rate(0.1).tick_time(1) == 10 * NS
    assert Rate(29.97).tick_time(2997) == 100 * NS


def test_rate_offset_shifts_every_tick():
    """The first tick is at T0 + offset; later ticks keep the same phase."""
    clock = Rate(10, offset=0.0015)
    assert [clock.tick_time(k) for k in range(3)] == [1_500_000, 101_500_000, 201_500_000]
    assert clock.tick_time(2, t0=7) == 201_500_007


@SETTINGS
@given(hz=RATES, offset=OFFSETS, t=st.integers(-10**12, 10**15), t0=st.integers(0, 10**12))
def test_first_tick_at_or_after(hz, offset, t, t0):
    """first_tick_at_or_after(t) is the smallest k with tick_time(k) ≥ t."""
    clock = Rate(hz, offset=offset)
    k = clock.first_tick_at_or_after(t, t0)
    assert k >= 0
    assert clock.tick_time(k, t0) >= t
    assert k == 0 or clock.tick_time(k - 1, t0) < t


@SETTINGS
@given(hz=RATES, offset=OFFSETS, k=st.integers(0, 10**12))
def test_first_tick_at_or_after_a_tick_is_that_tick(hz, offset, k):
    """first_tick_at_or_after(tick_time(k)) == k (ticks are strictly increasing for hz ≤ 1e9)."""
    clock = Rate(hz, offset=offset)
    if exact_hz(hz) <= NS:
        assert clock.first_tick_at_or_after(clock.tick_time(k)) == k


class Source(Flow):
    """Counts its ticks."""

    def __init__(self):
        self.n = 0

    def step(self):
        self.n += 1
        return {"out": self.n}


class Sink(Flow):
    """Two optional inputs; emits what it saw."""

    def step(self, a=None, b=None):
        return {"seen": [a, b]}


class Relay(Flow):
    """Passes its input on."""

    def step(self, x):
        return {"out": x}


@pytest.mark.parametrize("hz, offset", [(30, 0.0), (33.3, 0.0015), (7, 0.1), (200, 0.0), (0.5, 0.25), (29.97, 0.0)])
def test_rate_ticks_in_a_run(hz, offset):
    """A Rate flow in a run ticks at exactly the §3 times, microstep 0, for every t < duration."""
    with Pipeline("rate") as pipe:
        Source().named("src") @ Rate(hz, offset=offset)
    trace = pipe.run(duration=3.0)
    want = []
    k = 0
    while (t := ref_tick(hz, k, offset)) < 3 * NS:
        want.append((t, 0))
        k += 1
    assert [s.tag for s in trace.steps_of("src")] == want


@pytest.mark.parametrize("clock_of", [lambda hz: Rate(hz), lambda hz: Hybrid(hz, trigger=["a"])])
def test_long_run_has_no_drift(clock_of):
    """Over 10^5 ticks of a 33.3 Hz clock the last tick is exactly floor(k·1e9·10/333) ns."""
    clock = clock_of(33.3)
    assert clock.tick_time(100_000) == (100_000 * NS * 10) // 333
    assert clock.tick_time(100_000) == 3_003_003_003_003


# ---------------------------------------------------------------------------------------------
# Trigger and Hybrid
# ---------------------------------------------------------------------------------------------
def test_trigger_ports():
    """Trigger keeps its ports in order without duplicates; no ports means any input; it has no rate."""
    assert Trigger("a", "b", "a").trigger_ports == ("a", "b")
    assert Trigger().trigger_ports == ()
    assert Trigger("a").triggered and Trigger().triggered
    assert Trigger("a").hz is None
    assert not Rate(10).triggered and Rate(10).trigger_ports == ()


def test_hybrid_ports_and_rate():
    """Hybrid takes one port name or a list; it ticks at its rate exactly like Rate."""
    assert Hybrid(10, trigger="x").trigger_ports == ("x",)
    assert Hybrid(10, trigger=["x", "y", "x"]).trigger_ports == ("x", "y")
    h = Hybrid(33.3, trigger="x", offset=0.002)
    assert h.triggered and h.hz == Fraction(333, 10)
    assert [h.tick_time(k) for k in range(5)] == [Rate(33.3, offset=0.002).tick_time(k) for k in range(5)]


def test_clock_equality_and_ir_round_trip():
    """Clocks are values: equal schedules compare and hash equal; to_ir/clock_from_ir round-trips."""
    assert Rate(30) == Rate(30) and hash(Rate(30)) == hash(Rate(30))
    assert Rate(30) != Rate(30, offset=0.1)
    assert Rate(30) != Hybrid(30)
    assert Trigger("a") != Trigger("b")
    for clock in (Rate(33.3, offset=0.5), Trigger(), Trigger("a", "b"), Hybrid(10, trigger=["x"], offset=0.01)):
        assert clock_from_ir(clock.to_ir()) == clock
    assert Rate(30).to_ir() == {"Rate": {"hz": 30, "offset": 0.0}}


def _ticks(trace, node):
    return [s.tag for s in trace.steps_of(node)]


def test_trigger_ticks_only_on_its_ports():
    """Trigger("a") ticks on events at a, not at b; b is still sampled by its policy at a's ticks."""
    with Pipeline("trig") as pipe:
        fast = Source().named("fast") @ Rate(100)
        slow = Source().named("slow") @ Rate(10, offset=0.005)
        sink = Sink().named("sink") @ Trigger("a")
        fast.then(sink, map={"out": "b"})
        slow.then(sink, map={"out": "a"})
    trace = pipe.run(duration=0.3)
    assert _ticks(trace, "sink") == [(5 * MS, 1), (105 * MS, 1), (205 * MS, 1)]
    by_id = {e.id: e.value for e in trace.events}
    assert [by_id[s.produced[0]] for s in trace.steps_of("sink")] == [[1, 1], [2, 11], [3, 21]]


def test_trigger_without_ports_ticks_on_any_input():
    """Trigger() ticks on an event at any input port."""
    with Pipeline("any") as pipe:
        a = Source().named("a_src") @ Rate(10)
        b = Source().named("b_src") @ Rate(10, offset=0.05)
        sink = Sink().named("sink") @ Trigger()
        a.then(sink, map={"out": "a"})
        b.then(sink, map={"out": "b"})
    assert _ticks(pipe.run(duration=0.2), "sink") == [(0, 1), (50 * MS, 1), (100 * MS, 1), (150 * MS, 1)]


def test_several_triggers_at_one_tag_make_one_tick():
    """§10.3: ctrl @ Trigger("a", "b") with both arriving at (100, 1) steps once, with both."""
    with Pipeline("two") as pipe:
        a = Source().named("a_src") @ Rate(10)
        b = Source().named("b_src") @ Rate(10)
        sink = Sink().named("sink") @ Trigger("a", "b")
        a.then(sink, map={"out": "a"})
        b.then(sink, map={"out": "b"})
    trace = pipe.run(duration=0.15)
    assert _ticks(trace, "sink") == [(0, 1), (100 * MS, 1)]
    by_id = {e.id: e.value for e in trace.events}
    assert [by_id[s.produced[0]] for s in trace.steps_of("sink")] == [[1, 1], [2, 2]]


def test_trigger_chain_microsteps():
    """§10.2: a chain of zero-latency Trigger flows a → b → c ticks at (100, 1), (100, 2), (100, 3)."""
    with Pipeline("chain") as pipe:
        pol = Source().named("pol") @ Rate(10, offset=0.1)
        a = Relay().named("a") @ Trigger("x")
        b = Relay().named("b") @ Trigger("x")
        c = Relay().named("c") @ Trigger("x")
        pol.then(a, map={"out": "x"}).then(b, map={"out": "x"}).then(c, map={"out": "x"})
    trace = pipe.run(duration=0.15)
    assert [_ticks(trace, n) for n in "abc"] == [[(100 * MS, 1)], [(100 * MS, 2)], [(100 * MS, 3)]]


def test_hybrid_ticks_on_rate_and_on_triggers():
    """Hybrid(10, trigger="a") ticks at its rate and at each event on a; a coinciding pair is one tick."""
    with Pipeline("hyb") as pipe:
        # 'ev' ticks at 0, 50, 100 … ms and, with latency 50 ms, emits at (50,0), (100,0), …:
        # every other event lands exactly on the Hybrid's own rate tick at (100k, 0).
        ev = Source().configure(name="ev", latency=0.05) @ Rate(20)
        sink = Sink().named("sink") @ Hybrid(10, trigger="a")
        ev.then(sink, map={"out": "a"})
    trace = pipe.run(duration=0.3)
    assert _ticks(trace, "sink") == [(t * MS, 0) for t in (0, 50, 100, 150, 200, 250)]
    by_id = {e.id: e.value for e in trace.events}
    assert [by_id[s.produced[0]][0] for s in trace.steps_of("sink")] == [None, 1, 2, 3, 4, 5]


def test_hybrid_trigger_between_rate_ticks():
    """Hybrid(10, trigger="a") ticks at (t, 1) for an event from a zero-latency producer, besides its rate ticks."""
    with Pipeline("hyb2") as pipe:
        ev = Source().named("ev") @ Rate(10, offset=0.03)
        sink = Sink().named("sink") @ Hybrid(10, trigger="a")
        other = Source().named("other") @ Rate(100)
        ev.then(sink, map={"out": "a"})
        other.then(sink, map={"out": "b"})  # b is not a trigger port
    trace = pipe.run(duration=0.2)
    assert _ticks(trace, "sink") == [(0, 0), (30 * MS, 1), (100 * MS, 0), (130 * MS, 1)]


# ---------------------------------------------------------------------------------------------
# Impossible clocks
# ---------------------------------------------------------------------------------------------
BAD_HZ = [0, 0.0, -1, -30.5, float("nan"), float("inf"), float("-inf"), True, False, "10", None]


@pytest.mark.parametrize("hz", BAD_HZ, ids=repr)
@pytest.mark.parametrize("make, owner", [(lambda hz: Rate(hz), "Rate"), (lambda hz: Hybrid(hz, trigger="a"), "Hybrid")],
                         ids=["Rate", "Hybrid"])
def test_bad_hz_is_a_clock_error(make, owner, hz):
    """hz must be a finite number > 0 (not a bool): the error names the clock, the value, and hints at Trigger."""
    with pytest.raises(ClockError, match=re.escape(f"{owner}(hz={hz!r}): hz must be a finite number > 0, got {hz!r}")
                       + r"\n    hint: for an event-driven flow use Trigger\(\"port\"\) instead of a rate"):
        make(hz)


@pytest.mark.parametrize("offset", [-0.001, -1, float("nan"), float("inf"), True, "0"], ids=repr)
@pytest.mark.parametrize("make, owner", [(lambda o: Rate(10, offset=o), "Rate"),
                                         (lambda o: Hybrid(10, trigger="a", offset=o), "Hybrid")],
                         ids=["Rate", "Hybrid"])
def test_bad_offset_is_a_clock_error(make, owner, offset):
    """offset must be a finite number of seconds >= 0."""
    with pytest.raises(ClockError, match=re.escape(
            f"{owner}(offset={offset!r}): offset must be a finite number of seconds >= 0")):
        make(offset)


@pytest.mark.parametrize("port", ["", 3, None], ids=repr)
def test_bad_trigger_port_is_a_clock_error(port):
    """Trigger and Hybrid ports must be non-empty str names."""
    for owner, make in (("Trigger", lambda: Trigger("a", port)), ("Hybrid", lambda: Hybrid(10, trigger=["a", port]))):
        with pytest.raises(ClockError, match=re.escape(
                f"{owner}: trigger ports must be non-empty port names (str), got {port!r}")):
            make()


def test_clock_error_is_a_value_error():
    """ClockError is a ValueError, so generic validation code catches it."""
    with pytest.raises(ValueError):
        Rate(0)


def test_a_rate_may_tick_only_at_its_tick_times_at_microstep_0_before_the_end():
    """What the coordinator and the replay check a step record's tag against (issue 40 §4)."""
    rate = Rate(hz=50, offset=0.001)
    assert [rate.may_tick_at((t, 0)) for t in (1_000_000, 21_000_000, 421_000_000)] == [True] * 3
    assert not rate.may_tick_at((0, 0)) and not rate.may_tick_at((21_000_001, 0))
    assert not rate.may_tick_at((21_000_000, 1))  # a rate ticks at microstep 0
    assert rate.may_tick_at((981_000_000, 0), end_ns=1_000_000_000)
    assert not rate.may_tick_at((1_001_000_000, 0), end_ns=1_000_000_000)
    assert Trigger("x").may_tick_at((7, 3)) and Hybrid(10, "x").may_tick_at((7, 0))  # an event's tag: any
