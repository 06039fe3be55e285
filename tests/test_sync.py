"""Sync policies against brute-force references written straight from docs/semantics.md.

Each property test generates a random edge history (several producers, integer-ns tags with equal
times and microsteps, random values), a random increasing sequence of consumer tick tags, and a
random set of skipped ticks. It drives a policy through the runtime interface of ``retriever.sync``

    select(buf, tau) -> (value, ids, dropped, commit)
    commit_to(buf, commit)            # only for ticks that are not skipped

and compares every tick's ``(value, ids, dropped)`` with a reference that recomputes the answer
from the whole history on every tick. The references share no code with the library: they filter
``H`` (the events with tag ≤ τ), order it by (tag, producer id, seq) and apply the one-line rule of
the §4 table. Events are inserted into the buffer at a random moment before the first tick that
can see them, which is all the runtime promises (an event is produced before its tag is reached).
"""

from __future__ import annotations

import math
import random
from dataclasses import dataclass
from fractions import Fraction
from typing import Any

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from retriever import (
    MISSING,
    ActionChunking,
    EventStream,
    Exact,
    Flow,
    Latest,
    LatestDistinct,
    Pipeline,
    Queue,
    Rate,
    Trigger,
    Window,
)
from retriever.sync import PortBuffer

SETTINGS = settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])
MS = 1_000_000  # ns


# ---------------------------------------------------------------------------------------------
# Scenarios: a random edge history, consumer ticks and skips
# ---------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class RefEvent:
    """One upstream event as the reference sees it."""

    tag: tuple[int, int]
    node: str
    seq: int
    value: Any

    @property
    def id(self) -> tuple[str, str, int]:
        return (self.node, "out", self.seq)


@dataclass
class Scenario:
    unit: int  # ns per time unit: 1 (raw ns) or 1 ms
    events: list[RefEvent]
    ticks: list[tuple[int, int]]
    skipped: list[bool]
    inserts: list[list[RefEvent]]  # inserts[i]: events put into the buffer just before tick i
    trim_batch: int = 64  # the PortBuffer's: inproc's batches, or 1 as in the real-time backend

    def seconds(self, units: int) -> float:
        """``units`` time units as the float seconds a user would write."""
        s = units * self.unit / 1e9
        assert round(s * 1e9) == units * self.unit  # DESIGN §3: seconds -> ns is round(x * 1e9)
        return s


def plain_value(n: int) -> int:
    """Event values for the plain policies: small ints, repeats welcome (ids tell events apart)."""
    return n % 2001 - 1000


@st.composite
def scenarios(draw, make_value=plain_value, long: bool = False):
    """A random history on one consumer port fed by 1–3 producers, plus ticks and skips.

    Short scenarios are drawn field by field, so failures shrink well. ``long`` ones are dense
    (70–160 events over 120 time units) so the buffer's batched trimming (every 64 entries) kicks
    in; they come from one seeded ``Random`` because drawing hundreds of fields is slow.
    ``make_value`` turns a random non-negative int into an event value. Each event enters the
    buffer at a random moment before the first tick that can see it (``insert`` ∈ [0, 1) of the
    way there), in random order across producers.
    """
    unit = draw(st.sampled_from([1, MS]))
    trim_batch = draw(st.sampled_from([64, 2, 1]))
    producers = draw(st.sampled_from([("a",), ("b", "a"), ("c", "a", "b")]))
    if long:
        rnd = random.Random(draw(st.integers(0, 2**32)))  # an int seed shrinks fast; a Random does not
        horizon = 120
        raw = [(rnd.choice(producers), rnd.randint(0, horizon), rnd.randint(0, 3), rnd.randrange(10**6),
                rnd.random()) for _ in range(rnd.randint(70, 160))]
        tick_units = [(rnd.randint(0, horizon + 5), rnd.randint(0, 4)) for _ in range(rnd.randint(1, 80))]
        skips = [rnd.random() < 0.3 for _ in range(len(tick_units))]
    else:
        horizon = 30
        raw = draw(st.lists(st.tuples(st.sampled_from(producers), st.integers(0, horizon), st.integers(0, 3),
                                      st.integers(0, 10**6), st.floats(0, 1, exclude_max=True)), max_size=40))
        tick_units = draw(st.lists(st.tuples(st.integers(0, horizon + 5), st.integers(0, 4)), min_size=1, max_size=30))
        skips = draw(st.lists(st.booleans(), min_size=len(tick_units), max_size=len(tick_units)))
    ticks = [(t * unit, m) for t, m in sorted(set(tick_units))]
    skipped = skips[:len(ticks)]
    events, inserts = [], [[] for _ in ticks]
    for p in producers:
        # one producer port emits at most once per tag, with seq increasing in tag order
        mine = sorted({(t, m): (n, f) for q, t, m, n, f in raw if q == p}.items())
        for seq, ((t, m), (n, frac)) in enumerate(mine):
            ev = RefEvent((t * unit, m), p, seq, make_value(n))
            events.append(ev)
            first_seen = next((i for i, tau in enumerate(ticks) if tau >= ev.tag), len(ticks) - 1)
            inserts[int(frac * (first_seen + 1))].append(ev)
    # within one moment, insert in an order unrelated to (tag, producer, seq)
    inserts = [sorted(batch, key=lambda e: (e.seq * 7919 + ord(e.node)) % 997) for batch in inserts]
    return Scenario(unit, events, ticks, skipped, inserts, trim_batch)


