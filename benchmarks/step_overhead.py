"""Step overhead of the in-process backend, against a hand-written loop making the same calls.

A chain of trivial flows, all on one ``Rate(hz)``, wired with ``Latest()`` edges:

    src @ Rate ──x──▶ s01 @ Rate ──x──▶ s02 @ Rate ──x──▶ … ──x──▶ sNN @ Rate

Two variants of the same chain:

- ``typed``:   ``Flow[None, Num]`` / ``Flow[Num, Num]`` with an ``@io`` dataclass ``Num(x)``;
- ``untyped``: ``step(self)`` / ``step(self, x)`` returning ``{"x": ...}``.

For each variant the script times ``pipe.run(duration)`` on the ``inproc`` backend (the session is
opened before the clock starts) and a hand-written loop that makes **exactly the same** ``step``
calls on fresh instances of the same flow classes, in the same per-tick order (the inproc order:
node ids sorted), passing each stage what ``Latest()`` gives it at that tick (the upstream output
of the previous tick; nothing at the start, where the framework skips the tick) — for the typed
variant including the ``Num(x=...)`` input construction. No framework code runs in the loop. Both
runs are cross-checked: same number of step calls per flow, same last output per flow.

"steps" are ``step()`` calls (skipped ticks are not counted; stage ``i`` is skipped on its first
``i`` ticks only). The framework side includes everything a run does per step — scheduling, sync,
the step record and events it keeps in ``pipe.trace`` — so its cost depends on the run length
(the trace, and the cyclic GC's work over it, grow with it): each ``--duration`` is one row.
Targets (measured, not asserted; judged on medians): ≥ 100k steps/s and ≤ 5× the hand loop.

A third side, the *floor*, is the hand loop plus only the trace records a run keeps (two
``time_ns()`` per step, the event tuple, the step record with its consumed ids), in inproc's
shapes, cross-checked to be as many as the framework's. No pure-Python backend that keeps this
trace can be faster, so floor/hand says how much of the ratio any such backend must pay.

    .venv/bin/python benchmarks/step_overhead.py                  # defaults: 10 s and 60 s rows, < 1 min
    .venv/bin/python benchmarks/step_overhead.py --stages 8 --duration 10 --repeats 9
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

from retriever import Flow, Latest, Pipeline, Rate, io  # noqa: E402
from retriever.time import seconds_to_ns  # noqa: E402

TARGET_STEPS_PER_S = 100_000
TARGET_RATIO = 5.0


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


def node_names(stages: int) -> list[str]:
    """Chain order; zero-padded so that the inproc tick order (ids sorted) is the chain order."""
    width = max(2, len(str(stages)))
    return ["src"] + [f"s{i:0{width}d}" for i in range(1, stages + 1)]


# ---------------------------------------------------------------------------------------------
# The framework run
# ---------------------------------------------------------------------------------------------
def build(variant: str, stages: int, hz: float) -> tuple[Pipeline, list[str]]:
    src_cls, stage_cls = VARIANTS[variant]
    names = node_names(stages)
    with Pipeline(f"step_overhead_{variant}") as pipe:
        prev = src_cls().named(names[0]) @ Rate(hz)
        for name in names[1:]:
            prev = prev.then(stage_cls().named(name) @ Rate(hz), sync=Latest())
    return pipe, names


def run_framework(variant: str, stages: int, hz: float, duration: float):
    pipe, names = build(variant, stages, hz)
    pipe.step(0.0)  # open the session (compile, wire, reset flows) outside the timed region
    gc.collect()
    t0 = time.perf_counter()
    pipe.run(duration=duration)
    elapsed = time.perf_counter() - t0
    stats = pipe.stats()
    trace = pipe.trace
    last = {}
    for ev in trace.events:  # execution order: the last one per node is its newest (port x)
        last[ev.node] = ev.value
    calls = {n: stats[n].steps for n in names}
    ticks = sum(s.ticks for s in stats.values())
    result = elapsed, calls, last, ticks, (len(trace.raw_events), len(trace.raw_steps))
    pipe.reset()
    return result


# ---------------------------------------------------------------------------------------------
# The hand-written loop: the same step() calls, no framework
# ---------------------------------------------------------------------------------------------
def n_ticks(hz: float, duration: float) -> int:
    """Ticks of Rate(hz) with t < duration, from the framework's own (exact) tick times."""
    return Rate(hz).first_tick_at_or_after(seconds_to_ns(duration))


def hand_typed(src, stages, ticks):
    """Per tick, in chain order: the source, then each stage with Latest's value (the upstream's
    output of an earlier tick; MISSING → no call)."""
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
    return visible, new


def hand_untyped(src, stages, ticks):
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
    return visible, new


