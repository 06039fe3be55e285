"""Functional determinism of the in-process backend (docs/semantics.md).

Hypothesis generates random multi-rate graphs with cycles — Rate sources at 7…200 Hz, Trigger,
Hybrid and Rate flows, random sync policies, LET latencies, delayed feedback edges, and
instantaneous trigger cycles that terminate — and checks that the trace is a function of the
program alone:

- every ``tie_break_seed`` (any order of the ticks that share a tag) gives the same digest as the
  default order;
- two fresh pipelines built from the same description give equal traces;
- ``pipe.step(dt)``/``pipe.run(duration)`` in several increments give the trace of one
  ``pipe.run(duration)``.

The flows fold every input they receive into their state and emit values derived from both, so a
tick that saw a different snapshot, ran in a different order relative to its own earlier ticks,
or consumed a different Queue batch would change every later value.

How the generated cycles stay finite within an instant: ordinary feedback edges (to a node with a
lower or equal index) are made non-instantaneous (a delay, a producer with latency, or a
consumer that does not trigger on that port); the only instantaneous feedback is a *rally*
between ``Rally`` flows: a rally hop ``h`` arrives on port ``b`` (LatestDistinct) and is answered
with ``h + 1`` on ``fb`` while ``h + 1 < limit``, emitting nothing on ``out``; so every rally dies
out after ``limit`` microsteps (DESIGN §10.9's monitor ⇄ policy, with a flow that stops emitting).
"""

from __future__ import annotations

import contextlib
import warnings
from dataclasses import dataclass, field

import pytest
from hypothesis import HealthCheck, given, reject, settings
from hypothesis import strategies as st

from retriever import (
    ActionChunking,
    Burst,
    CausalityError,
    Exact,
    Flow,
    Hybrid,
    Latest,
    LatestDistinct,
    Pipeline,
    Queue,
    Rate,
    RetrieverWarning,
    StepError,
    Trigger,
    Window,
)

P = 2_147_483_647  # values stay small ints; msgpack and digests stay cheap


def fold(x) -> int:
    """A deterministic int summary of an input value: None, int, or (nested) lists of them."""
    if x is None:
        return 1
    if isinstance(x, (list, tuple)):
        h = 7 + len(x)
        for v in x:
            h = (h * 31 + fold(v)) % P
        return h
    return x % P


# Why each run has a work budget: delayed feedback into Trigger flows makes tick trains whose tags
# are sums of the graph's delays and latencies, so the number of ticks grows exponentially with
# the run and nothing in the generator bounds it. Counting steps alone is not enough: such a train
# feeding a Window(duration=...) makes windows of thousands of values, every tick consumes them
# all, and each step record keeps their ids, so memory grows as steps × window size. (CI, where
# Hypothesis derandomises, met such a graph: 4430-value windows at 0.97 s, pytest past 6 GB and
# killed.) So every step spends one unit plus one per value it receives; a run that spends more
# than WORK_BUDGET stops and its example is rejected. Runs are deterministic, so every run of one
# graph spends the same, and each example's time and memory stay bounded.
WORK_BUDGET = 200_000  # per run: steps + values consumed


class OverBudget(Exception):
    """A run spent its WORK_BUDGET (raised from a step, so it stops the run as a StepError)."""


class Budget:
    left = WORK_BUDGET

    @classmethod
    def spend(cls, *inputs) -> None:
        cls.left -= 1 + sum(len(x) for x in inputs if type(x) is list)
        if cls.left < 0:
            raise OverBudget(f"more than {WORK_BUDGET} steps and values consumed")


# ---------------------------------------------------------------------------------------------
# Flows (module level, so the graphs are ordinary, IR-rebuildable programs)
# ---------------------------------------------------------------------------------------------
class Src(Flow):
    """A source: a counter mixed with a salt; emits nothing on every ``sparse``-th tick. With
    ``burst``, a Burst of ``n % burst`` such values a tick (an empty one: no event)."""

    def __init__(self, salt: int = 0, sparse: int = 0, burst: int = 0):
        self.salt, self.sparse, self.burst, self.n = salt, sparse, burst, 0

    def step(self):
        Budget.spend()
        return self.count()

    def count(self):
        self.n += 1
        if self.sparse and self.n % self.sparse == 0:
            return None
        value = (self.n * 1_000_003 + self.salt) % P
        if self.burst:
            return {"out": Burst((value + i) % P for i in range(self.n % self.burst))}
        return {"out": value}