def any_scenario(make_value=plain_value):
    return st.one_of(scenarios(make_value), scenarios(make_value, long=True))


# ---------------------------------------------------------------------------------------------
# Driving the library
# ---------------------------------------------------------------------------------------------
def buffer_entry(tag, node, seq, value) -> tuple:
    """A PortBuffer entry as the runtime inserts it (see ``PortBuffer``'s docstring)."""
    return (tag, node, "out", seq, value)


def run_policy(policy, sc: Scenario, commit_missing: bool = True) -> list[tuple]:
    """What the policy returns at each tick, committing after every tick that is not skipped.

    ``commit_missing=False`` mirrors ``backends/inproc.py``, which never commits a port whose
    value was MISSING; the documented interface commits every non-skipped tick.
    """
    buf = PortBuffer(trim_batch=sc.trim_batch)
    results = []
    for i, tau in enumerate(sc.ticks):
        for ev in sc.inserts[i]:
            buf.insert(buffer_entry(ev.tag, ev.node, ev.seq, ev.value))
        value, ids, dropped, commit = policy.select(buf, tau)
        results.append((value, ids if value is not MISSING else None, dropped))
        if not sc.skipped[i] and (commit_missing or value is not MISSING):
            policy.commit_to(buf, commit)
    return results


def history(sc: Scenario, tau) -> list[RefEvent]:
    """H: the events with tag ≤ τ, merged by tag, then producer id, then seq (DESIGN §4, §10.8)."""
    return sorted((e for e in sc.events if e.tag <= tau), key=lambda e: (e.tag, e.node, e.seq))


def one(e: RefEvent) -> tuple:
    return (e.value, (e.id,), 0)


NOTHING = (MISSING, None, 0)


def check(policy, reference, sc: Scenario, **kw) -> None:
    got = run_policy(policy, sc, **kw)
    want = reference(sc)
    for i, (g, w) in enumerate(zip(got, want)):
        assert g == w, (f"{policy!r} at tick {i} τ={sc.ticks[i]} (skipped so far: "
                        f"{[t for t, s in zip(sc.ticks[:i], sc.skipped) if s]}): got {g}, want {w}")
    assert len(got) == len(want)


# ---------------------------------------------------------------------------------------------
# References, one per policy, straight from the §4 table
# ---------------------------------------------------------------------------------------------
def ref_latest(staleness_ns):
    def ref(sc):
        out = []
        for tau in sc.ticks:
            h = history(sc, tau)
            if not h or (staleness_ns is not None and tau[0] - h[-1].tag[0] > staleness_ns):
                out.append(NOTHING)
            else:
                out.append(one(h[-1]))
        return out
    return ref


def ref_latest_distinct(sc):
    consumed, out = set(), []
    for tau, skipped in zip(sc.ticks, sc.skipped):
        h = history(sc, tau)
        if not h or h[-1].id in consumed:
            out.append(NOTHING)
            continue
        out.append(one(h[-1]))
        if not skipped:
            consumed.add(h[-1].id)
    return out


def ref_window(buffer_size, duration_ns):
    def ref(sc):
        out = []
        for tau in sc.ticks:
            h = [e for e in history(sc, tau) if duration_ns is None or tau[0] - e.tag[0] <= duration_ns]
            if buffer_size is not None:
                h = h[-buffer_size:]
            out.append(([e.value for e in h], tuple(e.id for e in h), 0))
        return out
    return ref


