"""Step overhead of the in-process backend, against a hand-written loop making the same calls.

Chains of trivial flows behind one ``Rate(hz)`` source, wired with ``Latest()`` edges:

    src @ Rate ──x──▶ s01 @ clock ──x──▶ s02 @ clock ──x──▶ … ──x──▶ sNN @ clock

A chain is named ``VARIANT-CLOCK-FLOWS``:

- VARIANT ``typed``: ``Flow[None, Num]`` / ``Flow[Num, Num]`` with an ``@io`` dataclass ``Num(x)``;
  ``untyped``: ``step(self)`` / ``step(self, x)`` returning ``{"x": ...}``;
- CLOCK ``rate``: every stage ``@ Rate(hz)`` too (one schedule: a stage sees its upstream's output
  of the tick before); ``trigger``: every stage ``@ Trigger()`` (a stage ticks one microstep
  after its upstream, on its output of the same tick);
- FLOWS: the source and the stages, counted together.

For each chain the script times ``pipe.run(duration)`` on the ``inproc`` backend (the session is
opened before the clock starts) and a hand-written loop that makes **exactly the same** ``step``
calls on fresh instances of the same flow classes, in the same order, passing each stage what
``Latest()`` gives it at that tick — for the typed variant including the ``Num(x=...)`` input
construction. No framework code runs in the loop. Both runs are cross-checked: same number of
step calls per flow, same last output per flow.

"steps" are ``step()`` calls (skipped ticks are not counted; in a rate chain stage ``i`` is
skipped on its first ``i`` ticks). The framework side includes everything a run does per step —
scheduling, sync, the records it keeps in ``pipe.trace`` — so its cost may depend on the run
length: each ``--duration`` is one row. Targets (measured, not asserted; judged on medians):
≥ 500k steps/s on the typed chains; at most 3× the hand loop on typed chains, 5× on untyped ones.

Two more columns. The *floor*: the hand loop plus only the records a run keeps, in the shapes
inproc keeps them (a ``time_ns()`` per step, the event, the compact step record in the trace's
tape), cross-checked to be as many as the framework's; floor/hand says how much of the ratio any
backend that keeps this trace in pure Python must pay. *read*: what reading the trace afterwards
costs (the first ``pipe.trace.raw_steps`` expands the compact records into events and step records).

    .venv/bin/python benchmarks/step_overhead.py                  # the four default chains, < 2 min
    .venv/bin/python benchmarks/step_overhead.py --chains typed-trigger-10 --duration 10 --repeats 9
    .venv/bin/python benchmarks/step_overhead.py --no-gc          # diagnostic: how much is the cyclic GC
"""

from __future__ import annotations

import argparse
import datetime
import gc
import os
import platform
import statistics
import sys
import time
from dataclasses import dataclass
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # run from a checkout without installing

from retriever import Flow, Latest, Pipeline, Rate, Trigger, io  # noqa: E402
from retriever.backends import inproc_ticks  # noqa: E402
from retriever.time import seconds_to_ns  # noqa: E402

TARGET_STEPS_PER_S = 500_000  # typed chains
TARGET_RATIO = {"typed": 3.0, "untyped": 5.0}
DEFAULT_CHAINS = "typed-rate-5,untyped-rate-5,typed-rate-10,typed-trigger-10"


# ---------------------------------------------------------------------------------------------
# Trivial flows
# ---------------------------------------------------------------------------------------------
@io
@dataclass
class Num:
    x: int


class TypedSource(Flow[None, Num]):
    def __init__(self):
        self.k = 0

    def step(self) -> Num:
        self.k += 1
        return Num(x=self.k)


class TypedStage(Flow[Num, Num]):
    def step(self, inp: Num) -> Num:
        return Num(x=inp.x + 1)


class UntypedSource(Flow):
    def __init__(self):
        self.k = 0

    def step(self):
        self.k += 1
        return {"x": self.k}


class UntypedStage(Flow):
    def step(self, x):
        return {"x": x + 1}


VARIANTS = {"typed": (TypedSource, TypedStage), "untyped": (UntypedSource, UntypedStage)}
CLOCKS = ("rate", "trigger")