class Beside(Src):
    """A Src that spends none of the work budget: a flow run beside a generated graph, which
    leaves where the graph's run spends its budget, and stops, as it is alone."""

    def step(self):
        return self.count()


class Chunker(Flow):
    """A source of 4-row action chunks whose rows depend on its tick count."""

    def __init__(self, salt: int = 0):
        self.salt, self.n = salt, 0

    def step(self):
        Budget.spend()
        self.n += 1
        return {"out": [(self.n * 100 + i + self.salt) % P for i in range(4)]}


class Mix(Flow):
    """Folds its (all optional) inputs into its state; emits the state on ``out`` unless it is ≡ 0 mod ``sparse``."""

    def __init__(self, salt: int = 0, sparse: int = 0):
        self.salt, self.sparse, self.state, self.n = salt, sparse, salt, 0

    def mix(self, a, b, c) -> int:
        Budget.spend(a, b, c)
        self.n += 1
        self.state = (self.state * 1_000_003 + self.salt + 31 * fold(a) + 17 * fold(b) + 7 * fold(c) + self.n) % P
        return self.state

    def step(self, a=None, b=None, c=None):
        s = self.mix(a, b, c)
        return None if self.sparse and s % self.sparse == 0 else {"out": s}


class Need(Mix):
    """Like Mix, but ``a`` is required: a tick where ``a`` is MISSING is skipped and consumes nothing."""

    def step(self, a, b=None, c=None):
        return Mix.step(self, a, b, c)


class Rally(Mix):
    """A Mix that also plays rallies on ``fb`` → (another Rally's) ``b``.

    Ticked with a fresh rally hop ``b`` it answers ``b + 1`` on ``fb`` while that is below
    ``limit`` and emits nothing on ``out``; otherwise it emits its state on ``out`` and serves a
    new rally (hop 0) on ``fb``.
    """

    def __init__(self, salt: int = 0, sparse: int = 0, limit: int = 3):
        super().__init__(salt, sparse)
        self.limit = limit

    def step(self, a=None, b=None, c=None):
        s = self.mix(a, b, c)
        if b is not None:
            return {"fb": b + 1} if b + 1 < self.limit else None
        out = None if self.sparse and s % self.sparse == 0 else s
        return {"out": out, "fb": 0}


# ---------------------------------------------------------------------------------------------
# Random graphs
# ---------------------------------------------------------------------------------------------
RATES = [7, 10, 20, 30, 33.3, 50, 100, 200]
POLICIES = [Latest(), Latest(staleness=0.05), LatestDistinct(), Window(buffer_size=4), Window(duration=0.05),
            Window(buffer_size=3, duration=0.1), Queue(), Queue(maxsize=1), Queue(maxsize=3), Exact(),
            Exact(tolerance=0.01)]
CHUNK_POLICIES = [ActionChunking(control_hz=200, chunk_steps=4), ActionChunking(control_hz=33.3, chunk_steps=4),
                  ActionChunking(control_hz=50, chunk_steps=4, on_exhausted="missing")]


@dataclass
class NodeSpec:
    kind: str  # Src | Beside | Chunker | Mix | Need | Rally
    clock: object
    latency: float = 0.0
    params: dict = field(default_factory=dict)


@dataclass
class EdgeSpec:
    src: int
    src_port: str
    dst: int
    dst_port: str
    sync: object
    delay: float = 0.0