def ref_queue(maxsize):
    def ref(sc):
        consumed, out = set(), []
        for tau, skipped in zip(sc.ticks, sc.skipped):
            new = [e for e in history(sc, tau) if e.id not in consumed]
            dropped = max(0, len(new) - maxsize) if maxsize is not None else 0
            batch = new[dropped:]
            out.append(([e.value for e in batch], tuple(e.id for e in batch), dropped))
            if not skipped:
                consumed.update(e.id for e in new)  # dropped events count as consumed
        return out
    return ref


def ref_exact(tolerance_ns):
    def ref(sc):
        out = []
        for tau in sc.ticks:
            h = history(sc, tau)
            near = [(abs(tau[0] - e.tag[0]), i, e) for i, e in enumerate(h) if abs(tau[0] - e.tag[0]) <= tolerance_ns]
            out.append(one(min(near)[2]) if near else NOTHING)  # nearest; earlier on ties
        return out
    return ref


def ref_action_chunking(control_hz, chunk_steps, on_exhausted):
    hz = Fraction(repr(control_hz)) if isinstance(control_hz, float) else Fraction(control_hz)

    def ref(sc):
        out = []
        for tau in sc.ticks:
            started = []
            for e in history(sc, tau):
                rows, t0 = (e.value["actions"], e.value["t0"]) if isinstance(e.value, dict) else (e.value, e.tag[0])
                if t0 <= tau[0]:
                    started.append((e, rows, t0))
            if not started:
                out.append(NOTHING)
                continue
            e, rows, t0 = started[-1]  # the newest chunk that has started
            row = math.floor((tau[0] - t0) * hz / 10**9)
            if row >= chunk_steps:
                if on_exhausted == "missing":
                    out.append(NOTHING)
                    continue
                row = chunk_steps - 1
            out.append((rows[row], (e.id,), 0))
        return out
    return ref


# ---------------------------------------------------------------------------------------------
# Properties
# ---------------------------------------------------------------------------------------------
@SETTINGS
@given(sc=any_scenario(), stale=st.none() | st.integers(0, 12))
def test_latest_matches_reference(sc, stale):
    """Latest(staleness): newest of H, MISSING when H is empty or the newest is older than staleness."""
    policy = Latest() if stale is None else Latest(staleness=sc.seconds(stale))
    check(policy, ref_latest(None if stale is None else stale * sc.unit), sc)


@SETTINGS
@given(sc=any_scenario())
def test_latest_distinct_matches_reference(sc):
    """LatestDistinct: newest of H unless this consumer already consumed it; skipped ticks consume nothing.

    Drives the documented interface: ``commit_to(buf, commit)`` after every tick that is not skipped,
    including ticks where this port's value was MISSING (an optional port takes its default).
    """
    check(LatestDistinct(), ref_latest_distinct, sc)


@SETTINGS
@given(sc=any_scenario())
def test_latest_distinct_matches_reference_inproc_convention(sc):
    """As above, committing only ticks whose value was not MISSING (what backends/inproc.py does)."""
    check(LatestDistinct(), ref_latest_distinct, sc, commit_missing=False)


@SETTINGS
@given(sc=any_scenario(), size=st.none() | st.integers(1, 6), dur=st.none() | st.integers(0, 12))
def test_window_matches_reference(sc, size, dur):
    """Window(buffer_size, duration): values of H within duration of τ (inclusive), newest buffer_size, oldest first."""
    policy = Window(buffer_size=size, duration=None if dur is None else sc.seconds(dur))
    check(policy, ref_window(size, None if dur is None else dur * sc.unit), sc)


@SETTINGS
@given(sc=any_scenario(), maxsize=st.none() | st.integers(1, 5))
def test_queue_matches_reference(sc, maxsize):
    """Queue(maxsize): unconsumed events of H, oldest first; overflow drops the oldest and counts them.

    A skipped tick consumes nothing, so its events are offered again on the next tick.
    """
    check(Queue(maxsize) if maxsize is not None else Queue(), ref_queue(maxsize), sc)