@dataclass(frozen=True)
class Chain:
    variant: str
    clock: str
    flows: int

    @classmethod
    def parse(cls, name: str) -> "Chain":
        try:
            variant, clock, flows = name.split("-")
            chain = cls(variant, clock, int(flows))
        except ValueError:
            raise ValueError(f"{name!r} is not VARIANT-CLOCK-FLOWS (e.g. typed-rate-5)") from None
        if variant not in VARIANTS or clock not in CLOCKS or chain.flows < 2:
            raise ValueError(f"{name!r}: VARIANT is one of {', '.join(VARIANTS)}, CLOCK one of "
                             f"{', '.join(CLOCKS)}, FLOWS at least 2")
        return chain

    def __str__(self) -> str:
        return f"{self.variant}-{self.clock}-{self.flows}"

    def names(self) -> list[str]:
        """Chain order; zero-padded so that the inproc tick order (ids sorted) is the chain order."""
        width = max(2, len(str(self.flows - 1)))
        return ["src"] + [f"s{i:0{width}d}" for i in range(1, self.flows)]


# ---------------------------------------------------------------------------------------------
# The framework run
# ---------------------------------------------------------------------------------------------
def build(chain: Chain, hz: float) -> tuple[Pipeline, list[str]]:
    src_cls, stage_cls = VARIANTS[chain.variant]
    names = chain.names()
    with Pipeline(f"step_overhead_{chain}".replace("-", "_")) as pipe:
        prev = src_cls().named(names[0]) @ Rate(hz)
        for name in names[1:]:
            clock = Rate(hz) if chain.clock == "rate" else Trigger()
            prev = prev.then(stage_cls().named(name) @ clock, sync=Latest())
    return pipe, names


def run_framework(chain: Chain, hz: float, duration: float, cold: bool = False):
    """Time ``pipe.run(duration)`` on a session opened beforehand; also the open itself (compile
    the graph, wire it, generate the ticks: ``cold``, with no code of an earlier session at hand)."""
    pipe, names = build(chain, hz)
    if cold:
        inproc_ticks.clear_compiled_ticks()
    t0 = time.perf_counter()
    pipe.step(0.0)  # open the session outside the timed region
    opened = time.perf_counter() - t0
    gc.collect()
    t0 = time.perf_counter()
    pipe.run(duration=duration)
    elapsed = time.perf_counter() - t0
    trace = pipe.trace
    t0 = time.perf_counter()
    records = (len(trace.raw_events), len(trace.raw_steps))  # the first read expands the tape
    read = time.perf_counter() - t0
    stats = pipe.stats()
    last = {}
    for ev in trace.events:  # execution order: the last one per node is its newest (port x)
        last[ev.node] = ev.value
    calls = {n: stats[n].steps for n in names}
    pipe.reset()
    return elapsed, read, opened, calls, last, records


# ---------------------------------------------------------------------------------------------
# The hand-written loops: the same step() calls, no framework
# ---------------------------------------------------------------------------------------------
def n_ticks(hz: float, duration: float) -> int:
    """Ticks of Rate(hz) with t < duration, from the framework's own (exact) tick times."""
    return Rate(hz).first_tick_at_or_after(seconds_to_ns(duration))


def hand_typed_rate(src, stages, ticks):
    """Per tick, in chain order: the source, then each stage with Latest's value (the upstream's
    output of an earlier tick; MISSING → no call). Returns each node's last output."""
    n = len(stages)
    visible = [None] * n  # visible[i]: newest x stage i can see (its upstream's, from earlier ticks)
    src_step = src.step
    steps = [s.step for s in stages]
    rng = range(n)
    for _ in range(ticks):
        new = src_step().x
        for i in rng:
            v = visible[i]
            visible[i] = new  # visible from the next tick on (tag (t, 1) > (t, 0)); None only
            # while warming up, when visible[i] is still None anyway
            if v is None:
                new = None  # skipped: no step call, no output
                continue
            new = steps[i](Num(x=v)).x
    return [*visible, new]