@dataclass
class GraphSpec:
    nodes: list[NodeSpec]
    edges: list[EdgeSpec]

    def build(self) -> Pipeline:
        """A fresh pipeline with fresh flows for this description."""
        classes = {"Src": Src, "Beside": Beside, "Chunker": Chunker, "Mix": Mix, "Need": Need, "Rally": Rally}
        with Pipeline("random") as pipe:
            flows = [classes[n.kind](**n.params).configure(name=f"n{i}", latency=n.latency) @ n.clock
                     for i, n in enumerate(self.nodes)]
            for e in self.edges:
                pipe.connect(flows[e.src], flows[e.dst], sync=e.sync, map={e.src_port: e.dst_port}, delay=e.delay)
        return pipe

    def __repr__(self) -> str:  # readable falsifying examples
        lines = [f"  n{i}: {n.kind}{n.params} @ {n.clock!r}" + (f" latency={n.latency}" if n.latency else "")
                 for i, n in enumerate(self.nodes)]
        lines += [f"  n{e.src}.{e.src_port} -> n{e.dst}.{e.dst_port} {e.sync!r}"
                  + (f" delay={e.delay}" if e.delay else "") for e in self.edges]
        return "GraphSpec(\n" + "\n".join(lines) + "\n)"


def _triggers(clock, port: str) -> bool:
    return clock.triggered and (not clock.trigger_ports or port in clock.trigger_ports)


@st.composite
def graphs(draw) -> GraphSpec:
    """A random multi-rate graph: 1–3 Rate sources then 2–5 inner flows, with cycles."""
    rate = st.sampled_from(RATES)
    offset = st.sampled_from([0.0, 0.0, 0.005, 0.0125])
    latency = st.sampled_from([0.0] * 5 + [0.01, 0.05, 0.1])
    salt = st.integers(0, 1000)
    sparse = st.sampled_from([0, 0, 3, 5])

    nodes: list[NodeSpec] = []
    for _ in range(draw(st.integers(1, 3))):
        if draw(st.integers(0, 3)) == 0:
            nodes.append(NodeSpec("Chunker", Rate(draw(rate)), draw(latency), {"salt": draw(salt)}))
        else:
            nodes.append(NodeSpec("Src", Rate(draw(rate), offset=draw(offset)), draw(latency),
                                  {"salt": draw(salt), "sparse": draw(sparse),
                                   "burst": draw(st.sampled_from([0, 0, 0, 4]))}))
    n_sources = len(nodes)
    for _ in range(draw(st.integers(2, 5))):
        kind = draw(st.sampled_from(["Mix", "Mix", "Need", "Rally", "Rally", "Rally"]))
        if kind == "Rally":  # mostly triggered by rallies on b, so rallies run in microsteps
            choice = draw(st.sampled_from(["trigger_any", "trigger_b", "trigger_b", "hybrid_b", "rate"]))
        else:
            choice = draw(st.sampled_from(["rate", "trigger_any", "trigger_any", "trigger_a", "trigger_b",
                                           "hybrid_a", "hybrid_b"]))
        clock = {
            "rate": lambda: Rate(draw(rate), offset=draw(offset)),
            "trigger_any": lambda: Trigger(),
            "trigger_a": lambda: Trigger("a"),
            "trigger_b": lambda: Trigger("a", "b"),
            "hybrid_a": lambda: Hybrid(draw(rate), trigger=["a"]),
            "hybrid_b": lambda: Hybrid(draw(rate), trigger=["b"] if kind == "Rally" else ["a", "b"]),
        }[choice]()
        params = {"salt": draw(salt), "sparse": draw(sparse)}
        if kind == "Rally":
            params["limit"] = draw(st.integers(1, 6))
        nodes.append(NodeSpec(kind, clock, draw(latency), params))

    edges: list[EdgeSpec] = []
    seen: set = set()
    port_policy: dict = {}
    chunkers = [i for i, n in enumerate(nodes) if n.kind == "Chunker"]
    others = [i for i, n in enumerate(nodes) if n.kind != "Chunker"]
    for dst in range(n_sources, len(nodes)):
        d = nodes[dst]
        ordinary_ports = ["a"] if d.kind == "Rally" else ["a", "b"]
        for _ in range(draw(st.integers(1 if d.kind == "Rally" else 0, 3))):
            src = draw(st.sampled_from(others))
            port = draw(st.sampled_from(ordinary_ports))
            delay = draw(st.sampled_from([0.0, 0.0, 0.0, 0.01, 0.05]))
            if src >= dst and not delay and not nodes[src].latency and _triggers(d.clock, port):
                delay = draw(st.sampled_from([0.01, 0.025, 1 / 30]))  # feedback: never instantaneous
            policy = port_policy.setdefault((dst, port), draw(st.sampled_from(POLICIES)))
            if (src, dst, port) not in seen:
                seen.add((src, dst, port))
                edges.append(EdgeSpec(src, "out", dst, port, policy, delay))
        if d.kind == "Rally":  # rallies: the only instantaneous feedback
            rallies = [i for i, n in enumerate(nodes) if n.kind == "Rally"]
            for src in draw(st.lists(st.sampled_from(rallies), min_size=1, max_size=2, unique=True)):
                edges.append(EdgeSpec(src, "fb", dst, "b", LatestDistinct()))
        if chunkers and draw(st.booleans()):
            policy = draw(st.sampled_from(CHUNK_POLICIES))
            for src in draw(st.lists(st.sampled_from(chunkers), min_size=1, max_size=2, unique=True)):
                edges.append(EdgeSpec(src, "out", dst, "c", policy, draw(st.sampled_from([0.0, 0.0, 0.02]))))
    return GraphSpec(nodes, edges)