def floor_loop(variant, src, stages, ticks, names, period_ns):
    """The hand loop plus only what every step of a run must leave in its trace, in the shapes
    inproc records them: two ``time_ns()`` reads around the step, the event tuple, and the step
    record with its consumed ids (a record per skipped tick too). No scheduling, no sync
    policies, no dispatch: a pure-Python backend that keeps this trace cannot be cheaper."""
    events, steps = [], []
    add_event, add_step = events.append, steps.append
    n = len(stages)
    visible = [None] * n  # as in hand_typed: stage i's newest visible input
    visible_ids = [None] * n  # … and the ids tuple a Latest() selection of it consumes
    seqs = [0] * (n + 1)
    src_step = src.step
    fns = [s.step for s in stages]
    typed = variant == "typed"
    for k in range(ticks):
        tau = (k * period_ns, 0)
        out_tag = (tau[0], 1)
        start = time.time_ns()
        raw = src_step()
        end = time.time_ns()
        new = raw.x if typed else raw["x"]
        seq = seqs[0]
        seqs[0] = seq + 1
        ids = ((names[0], "x", seq),)
        add_event((out_tag, names[0], "x", seq, new, end))
        add_step((names[0], tau, {}, ids, "ok", None, start, end - start))
        for i in range(n):
            v, v_ids = visible[i], visible_ids[i]
            visible[i], visible_ids[i] = new, ids
            name = names[i + 1]
            if v is None:
                new = None
                add_step((name, tau, {}, (), "skipped", {"missing": ["x"]}, 0, 0))
                continue
            start = time.time_ns()
            new = fns[i](Num(x=v)).x if typed else fns[i](x=v)["x"]
            end = time.time_ns()
            seq = seqs[i + 1]
            seqs[i + 1] = seq + 1
            ids = ((name, "x", seq),)
            add_event((out_tag, name, "x", seq, new, end))
            add_step((name, tau, {"x": v_ids}, ids, "ok", None, start, end - start))
    return events, steps


def run_floor(variant: str, stages: int, hz: float, duration: float):
    src_cls, stage_cls = VARIANTS[variant]
    ticks = n_ticks(hz, duration)
    names = node_names(stages)
    gc.collect()
    thresholds = gc.get_threshold()  # full collections held off, as InprocSession.advance does
    gc.set_threshold(thresholds[0], thresholds[1], 1 << 30)
    t0 = time.perf_counter()
    events, steps = floor_loop(variant, src_cls(), [stage_cls() for _ in range(stages)], ticks, names,
                               round(1e9 / hz))
    elapsed = time.perf_counter() - t0
    gc.set_threshold(*thresholds)
    return elapsed, (len(events), len(steps))


def run_hand(variant: str, stages: int, hz: float, duration: float):
    src_cls, stage_cls = VARIANTS[variant]
    src, chain = src_cls(), [stage_cls() for _ in range(stages)]
    ticks = n_ticks(hz, duration)
    loop = hand_typed if variant == "typed" else hand_untyped
    gc.collect()
    t0 = time.perf_counter()
    visible, new = loop(src, chain, ticks)
    elapsed = time.perf_counter() - t0
    names = node_names(stages)
    # the hand loop's last outputs: visible[i] is node i's newest output; `new` the last stage's
    last = {names[i]: visible[i] for i in range(stages)}
    last[names[-1]] = new
    # stage i (1-based) is skipped on its first i ticks, exactly as the framework skips them
    calls = {names[0]: ticks, **{names[i]: max(0, ticks - i) for i in range(1, stages + 1)}}
    return elapsed, calls, last, ticks * (stages + 1)