def hand_untyped_rate(src, stages, ticks):
    n = len(stages)
    visible = [None] * n
    src_step = src.step
    steps = [s.step for s in stages]
    rng = range(n)
    for _ in range(ticks):
        new = src_step()["x"]
        for i in rng:
            v = visible[i]
            visible[i] = new
            if v is None:
                new = None
                continue
            new = steps[i](x=v)["x"]
    return [*visible, new]


def hand_typed_trigger(src, stages, ticks):
    """Per tick: the source, then each stage, one microstep after its upstream, with Latest's
    value: its upstream's output of this tick. Returns each node's last output."""
    outs = [None] * (len(stages) + 1)
    src_step = src.step
    steps = list(enumerate([s.step for s in stages], 1))
    for _ in range(ticks):
        outs[0] = new = src_step().x
        for i, step in steps:
            outs[i] = new = step(Num(x=new)).x
    return outs


def hand_untyped_trigger(src, stages, ticks):
    outs = [None] * (len(stages) + 1)
    src_step = src.step
    steps = list(enumerate([s.step for s in stages], 1))
    for _ in range(ticks):
        outs[0] = new = src_step()["x"]
        for i, step in steps:
            outs[i] = new = step(x=new)["x"]
    return outs


HAND = {("typed", "rate"): hand_typed_rate, ("untyped", "rate"): hand_untyped_rate,
        ("typed", "trigger"): hand_typed_trigger, ("untyped", "trigger"): hand_untyped_trigger}


def expected_calls(chain: Chain, ticks: int) -> list[int]:
    """Step calls per flow: in a rate chain stage i is skipped on its first i ticks, as the
    framework skips them (Latest finds nothing yet); a trigger chain steps every flow every tick."""
    if chain.clock == "trigger":
        return [ticks] * chain.flows
    return [max(0, ticks - i) for i in range(chain.flows)]


def run_hand(chain: Chain, hz: float, duration: float):
    src_cls, stage_cls = VARIANTS[chain.variant]
    src, stages = src_cls(), [stage_cls() for _ in range(chain.flows - 1)]
    ticks = n_ticks(hz, duration)
    gc.collect()
    t0 = time.perf_counter()
    outs = HAND[chain.variant, chain.clock](src, stages, ticks)
    elapsed = time.perf_counter() - t0
    names = chain.names()
    return elapsed, dict(zip(names, expected_calls(chain, ticks))), dict(zip(names, outs))


def floor_loop(chain: Chain, src, stages, ticks, period_ns):
    """The hand loop plus only what every step of a run leaves in its trace, in the shapes inproc
    records them: a ``time_ns()`` read per step (each step of a tick starts when the one before it
    ended, as in inproc's fused rate groups and Trigger chains, plus one read per tick), the event
    (the consumer's buffer entry too), and the compact step record in the tape (a Trigger chain's
    link's the short one, without what the record before it says); a skipped tick's step record.
    No scheduling, no sync policies, no dispatch. Returns (events, step records)."""
    tape = []
    add = tape.extend
    n = len(stages)
    typed, rate = chain.variant == "typed", chain.clock == "rate"
    visible: list = [None] * n  # stage i's input: the newest event it sees
    seqs = [0] * (n + 1)
    src_step = src.step
    fns = [s.step for s in stages]
    skips = 0
    for k in range(ticks):
        tau = (k * period_ns, 0)
        out_tag = (tau[0], 1)
        start = time.time_ns()
        raw = src_step()
        end = time.time_ns()  # (the next step of the tick starts at it)
        v = raw.x if typed else raw["x"]
        seq = seqs[0]
        seqs[0] = seq + 1
        new = (out_tag, "src", "x", seq, v, end)
        add((floor_loop, tau, start, end, v, seq))
        for i in range(n):
            if rate:
                entry = visible[i]
                visible[i] = new
                if entry is None:
                    skips += 1
                    new = None
                    continue
            else:
                entry = new
                tau, out_tag = out_tag, (tau[0], out_tag[1] + 1)
            start = end
            v = fns[i](Num(x=entry[4])).x if typed else fns[i](x=entry[4])["x"]
            end = time.time_ns()
            seq = seqs[i + 1]
            seqs[i + 1] = seq + 1
            new = (out_tag, "s", "x", seq, v, end)
            if rate:
                add((floor_loop, tau, start, end, entry[3], v, seq))
            else:  # a link of a Trigger chain: its tag, start and slot are the record's before
                add((floor_loop, end, v, seq))
    return ticks * (n + 1) - skips, ticks * (n + 1)  # every tick leaves a step record, a skipped one too