@contextlib.contextmanager
def budget():
    """A fresh WORK_BUDGET for one run of a generated graph (a run, a replay, a re-simulation);
    the example is rejected if the run spends it all."""
    Budget.left = WORK_BUDGET
    try:
        yield
    except StepError as error:
        if isinstance(error.__cause__, OverBudget):
            reject()
        raise


def run(spec: GraphSpec, duration: float, **options):
    """Build and run ``spec`` within a fresh budget."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RetrieverWarning)  # instantaneous cycles, unfed ports: intended here
        pipe = spec.build()
        with budget():
            return pipe, pipe.run(duration=duration, **options)


DURATION = 1.0
SEEDS = [0, 1, 2, 12345]
SETTINGS = settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])


# ---------------------------------------------------------------------------------------------
# Properties
# ---------------------------------------------------------------------------------------------
@settings(SETTINGS, max_examples=60)
@given(spec=graphs())
def test_trace_is_independent_of_tie_breaking(spec):
    """Any order of the ticks that share a tag (tie_break_seed) gives the default order's trace digest."""
    _, reference = run(spec, DURATION)
    assert reference.steps, "the generated graph never ticked"
    for seed in SEEDS:
        _, shuffled = run(spec, DURATION, tie_break_seed=seed)
        assert shuffled.digest() == reference.digest(), \
            f"tie_break_seed={seed}: {reference.first_difference(shuffled)}"


@SETTINGS
@given(spec=graphs())
def test_fresh_pipelines_give_equal_traces(spec):
    """The same program built twice, from fresh flows, runs to equal traces; so does a rerun after pipe.reset()."""
    pipe, first = run(spec, DURATION)
    _, second = run(spec, DURATION)
    assert first == second, first.first_difference(second)
    assert first.digest() == second.digest()
    pipe.reset()
    assert pipe.now == 0.0 and not pipe.trace.steps
    with budget():
        again = pipe.run(duration=DURATION)
    assert again.digest() == first.digest(), first.first_difference(again)


@SETTINGS
@given(spec=graphs(), cuts=st.lists(st.integers(0, round(DURATION * 1000)), max_size=5),
       use_run=st.lists(st.booleans(), min_size=6, max_size=6))