# ---------------------------------------------------------------------------------------------
# Driver
# ---------------------------------------------------------------------------------------------
def measure(variant: str, duration: float, args) -> dict:
    """Alternate framework, floor and hand-loop runs ``repeats`` times; cross-check the calls
    and the number of trace records once."""
    fw_times, hand_times, floor_times = [], [], []
    fw = hand = None
    for _ in range(args.repeats):
        t, *fw = run_framework(variant, args.stages, args.hz, duration)
        fw_times.append(t)
        t, records = run_floor(variant, args.stages, args.hz, duration)
        floor_times.append(t)
        t, *hand = run_hand(variant, args.stages, args.hz, duration)
        hand_times.append(t)
    fw, fw_records = fw[:3], fw[3]
    if records != fw_records:
        raise SystemExit(f"{variant}: the floor loop records (events, steps) {records}, the framework {fw_records}")
    if fw != hand:
        raise SystemExit(f"{variant}: the hand loop does not make the framework's calls:\n"
                         f"  framework (calls, last outputs, ticks) {fw}\n  hand loop (calls, last outputs, ticks) {hand}")
    steps = sum(fw[0].values())
    fw_best, fw_med = min(fw_times), statistics.median(fw_times)
    hand_best, hand_med = min(hand_times), statistics.median(hand_times)
    return {
        "variant": variant, "duration": duration, "steps": steps,
        "fw_best": steps / fw_best, "fw_med": steps / fw_med,
        "hand_best": steps / hand_best, "hand_med": steps / hand_med,
        "ratio_best": fw_best / hand_best, "ratio_med": fw_med / hand_med,
        "floor_med": statistics.median(floor_times) / hand_med,
        "us_fw": fw_med / steps * 1e6, "us_hand": hand_med / steps * 1e6,
    }


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--stages", type=int, default=4, help="downstream flows after the source (default 4)")
    p.add_argument("--hz", type=float, default=1000.0, help="rate of every flow (default 1000)")
    p.add_argument("--duration", type=float, nargs="+", default=[10.0, 60.0], metavar="S",
                   help="virtual seconds per timed run; several values give one row each "
                        "(default 10 60: 50k and 300k steps with 4 stages at 1 kHz; the trace the run "
                        "keeps grows with it, and so does the cost of the cyclic GC)")
    p.add_argument("--repeats", type=int, default=5, help="timed runs per row and side (default 5)")
    p.add_argument("--variants", default="typed,untyped", help="comma-separated: typed, untyped")
    p.add_argument("--no-gc", action="store_true", help="diagnostic: disable the cyclic GC during timed runs")
    p.add_argument("--profile", action="store_true",
                   help="diagnostic: instead of timing, run each variant once (first --duration) under "
                        "cProfile and print the top functions by own time")
    args = p.parse_args(argv)
    variants = [v.strip() for v in args.variants.split(",") if v.strip()]
    for v in variants:
        if v not in VARIANTS:
            p.error(f"unknown variant {v!r}; choose from {', '.join(VARIANTS)}")
    if args.stages < 1 or args.repeats < 1 or min(args.duration) <= 0 or args.hz <= 0:
        p.error("--stages and --repeats must be >= 1; --duration and --hz > 0")

    print("retriever step overhead: inproc backend vs a hand-written loop making the same step() calls")
    print(f"python {platform.python_version()} ({platform.python_implementation()}), {platform.machine()}, "
          f"{platform.system()}, {os.cpu_count()} cpus; {datetime.date.today().isoformat()}")
    print(f"chain: 1 Rate source + {args.stages} stages, all @ Rate({args.hz:g}), Latest() edges; "
          f"best / median of {args.repeats} runs per row" + ("; cyclic GC disabled" if args.no_gc else ""))
    print()
    if args.profile:
        import cProfile
        import pstats

        for v in variants:
            pipe, _ = build(v, args.stages, args.hz)
            pipe.step(0.0)
            prof = cProfile.Profile()
            prof.runcall(pipe.run, duration=args.duration[0])
            print(f"--- {v}, {args.duration[0]:g} s virtual, under cProfile (times inflated) ---")
            pstats.Stats(prof).sort_stats("tottime").print_stats(15)
        return 0
    if args.no_gc:
        gc.disable()
    rows = [measure(v, d, args) for d in args.duration for v in variants]
    if args.no_gc:
        gc.enable()

    head = (f"{'variant':<8} {'virtual':>7} {'steps':>7} │ {'inproc steps/s':>19} │ {'hand loop steps/s':>21} │ "
            f"{'inproc/hand':>11} │ {'floor':>5} │ {'µs/step (med)':>13} │ ≥100k/s  ≤5×")
    sub = (f"{'':<8} {'':>7} {'per run':>7} │ {'best':>9} {'median':>9} │ {'best':>10} {'median':>10} │ "
           f"{'best':>5} {'med':>5} │ {'/hand':>5} │ {'inproc':>6} {'hand':>6} │")
    print(head)
    print(sub)
    print("─" * len(head))
    met = dict.fromkeys(variants, True)
    for r in rows:
        meets_rate = r["fw_med"] >= TARGET_STEPS_PER_S
        meets_ratio = r["ratio_med"] <= TARGET_RATIO
        met[r["variant"]] &= meets_rate and meets_ratio
        print(f"{r['variant']:<8} {r['duration']:>6g}s {r['steps']:>7,} │ {r['fw_best']:>9,.0f} {r['fw_med']:>9,.0f} │ "
              f"{r['hand_best']:>10,.0f} {r['hand_med']:>10,.0f} │ {r['ratio_best']:>4.1f}× {r['ratio_med']:>4.1f}× │ "
              f"{r['floor_med']:>4.1f}× │ "
              f"{r['us_fw']:>6.2f} {r['us_hand']:>6.2f} │ "
              f"{'yes' if meets_rate else 'NO':<7}  {'yes' if meets_ratio else 'NO'}")
    print()
    print("floor/hand = the hand loop plus only the trace records a run keeps (two time_ns() per step, the event,\n"
          "the step record): no pure-Python backend that keeps this trace can be under it (median runs)")
    verdicts = ", ".join(f"{v} {'met' if ok else 'NOT met'}" for v, ok in met.items())
    print(f"targets, judged on medians: >= {TARGET_STEPS_PER_S:,} steps/s and <= {TARGET_RATIO:g}x the hand loop "
          f"-> {verdicts}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