def run_floor(chain: Chain, hz: float, duration: float):
    src_cls, stage_cls = VARIANTS[chain.variant]
    ticks = n_ticks(hz, duration)
    gc.collect()
    thresholds = gc.get_threshold()  # full collections held off, as InprocSession.advance does
    gc.set_threshold(thresholds[0], thresholds[1], 1 << 30)
    t0 = time.perf_counter()
    records = floor_loop(chain, src_cls(), [stage_cls() for _ in range(chain.flows - 1)], ticks, round(1e9 / hz))
    elapsed = time.perf_counter() - t0
    gc.set_threshold(*thresholds)
    return elapsed, records


# ---------------------------------------------------------------------------------------------
# Driver
# ---------------------------------------------------------------------------------------------
def measure(chain: Chain, duration: float, args) -> dict:
    """Alternate framework, floor and hand-loop runs ``repeats`` times; cross-check the calls
    and the number of trace records once."""
    fw_times, read_times, hand_times, floor_times = [], [], [], []
    # the open of a process that has compiled no ticks of this shape, in a short run of its own: an
    # untyped chain's last stage returns a port nothing consumes, and its ticks are compiled anew
    # at its first step, which a timed run should not hold (it would, in short runs, a lot)
    _, _, cold_open, *_ = run_framework(chain, args.hz, 0.1, cold=True)
    for _ in range(args.repeats):
        t, read, _, *fw, fw_records = run_framework(chain, args.hz, duration)
        fw_times.append(t)
        read_times.append(read)
        t, records = run_floor(chain, args.hz, duration)
        floor_times.append(t)
        t, *hand = run_hand(chain, args.hz, duration)
        hand_times.append(t)
    if records != fw_records:
        raise SystemExit(f"{chain}: the floor loop records (events, steps) {records}, the framework {fw_records}")
    if fw != hand:
        raise SystemExit(f"{chain}: the hand loop does not make the framework's calls:\n"
                         f"  framework (calls, last outputs) {fw}\n  hand loop (calls, last outputs) {hand}")
    steps = sum(fw[0].values())
    fw_best, fw_med = min(fw_times), statistics.median(fw_times)
    hand_best, hand_med = min(hand_times), statistics.median(hand_times)
    ratios = sorted(f / h for f, h in zip(fw_times, hand_times))  # each repeat's pair, run back to back
    return {
        "chain": chain, "duration": duration, "steps": steps,
        "fw_best": steps / fw_best, "fw_med": steps / fw_med,
        "hand_best": steps / hand_best, "hand_med": steps / hand_med,
        "ratio_best": fw_best / hand_best, "ratio_med": fw_med / hand_med,
        "ratio_lo": ratios[0], "ratio_hi": ratios[-1],
        "floor_med": statistics.median(floor_times) / hand_med,
        "us_fw": fw_med / steps * 1e6, "us_hand": hand_med / steps * 1e6,
        "us_read": statistics.median(read_times) / steps * 1e6,
        "cold_open": cold_open,
    }


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--chains", default=DEFAULT_CHAINS,
                   help=f"comma-separated VARIANT-CLOCK-FLOWS (default {DEFAULT_CHAINS})")
    p.add_argument("--hz", type=float, default=1000.0, help="rate of the source and of rate stages (default 1000)")
    p.add_argument("--duration", type=float, nargs="+", default=[10.0, 60.0], metavar="S",
                   help="virtual seconds per timed run; several values give one row each "
                        "(default 10 60: 10k and 60k ticks at 1 kHz)")
    p.add_argument("--repeats", type=int, default=5, help="timed runs per row and side (default 5)")
    p.add_argument("--no-gc", action="store_true", help="diagnostic: disable the cyclic GC during timed runs")
    p.add_argument("--profile", action="store_true",
                   help="diagnostic: instead of timing, run each chain once (first --duration) under "
                        "cProfile and print the top functions by own time")
    args = p.parse_args(argv)
    try:
        chains = [Chain.parse(c.strip()) for c in args.chains.split(",") if c.strip()]
    except ValueError as e:
        p.error(str(e))
    if not chains or args.repeats < 1 or min(args.duration) <= 0 or args.hz <= 0:
        p.error("give at least one chain; --repeats must be >= 1; --duration and --hz > 0")

    print("retriever step overhead: inproc backend vs a hand-written loop making the same step() calls")
    print(f"python {platform.python_version()} ({platform.python_implementation()}), {platform.machine()}, "
          f"{platform.system()}, {os.cpu_count()} cpus; {datetime.date.today().isoformat()}")
    print(f"chains behind one Rate({args.hz:g}) source, Latest() edges; best / median of {args.repeats} runs "
          "per row" + ("; cyclic GC disabled" if args.no_gc else ""))
    print()
    if args.profile:
        import cProfile
        import pstats

        for chain in chains:
            pipe, _ = build(chain, args.hz)
            pipe.step(0.0)
            prof = cProfile.Profile()
            prof.runcall(pipe.run, duration=args.duration[0])
            print(f"--- {chain}, {args.duration[0]:g} s virtual, under cProfile (times inflated) ---")
            pstats.Stats(prof).sort_stats("tottime").print_stats(15)
        return 0
    if args.no_gc:
        gc.disable()
    rows = [measure(c, d, args) for d in args.duration for c in chains]
    if args.no_gc:
        gc.enable()

    head = (f"{'chain':<18} {'virtual':>7} {'steps':>7} │ {'inproc steps/s':>19} │ {'hand loop steps/s':>21} │ "
            f"{'inproc/hand':>17} │ {'floor':>5} │ {'µs/step (med)':>20} │ {'open':>4} │ target")
    sub = (f"{'':<18} {'':>7} {'per run':>7} │ {'best':>9} {'median':>9} │ {'best':>10} {'median':>10} │ "
           f"{'med':>5} {'range':>11} │ {'/hand':>5} │ {'inproc':>6} {'hand':>6} {'read':>6} │ {'ms':>4} │")
    print(head)
    print(sub)
    print("─" * len(head))
    met = dict.fromkeys(map(str, chains), True)
    for r in rows:
        chain = r["chain"]
        ok = r["ratio_med"] <= TARGET_RATIO[chain.variant]
        if chain.variant == "typed":
            ok &= r["fw_med"] >= TARGET_STEPS_PER_S
        met[str(chain)] &= ok
        spread = f"{r['ratio_lo']:.1f}–{r['ratio_hi']:.1f}×"
        print(f"{str(chain):<18} {r['duration']:>6g}s {r['steps']:>7,} │ {r['fw_best']:>9,.0f} {r['fw_med']:>9,.0f} │ "
              f"{r['hand_best']:>10,.0f} {r['hand_med']:>10,.0f} │ {r['ratio_med']:>4.2f}× {spread:>11} │ "
              f"{r['floor_med']:>4.1f}× │ {r['us_fw']:>6.2f} {r['us_hand']:>6.2f} {r['us_read']:>6.2f} │ "
              f"{r['cold_open'] * 1e3:>4.1f} │ {'met' if ok else 'MISSED'}")
    print()
    print("inproc/hand: median run time over median run time; range: lowest and highest of the repeats' pairs.\n"
          "floor/hand: the hand loop plus only the records a run keeps (a time_ns() per step, the event, the\n"
          "compact step record), median runs. read: the first read of the trace after the run (expanding it).\n"
          "open: opening the session (compile the graph, wire it, generate and compile the ticks), the first run\n"
          "of a row, in a process that has compiled no ticks of that shape: what a new user's first run adds.")
    verdicts = ", ".join(f"{c} {'met' if ok else 'NOT met'}" for c, ok in met.items())
    print(f"targets, judged on medians: typed >= {TARGET_STEPS_PER_S:,} steps/s and <= {TARGET_RATIO['typed']:g}x "
          f"the hand loop, untyped <= {TARGET_RATIO['untyped']:g}x -> {verdicts}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