@SETTINGS
@given(sc=any_scenario(), tol=st.integers(0, 8))
def test_exact_matches_reference(sc, tol):
    """Exact(tolerance): the event nearest τ's time within tolerance, the earlier one on ties; else MISSING."""
    policy = Exact(tolerance=sc.seconds(tol)) if tol else Exact()
    check(policy, ref_exact(tol * sc.unit), sc)


@st.composite
def chunk_scenarios(draw):
    """A scenario whose values are action chunks of ``steps`` rows: lists, tuples, or dicts with ``t0``."""
    steps = draw(st.integers(1, 6))

    def chunk(n: int):
        rows = [n * 10 + i for i in range(steps)]
        form = n % 3
        if form == 0:
            return rows
        if form == 1:
            return tuple(rows)
        return {"actions": rows, "t0": (n // 3) % 41}  # t0 in time units until scaled below

    sc = draw(any_scenario(make_value=chunk))
    for e in sc.events:  # a dict chunk's own t0 (int ns), anywhere from before to after its tag
        if isinstance(e.value, dict):
            e.value["t0"] *= sc.unit
    return sc, steps


@SETTINGS
@given(data=chunk_scenarios(), hz=st.sampled_from([200, 1000, 30, 33.3, 7, 0.5, 1e6, 2.5e8]),
       on_exhausted=st.sampled_from(["hold", "missing"]))
def test_action_chunking_matches_reference(data, hz, on_exhausted):
    """ActionChunking: newest started chunk, row floor((τ.t − t0)·hz/1e9), hold or MISSING past the end."""
    sc, steps = data
    policy = ActionChunking(control_hz=hz, chunk_steps=steps, on_exhausted=on_exhausted)
    check(policy, ref_action_chunking(hz, steps, on_exhausted), sc)


@SETTINGS
@given(data=chunk_scenarios(), hz=st.sampled_from([200, 1000, 30, 33.3, 7, 2.5e8]),
       on_exhausted=st.sampled_from(["hold", "missing"]), horizon=st.integers(1, 40))
def test_action_chunking_horizon_matches_reference(data, hz, on_exhausted, horizon):
    """ActionChunking(horizon_ms=): at τ.t − t0 ≥ horizon a chunk is exhausted like one past its last row.

    Pinned to the policy's docstring (the paper's Appendix D-D ``horizon_ms``; DESIGN §4 is
    silent). When exhausted by the horizon, ``hold`` keeps the last row that started before it.
    """
    sc, steps = data
    horizon_ns = horizon * sc.unit
    horizon_ms = horizon_ns / 1e6
    assert round(horizon_ms * 1e6) == horizon_ns
    rate = Fraction(repr(hz)) if isinstance(hz, float) else Fraction(hz)
    policy = ActionChunking(control_hz=hz, chunk_steps=steps, on_exhausted=on_exhausted, horizon_ms=horizon_ms)
    plain = ref_action_chunking(hz, steps, on_exhausted)

    def ref(sc):
        out = []
        for tau, want in zip(sc.ticks, plain(sc)):
            started = [e for e in history(sc, tau)
                       if (e.value["t0"] if isinstance(e.value, dict) else e.tag[0]) <= tau[0]]
            if started:
                e = started[-1]
                t0 = e.value["t0"] if isinstance(e.value, dict) else e.tag[0]
                rows = e.value["actions"] if isinstance(e.value, dict) else e.value
                if tau[0] - t0 >= horizon_ns:
                    last = min(steps, math.ceil(horizon_ns * rate / 10**9)) - 1
                    want = (rows[last], (e.id,), 0) if on_exhausted == "hold" else NOTHING
            out.append(want)
        return out

    check(policy, ref, sc)


# ---------------------------------------------------------------------------------------------
# docs/semantics.md's worked examples 5 and 7, exactly
# ---------------------------------------------------------------------------------------------
def _stream(*tags_ms):
    s = EventStream("up")
    for i, t in enumerate(tags_ms):
        s.append((t * MS, 1), f"v{i}")
    return s


def test_window_example_10_5():
    """§10.5: with v1…v5 in H, Window(buffer_size=3) gives [v3, v4, v5]."""
    s = _stream(0, 10, 20, 30, 40, 50)
    assert s.sample(Window(buffer_size=3), (50 * MS, 1)) == ["v3", "v4", "v5"]


def test_event_stream_fresh_policy_starts_fresh():
    """A new policy object sampling an EventStream is a new consumer: no state from earlier, discarded ones.

    The types.py docstring pattern ``frames.sample(Latest(), now=...)`` creates a temporary policy
    per call; each call must answer from the whole stream, independent of earlier calls.
    """
    s = _stream(0, 10, 20, 30, 40, 50)
    assert s.sample(Window(buffer_size=3), (50 * MS, 1)) == ["v3", "v4", "v5"]
    assert s.sample(Window(buffer_size=3), (50 * MS, 0)) == ["v2", "v3", "v4"]  # v5 at (50,1) is not ≤ (50,0)
    assert s.sample(Latest(), 0.045) == "v4"
    assert s.sample(Latest(), 0.015) == "v1"
    assert s.sample(Queue(), 0.025) == ["v0", "v1", "v2"]
    assert s.sample(Queue(), 0.025) == ["v0", "v1", "v2"]


def test_queue_example_10_5():
    """§10.5: after consuming up to v0, Queue(maxsize=2) gives [v4, v5] with 3 dropped; next tick starts after v5."""
    buf, q = PortBuffer(), Queue(maxsize=2)
    for i, t in enumerate([0, 10, 20, 30, 40, 50, 60]):
        buf.insert(buffer_entry((t * MS, 1), "up", i, f"v{i}"))
    value, ids, dropped, commit = q.select(buf, (5 * MS, 0))
    assert (value, dropped) == (["v0"], 0)
    q.commit_to(buf, commit)
    value, ids, dropped, commit = q.select(buf, (55 * MS, 0))
    assert (value, ids, dropped) == (["v4", "v5"], (("up", "out", 4), ("up", "out", 5)), 3)
    q.commit_to(buf, commit)
    value, ids, dropped, commit = q.select(buf, (70 * MS, 0))
    assert (value, dropped) == (["v6"], 0)


class Ticker(Flow):
    """Source emitting ``v0``, ``v1``, … on its first ``count`` ticks, then nothing."""

    def __init__(self, count: int = 10**9, prefix: str = "v"):
        self.count, self.prefix, self.k = count, prefix, 0

    def step(self):
        k, self.k = self.k, self.k + 1
        return {"out": f"{self.prefix}{k}"} if k < self.count else None


class Echo(Flow):
    """Emits whatever it received on its one required port ``x``."""

    def step(self, x):
        return {"seen": x}


class MaybeEcho(Flow):
    """Emits what it received on its optional port ``x`` (None when MISSING)."""

    def step(self, x=None):
        return {"seen": "none" if x is None else x}


def _seen(trace, node="echo"):
    by_id = {e.id: e.value for e in trace.events}
    return {s.tag: (s.status, [by_id[i] for i in s.produced], s.detail, s.consumed) for s in trace.steps_of(node)}


def _dropped(detail, port):
    """The drop count a step record holds for ``port`` (flat ``{port: n}`` or under ``dropped``)."""
    detail = detail or {}
    return detail.get("dropped", detail).get(port, 0)


def test_queue_example_10_5_in_a_pipeline():
    """§10.5 through the in-process runtime: 3 dropped are counted in the step record; the next tick starts after v5."""
    with Pipeline("q105") as pipe:
        up = Ticker(count=8).named("up") @ Rate(100)          # v0..v7 at (0,1), (10,1), …, (70,1) ms
        echo = Echo().named("echo") @ Rate(20, offset=0.001)  # ticks at 1, 51, 101 ms
        up.then(echo, sync=Queue(maxsize=2), map={"out": "x"})
    seen = _seen(pipe.run(duration=0.11))
    assert seen[(1 * MS, 0)][1] == [["v0"]]
    status, out, detail, consumed = seen[(51 * MS, 0)]
    assert (status, out, _dropped(detail, "x")) == ("ok", [["v4", "v5"]], 3)
    assert consumed == {"x": (("up", "out", 4), ("up", "out", 5))}
    assert seen[(101 * MS, 0)][1] == [["v6", "v7"]]


def test_window_example_10_5_in_a_pipeline():
    """§10.5: Window(buffer_size=3) at a tick that sees v0…v5 delivers [v3, v4, v5]."""
    with Pipeline("w105") as pipe:
        up = Ticker().named("up") @ Rate(100)
        echo = Echo().named("echo") @ Rate(20, offset=0.001)
        up.then(echo, sync=Window(buffer_size=3), map={"out": "x"})
    seen = _seen(pipe.run(duration=0.06))
    assert seen[(1 * MS, 0)][1] == [["v0"]]
    assert seen[(51 * MS, 0)][1] == [["v3", "v4", "v5"]]


def test_skipped_tick_keeps_queue_example_10_6():
    """§10.6: a tick skipped for a missing required port consumes nothing; Queue and LatestDistinct events stay."""
    with Pipeline("s106") as pipe:
        img = Ticker(prefix="img").named("img") @ Rate(10, offset=0.05)  # first image at (50, 1) ms
        q = Ticker(prefix="q").named("q") @ Rate(100)
        once = Ticker(count=1, prefix="once").named("once") @ Rate(100, offset=0.01)  # one event at (10, 1)
        both = Both().named("both") @ Rate(40)                          # ticks at 0, 25, 50, 75 ms
        img.then(both, sync=Latest(), map={"out": "img"})
        q.then(both, sync=Queue(), map={"out": "items"})
        once.then(both, sync=LatestDistinct(), map={"out": "once"})
    trace = pipe.run(duration=0.08)
    recs = {s.tag[0] // MS: s for s in trace.steps_of("both")}
    assert recs[0].status == recs[25].status == recs[50].status == "skipped"
    assert recs[25].detail == {"missing": ["img"]}
    assert recs[25].consumed == {} and recs[25].produced == ()
    assert recs[75].status == "ok"
    by_id = {e.id: e.value for e in trace.events}
    assert by_id[recs[75].produced[0]] == ["img0", ["q0", "q1", "q2", "q3", "q4", "q5", "q6", "q7"], "once0"]


class Both(Flow):
    """Needs an image; also drains a queue and takes a LatestDistinct value when there is one."""

    def step(self, img, items, once=None):
        return {"out": [img, items, once]}


class Planner(Flow):
    """Emits an 8-row action chunk on the ticks listed in ``emit_on`` (tick index k → rows 'k:0'…'k:7')."""

    def __init__(self, emit_on=(0, 1, 3)):
        self.emit_on, self.k = list(emit_on), 0

    def step(self):
        k, self.k = self.k, self.k + 1
        return {"chunk": [f"{k}:{i}" for i in range(8)]} if k in self.emit_on else None


@pytest.mark.parametrize("on_exhausted", ["hold", "missing"])
def test_action_chunking_example_10_7(on_exhausted):
    """§10.7: ActionChunking(200, 8) at 100/105/135/140 ms around a chunk emitted at (100, 1)."""
    with Pipeline("ac107") as pipe:
        planner = Planner().named("planner") @ Rate(10)  # chunks at (0,1), (100,1), (300,1) ms
        ctrl = Echo().named("echo") @ Rate(200)
        planner.then(ctrl, sync=ActionChunking(control_hz=200, chunk_steps=8, on_exhausted=on_exhausted),
                     map={"chunk": "x"})
    seen = _seen(pipe.run(duration=0.31))
    hold = on_exhausted == "hold"

    def at(ms):
        status, out, _, _ = seen[(ms * MS, 0)]
        return out[0] if status == "ok" else status

    assert at(0) == "skipped"                            # chunk 0 is at (0,1): not ≤ (0,0)
    assert at(5) == "0:1"
    assert at(35) == "0:7"
    assert at(40) == ("0:7" if hold else "skipped")
    assert at(100) == ("0:7" if hold else "skipped")     # (100,0) does not see the chunk at (100,1)
    assert at(105) == "1:1"                              # floor((105−100)·200/1000) = 1
    assert at(135) == "1:7"
    assert at(140) == ("1:7" if hold else "skipped")     # row 8 ≥ 8
    assert at(300) == ("1:7" if hold else "skipped")
    assert at(305) == "3:1"                              # a newer chunk replaces it from its own t0


def test_action_chunking_example_10_7_on_a_stream():
    """§10.7 on an EventStream: rows 1 and 7, then hold / MISSING; the chunk's own t0 field wins over its tag."""
    for on_exhausted, past_end in (("hold", 7), ("missing", MISSING)):
        s = EventStream("planner")
        s.append((100 * MS, 1), list(range(8)))
        pol = ActionChunking(control_hz=200, chunk_steps=8, on_exhausted=on_exhausted)
        assert s.sample(pol, (100 * MS, 0)) is MISSING
        assert [s.sample(pol, 0.105), s.sample(pol, 0.135), s.sample(pol, 0.140)] == [1, 7, past_end]
    s = EventStream("planner")
    s.append((100 * MS, 1), {"actions": list(range(8)), "t0": 90 * MS})
    assert s.sample(ActionChunking(control_hz=200, chunk_steps=8), 0.105) == 3


def test_latest_distinct_stream_does_not_redeliver():
    """LatestDistinct on an EventStream: one event is delivered once, however often it is sampled."""
    s = EventStream("up")
    s.append(0.0, "v")
    pol = LatestDistinct()
    assert [s.sample(pol, 0.01) for _ in range(4)] == ["v", MISSING, MISSING, MISSING]


def test_latest_distinct_optional_port_in_a_pipeline():
    """LatestDistinct into an optional port of a faster consumer: each event is delivered exactly once."""
    with Pipeline("ld") as pipe:
        up = Ticker().named("up") @ Rate(10)
        echo = MaybeEcho().named("echo") @ Rate(40)
        up.then(echo, sync=LatestDistinct(), map={"out": "x"})
    seen = _seen(pipe.run(duration=0.3))
    got = [out[0] for _, (_, out, _, _) in sorted(seen.items())]
    assert got == ["none", "v0", "none", "none", "none", "v1", "none", "none", "none", "v2", "none", "none"]


# ---------------------------------------------------------------------------------------------
# Fan-in through a real pipeline (DESIGN §10.8)
# ---------------------------------------------------------------------------------------------
@SETTINGS
@given(
    rates=st.tuples(st.sampled_from([10, 20, 50, 100, 30, 33.3]), st.sampled_from([10, 20, 50, 100, 30, 33.3])),
    latencies=st.tuples(st.sampled_from([0, 0.01, 0.05]), st.sampled_from([0, 0.01, 0.05])),
    delays=st.tuples(st.sampled_from([0, 0.01, 0.02]), st.sampled_from([0, 0.01, 0.02])),
    policy=st.sampled_from([Window(), Window(buffer_size=3), Queue(), Queue(maxsize=2)]),
    consumer=st.sampled_from([Rate(25), Rate(100), Rate(7, offset=0.01), Trigger("x")]),
)
def test_fan_in_merge_order(rates, latencies, delays, policy, consumer):
    """Two producers into one port: the consumer sees H merged by (arrival tag, producer id, seq).

    Producers are declared in reverse id order ("zeta" before "alpha") so registration order
    cannot stand in for id order. An edge's delay shifts its stream to (t + delay, 0); equal
    rates, LET and delays make many equal arrival tags.
    """
    with Pipeline("fanin") as pipe:
        zeta = Ticker(prefix="z").configure(name="zeta", latency=latencies[0]) @ Rate(rates[0])
        alpha = Ticker(prefix="a").configure(name="alpha", latency=latencies[1]) @ Rate(rates[1])
        echo = Echo().named("echo") @ consumer
        pipe.connect(zeta, echo, sync=policy, map={"out": "x"}, delay=delays[0])
        pipe.connect(alpha, echo, sync=policy, map={"out": "x"}, delay=delays[1])
    trace = pipe.run(duration=0.3)
    delay_ns = {"zeta": round(delays[0] * 1e9), "alpha": round(delays[1] * 1e9)}

    def arrival(e):  # a delayed edge delivers at (t + delay, 0)
        return (e.tag[0] + delay_ns[e.node], 0) if delay_ns[e.node] else e.tag

    upstream = [(arrival(e), e.node, e.seq, e) for e in trace.events if e.node in delay_ns]
    upstream.sort(key=lambda x: x[:3])
    by_id = {e.id: e.value for e in trace.events}
    consumed: set = set()
    steps = trace.steps_of("echo")
    assert steps, "the consumer never ticked"
    for rec in steps:
        h = [x[3] for x in upstream if x[0] <= rec.tag]
        if isinstance(policy, Queue):
            h = [e for e in h if e.id not in consumed]
            consumed.update(e.id for e in h)  # dropped ones count as consumed
        keep = policy.maxsize if isinstance(policy, Queue) else policy.buffer_size
        if keep is not None:
            h = h[-keep:]
        assert rec.status == "ok"
        assert rec.consumed.get("x", ()) == tuple(e.id for e in h), rec
        assert by_id[rec.produced[0]] == [e.value for e in h], rec