def test_increments_give_the_one_run_trace(spec, cuts, use_run):
    """step(dt)/run(dt) in several increments (some of length 0) give the trace of one run(duration).

    Windows are half-open, so a tick at exactly a cut belongs to the next increment, and the
    increments' ns add up exactly (each dt is a whole number of ms).
    """
    _, whole = run(spec, DURATION)
    whole_steps = whole.canonical()[1]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RetrieverWarning)
        pipe = spec.build()
        Budget.left = WORK_BUDGET  # the whole run kept within it, so these increments do too
        bounds = [0, *sorted(cuts), round(DURATION * 1000)]
        for (lo, hi), by_run in zip(zip(bounds, bounds[1:]), use_run):
            dt = (hi - lo) / 1000
            pipe.run(duration=dt) if by_run else pipe.step(dt)
            # after each call: exactly the ticks with t < now have run
            now_ns = round(pipe.now * 1e9)
            assert now_ns == hi * 1_000_000
            assert pipe.trace.canonical()[1] == [s for s in whole_steps if s.tag[0] < now_ns]
    assert pipe.trace.digest() == whole.digest(), whole.first_difference(pipe.trace)


# ---------------------------------------------------------------------------------------------
# Instantaneous cycles, by hand
# ---------------------------------------------------------------------------------------------
class Monitor(Flow):
    """§10.9's monitor: feeds the policy back until it has bounced ``rounds`` times in one instant."""

    def __init__(self, rounds: int = 5):
        self.rounds, self.state = rounds, 0

    def step(self, obs=None, fb=None):
        self.state = (self.state * 31 + fold(obs) + fold(fb)) % P
        hop = 0 if fb is None else fb + 1
        return {"skill": hop} if hop < self.rounds else None


class Policy(Flow):
    """§10.9's policy: answers every skill on ``fb`` with the hop it got."""

    def __init__(self):
        self.state = 0

    def step(self, skill):
        self.state = (self.state * 31 + skill) % P
        return {"fb": skill, "act": self.state}


def _monitor_policy(rounds: int, max_microsteps: int = 1000) -> Pipeline:
    with Pipeline("zeno", max_microsteps=max_microsteps) as pipe:
        cam = Src(salt=3).named("cam") @ Rate(30)
        ctrl = Mix(salt=5).named("ctrl") @ Rate(200)
        monitor = Monitor(rounds=rounds).named("monitor") @ Trigger("obs", "fb")
        policy = Policy().named("policy") @ Trigger("skill")
        cam.then(monitor, sync=Latest(), map={"out": "obs"})
        monitor.then(policy, sync=LatestDistinct(), map={"skill": "skill"})
        policy.then(monitor, sync=LatestDistinct(), map={"fb": "fb"})
        policy.then(ctrl, sync=Queue(), map={"act": "a"})
    return pipe


@pytest.mark.filterwarnings("ignore::retriever.RetrieverWarning")
@pytest.mark.parametrize("rounds", [1, 4, 40])
def test_terminating_instantaneous_cycle_is_schedule_independent(rounds):
    """monitor ⇄ policy on Trigger clocks runs in microsteps (t, 1), (t, 2), … and stops; any tie-break, one trace."""
    reference = _monitor_policy(rounds).run(duration=0.5)
    ticks = [s.tag for s in reference.steps_of("monitor")]
    # the monitor ticks at (0, 1), (0, 3), …: hop i arrives at (0, 2i + 1); hop `rounds` is not answered
    assert ticks[:rounds + 2] == [(0, 2 * i + 1) for i in range(rounds + 1)] + [(33_333_333, 1)]
    assert max(m for _, m in ticks) == 2 * rounds + 1
    for seed in SEEDS:
        assert _monitor_policy(rounds).run(duration=0.5, tie_break_seed=seed).digest() == reference.digest()


@pytest.mark.filterwarnings("ignore::retriever.RetrieverWarning")
def test_zeno_loop_stops_with_the_same_error_under_any_tie_break():
    """A cycle that never stops emitting hits max_microsteps with the same CausalityError whatever the tie-break."""
    messages = set()
    for seed in [None, *SEEDS]:
        with pytest.raises(CausalityError) as info:
            _monitor_policy(rounds=10**9, max_microsteps=50).run(duration=0.5, tie_break_seed=seed)
        messages.add(str(info.value))
    assert len(messages) == 1, messages
    (message,) = messages
    assert "t=0.000000000s" in message and "max_microsteps=50" in message
    assert "monitor → policy → monitor" in message
