"""Ticks/s and end-to-end latency as the graph grows (issue 22 §4): 10, 50, 200 flows, in-process
and on Zenoh. (``scale.py`` measures startup, CPU and memory of a Zenoh fan; this one what a
graph of N flows does per second, and how long a source's event takes to reach its end.)

Shapes (flows in ``zenoh_flows.py``; every flow passes the source's count on):

- ``chain``: ``src = Counter() @ Rate(hz)`` → ``s0`` → ``s1`` → … → ``s{N-2}``, each
  ``Keep() @ Trigger("count")`` over ``Latest()``: N flows, N-1 hops in a row.
- ``fan``: ``src`` → N-2 branches ``Keep() @ Trigger("count")`` → ``join = Join() @
  Trigger("count")`` over ``Queue()``: out to N-2 flows and back into one. The join's ticks wait
  for every branch's frontier (docs/realtime.md): event-time waiting at its widest.

Backends:

- ``inproc``: virtual time, as fast as it goes. ``pipe.run(duration)`` over enough virtual time
  for about ``--inproc-steps`` steps (the session opened first, outside the clock). ticks/s = the
  run's step records / its wall seconds.
- ``zenoh``: real time, one worker process per flow, the source at ``--hz`` for ``--duration`` s.
  Each run is a fresh process (this script with ``--one``), started in a process group of its own
  and killed with it after ``--timeout`` s. ticks/s = the run's step records / ``--duration``
  (the clocks fix it when every flow keeps up: the table says whether they did).

End-to-end latency, both backends: for each source event (count ``k``), the wall time its source
published it (``Event.publish_ns``) to the wall time the step of the last flow that consumed it
started (``StepRecord.wall_start_ns``): the last stage's step that took the copy carrying ``k``
(chain), or the join's step that took the last of the N-2 copies (fan). In-process that is the
scheduler's work over the hops (no transport, no waiting); on Zenoh, the hops through processes.
The first ``--warmup`` source events of a run are dropped. Per run: median, p10, p90; the table
gives the median over repeats of each, with the [min–max] of the runs' medians.

    .venv/bin/python benchmarks/scale_latency.py                 # 10 50 200 flows, 3 repeats, ~15 min
    .venv/bin/python benchmarks/scale_latency.py --quick         # a few flows, one repeat, ~10 s
    .venv/bin/python benchmarks/scale_latency.py --backends inproc --flows 10 50 200 500
"""

from __future__ import annotations

import argparse
import csv
import datetime
import json
import os
import platform
import shutil
import signal
import statistics
import subprocess
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent))  # run from a checkout without installing
sys.path.insert(0, str(HERE))  # zenoh_flows: the workers get this path from the coordinator

from latency import quantile  # noqa: E402  (the same percentiles as the latency benchmark)

OUT = HERE / "scale_results"
SHAPES = ("chain", "fan")
EARLY_NS = 100_000_000  # zenoh: "complete_early" counts the source events published this long before the end
FIELDS = ("backend", "shape", "flows", "repeat", "hz", "duration_s", "wall_s", "run_s", "steps", "ticks_per_s",
          "src_ticks", "src_due", "complete", "complete_early", "overrun", "incomplete", "late", "lat_n", "lat_p10_us",
          "lat_p50_us", "lat_p90_us", "load_1min", "error")


def loadavg() -> str:
    return " ".join(f"{x:.2f}" for x in os.getloadavg())


# ---------------------------------------------------------------------------------------------
# The graphs, and the latency read from a run's trace (determinism_cost.py uses both)
# ---------------------------------------------------------------------------------------------
def build(shape: str, flows: int, hz: float, **pipeline):
    """``flows`` flows in ``shape``; returns (pipe, the last flow's id, copies of an event it takes)."""
    from zenoh_flows import Counter, Join, Keep

    from retriever import Latest, Pipeline, Queue, Rate, Trigger

    if shape == "chain" and flows < 2 or shape == "fan" and flows < 3:
        raise SystemExit(f"a {shape} needs at least {2 if shape == 'chain' else 3} flows, not {flows}")
    with Pipeline(f"{shape}{flows}", **pipeline) as pipe:
        src = Counter().named("src") @ Rate(hz=hz)
        if shape == "chain":
            prev = src
            for i in range(flows - 1):
                prev = prev.then(Keep().named(f"s{i}") @ Trigger("count"), sync=Latest())
            return pipe, f"s{flows - 2}", 1
        join = Join().named("join") @ Trigger("count")
        for i in range(flows - 2):
            src.then(Keep().named(f"b{i}") @ Trigger("count"), sync=Latest()).then(join, sync=Queue(maxsize=1 << 16))
    return pipe, "join", flows - 2


def e2e_latency_ns(trace, source: str, last: str, copies: int, warmup: int = 0,
                   before_ns: int | None = None) -> tuple[list[int], int]:
    """Per source event (in seq order, the first ``warmup`` dropped; with ``before_ns``, only those
    whose tag time is below it): the wall time from its publication (``publish_ns``) to the start
    (``wall_start_ns``) of the step of ``last`` that consumed the last of its ``copies`` (events
    whose value is the source's value, the count); and how many of those source events there were."""
    value = {(ev.node, ev.port, ev.seq): ev.value for ev in trace.events}
    published = {ev.value: ev.publish_ns for ev in trace.events
                 if ev.node == source and (before_ns is None or ev.tag[0] < before_ns)}
    kept = sorted(published)[warmup:]
    got: dict = {}  # count -> [copies consumed, the latest consuming step's wall start]
    for st in trace.steps_of(last):
        for ids in st.consumed.values():
            for eid in ids:
                seen = got.setdefault(value[eid], [0, 0])
                seen[0] += 1
                seen[1] = max(seen[1], st.wall_start_ns)
    return [got[k][1] - published[k] for k in kept if k in got and got[k][0] >= copies], len(kept)


def percentiles_us(lat_ns: list[int]) -> tuple[float, float, float]:
    s = sorted(lat_ns)
    return tuple(quantile(s, q) / 1e3 for q in (0.1, 0.5, 0.9))


# ---------------------------------------------------------------------------------------------
# One run
# ---------------------------------------------------------------------------------------------
def run_inproc(shape: str, flows: int, hz: float, steps: int, warmup: int) -> dict:
    pipe, last, copies = build(shape, flows, hz)
    per_tick = flows if shape == "chain" else flows - 1  # steps per source tick (the join steps once)
    ticks = max(warmup + 5, -(-steps // per_tick))
    duration = ticks / hz
    pipe.step(0.0)  # open the session outside the timed region (no tick has t < 0)
    t0 = time.perf_counter()
    trace = pipe.run(duration=duration)
    wall = time.perf_counter() - t0
    lat, considered = e2e_latency_ns(trace, "src", last, copies, warmup)
    src_ticks = len(trace.steps_of("src"))
    pipe.reset()
    return {"duration_s": duration, "wall_s": wall, "run_s": wall, "steps": len(trace.steps),
            "ticks_per_s": len(trace.steps) / wall, "src_ticks": src_ticks, "src_due": ticks,
            "complete": len(lat) / max(1, considered), "complete_early": len(lat) / max(1, considered),
            "overrun": 0, "incomplete": 0, "late": 0, "lat": lat}


def run_zenoh(shape: str, flows: int, hz: float, duration: float, warmup: int, startup_timeout: float,
              log: str | None = None, **pipeline) -> dict:
    """In this process: one run on the zenoh backend. Prints the run's directory to stderr first
    (so that whoever started this process can remove it if it has to kill it)."""
    from retriever.backends.zenoh.coordinator import _ticks_due

    pipe, last, copies = build(shape, flows, hz, **pipeline)
    begin = time.monotonic()
    session = pipe.open("zenoh", quiet=True, startup_timeout=startup_timeout)
    print(f"RUNDIR {session._dir}", file=sys.stderr, flush=True)
    trace = pipe.run(duration=duration, backend="zenoh", log=log, overwrite=True)
    run_s = time.monotonic() - begin
    counts = dict(pipe.counts())
    lat, considered = e2e_latency_ns(trace, "src", last, copies, warmup)
    # the source's events published at least EARLY_NS before the end: these have time to reach the
    # last flow (the last ones' hops may be due past the end, and never run)
    early, early_n = e2e_latency_ns(trace, "src", last, copies, 0, before_ns=round(duration * 1e9) - EARLY_NS)
    src_ticks = len(trace.steps_of("src"))
    due = _ticks_due(session.graph.nodes["src"].clock, round(duration * 1e9))
    pipe.reset()  # closes the session: its processes, zenoh sessions and run directory
    return {"duration_s": duration, "wall_s": duration, "run_s": run_s, "steps": len(trace.steps),
            "ticks_per_s": len(trace.steps) / duration, "src_ticks": src_ticks, "src_due": due,
            "complete": len(lat) / max(1, considered), "complete_early": len(early) / max(1, early_n),
            "overrun": counts.get("overrun", 0),
            "incomplete": counts.get("incomplete", 0), "late": counts.get("late", 0), "lat": lat}


def in_fresh_process(argv: list[str], timeout: float, script: str = __file__) -> dict:
    """Run ``script`` (this one by default) with ``argv`` (``--one ...``) in a new process group;
    its last stdout line is the run's JSON. On timeout the group is killed (by its id) and the
    run's directory removed."""
    cmd = [sys.executable, str(Path(script).resolve()), *argv]
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True,
                            env={**os.environ, "PYTHONUNBUFFERED": "1"})
    try:
        out, err = proc.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        out, err = proc.communicate()
        _remove_run_dirs(err)
        return {"error": f"did not finish in {timeout:g} s (killed); stderr: {_tail(err)}"}
    if proc.returncode != 0:
        _remove_run_dirs(err)
        return {"error": f"exit {proc.returncode}: {_tail(err)}"}
    return json.loads(out.strip().splitlines()[-1])


def _tail(err: str) -> str:
    lines = [ln for ln in err.strip().splitlines() if not ln.startswith("RUNDIR ")]
    return " | ".join(lines[-6:])[-1500:]


def _remove_run_dirs(err: str) -> None:
    for line in err.splitlines():
        if line.startswith("RUNDIR "):
            path = Path(line[len("RUNDIR "):].strip())
            if path.name.startswith("retriever-run-"):
                shutil.rmtree(path, ignore_errors=True)


# ---------------------------------------------------------------------------------------------
# Tables and plot
# ---------------------------------------------------------------------------------------------
def med_range(values: list[float], fmt: str = "{:,.0f}") -> str:
    if not values:
        return "-"
    return f"{fmt.format(statistics.median(values))} [{fmt.format(min(values))}–{fmt.format(max(values))}]"


def print_table(rows: list[dict], keys: list[tuple]) -> None:
    head = (f"{'backend':<7} {'shape':<5} {'flows':>5} │ {'runs':>4} │ {'ticks/s, median [min–max]':>27} │ "
            f"{'e2e latency µs: p50 [min–max]':>30} {'p10':>8} {'p90':>8} │ {'src ticks':>9} {'reached':>7} │ "
            f"{'overrun incompl late':>20}")
    print(head)
    print("─" * len(head))
    for backend, shape, flows in keys:
        mine = [r for r in rows if (r["backend"], r["shape"], r["flows"]) == (backend, shape, flows)]
        ok = [r for r in mine if not r["error"]]
        fails = len(mine) - len(ok)
        if not ok:
            print(f"{backend:<7} {shape:<5} {flows:>5} │ {0:>2}/{len(mine)} │ "
                  f"every run failed: {mine[0]['error'][:160]}")
            continue
        lat_fmt = "{:,.1f}" if backend == "inproc" else "{:,.0f}"
        src = statistics.median(r["src_ticks"] / r["src_due"] for r in ok)
        reached = statistics.median(r["complete"] for r in ok)
        bad = "/".join(str(sum(r[k] for r in ok)) for k in ("overrun", "incomplete", "late"))
        print(f"{backend:<7} {shape:<5} {flows:>5} │ {len(ok):>2}/{len(mine)} │ "
              f"{med_range([r['ticks_per_s'] for r in ok]):>27} │ "
              f"{med_range([r['lat_p50_us'] for r in ok], lat_fmt):>30} "
              f"{lat_fmt.format(statistics.median(r['lat_p10_us'] for r in ok)):>8} "
              f"{lat_fmt.format(statistics.median(r['lat_p90_us'] for r in ok)):>8} │ {src:>8.1%} {reached:>7.1%} │ "
              f"{bad:>20}" + (f"   ({fails} failed)" if fails else ""))


def plot(rows: list[dict], path: Path, title: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(12, 4.6))
    styles = {("inproc", "chain"): ("C0", "o-"), ("inproc", "fan"): ("C0", "s--"),
              ("zenoh", "chain"): ("C3", "o-"), ("zenoh", "fan"): ("C3", "s--")}
    failed = []
    for (backend, shape), (color, style) in styles.items():
        mine = [r for r in rows if r["backend"] == backend and r["shape"] == shape]
        flows = sorted({r["flows"] for r in mine})
        xs, tps, tlo, thi, p50, p10, p90 = [], [], [], [], [], [], []
        for n in flows:
            ok = [r for r in mine if r["flows"] == n and not r["error"]]
            if not ok:
                failed.append(f"{backend} {shape} {n}")
                continue
            t = [r["ticks_per_s"] for r in ok]
            xs.append(n)
            tps.append(statistics.median(t))
            tlo.append(tps[-1] - min(t))
            thi.append(max(t) - tps[-1])
            p50.append(statistics.median(r["lat_p50_us"] for r in ok) / 1e3)
            p10.append(statistics.median(r["lat_p10_us"] for r in ok) / 1e3)
            p90.append(statistics.median(r["lat_p90_us"] for r in ok) / 1e3)
        if not xs:
            continue
        label = f"{backend} {shape}"
        ax1.errorbar(xs, tps, yerr=[tlo, thi], fmt=style, color=color, label=label, capsize=3)
        ax2.errorbar(xs, p50, yerr=[[a - b for a, b in zip(p50, p10)], [b - a for a, b in zip(p50, p90)]],
                     fmt=style, color=color, label=label, capsize=3)
    for ax in (ax1, ax2):
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlabel("flows (N)")
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=8)
    ax1.set_ylabel("ticks/s (steps per wall second)\nmedian, bars: min–max of runs")
    ax2.set_ylabel("end-to-end latency, ms\nmedian, bars: p10–p90")
    ax1.set_title("throughput: inproc as fast as it goes; zenoh at a fixed rate", fontsize=9)
    ax2.set_title("source event published → last flow's step that consumed it", fontsize=9)
    if failed:
        ax1.text(0.02, 0.02, "failed: " + ", ".join(failed), transform=ax1.transAxes, fontsize=7, color="C3")
    fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


# ---------------------------------------------------------------------------------------------
# Driver
# ---------------------------------------------------------------------------------------------
def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--flows", type=int, nargs="+", default=[10, 50, 200], help="graph sizes (default 10 50 200)")
    p.add_argument("--zenoh-flows", type=int, nargs="+", help="graph sizes on zenoh (default: --flows)")
    p.add_argument("--shapes", default="chain,fan", help="comma-separated: chain, fan (default both)")
    p.add_argument("--backends", default="inproc,zenoh", help="comma-separated: inproc, zenoh (default both)")
    p.add_argument("--repeats", type=int, default=3, help="runs per point (default 3)")
    p.add_argument("--hz", type=float, default=10.0, help="the source's rate (default 10; virtual on inproc)")
    p.add_argument("--duration", type=float, default=5.0, help="zenoh: seconds of ticking per run (default 5)")
    p.add_argument("--inproc-steps", type=int, default=30000, help="inproc: steps per run, about (default 30000)")
    p.add_argument("--warmup", type=int, default=5, help="first source events of a run not measured (default 5)")
    p.add_argument("--timeout", type=float, default=420.0, help="zenoh: a run killed after this many s (default 420)")
    p.add_argument("--startup-timeout", type=float, default=300.0,
                   help="zenoh: the coordinator's wait for its workers (default 300; the backend's own is 60)")
    p.add_argument("--out", type=Path, default=OUT, help=f"directory for the CSV and PNG (default {OUT})")
    p.add_argument("--quick", action="store_true",
                   help="a smoke run: 4 and 8 flows in-process, 4 on zenoh, 1 repeat of 1 s, 2000 steps")
    p.add_argument("--one", nargs=4, metavar=("SHAPE", "FLOWS", "REPEAT", "_"), help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if args.one:
        shape, flows = args.one[0], int(args.one[1])
        r = run_zenoh(shape, flows, args.hz, args.duration, args.warmup, args.startup_timeout)
        print(json.dumps(r))
        return 0
    if args.quick:
        args.flows, args.zenoh_flows, args.repeats, args.duration = [4, 8], [4], 1, 1.0
        args.inproc_steps, args.warmup, args.hz = 2000, 2, 20.0
    shapes = [s for s in args.shapes.split(",") if s]
    backends = [b for b in args.backends.split(",") if b]
    zenoh_flows = args.zenoh_flows or args.flows
    args.out.mkdir(parents=True, exist_ok=True)

    from importlib.metadata import version

    load_start = loadavg()
    print("retriever scale: ticks/s and end-to-end latency vs flows; "
          f"python {platform.python_version()}, {os.cpu_count()} cpus, eclipse-zenoh {version('eclipse-zenoh')}; "
          f"{datetime.datetime.now().isoformat(timespec='seconds')}; load average at start {load_start}", flush=True)
    print(f"source @ {args.hz:g} Hz; inproc ~{args.inproc_steps} steps per run; zenoh {args.duration:g} s per run; "
          f"{args.repeats} repeats; first {args.warmup} source events dropped", flush=True)
    rows, keys = [], []
    for backend in backends:
        for shape in shapes:
            for flows in (args.flows if backend == "inproc" else zenoh_flows):
                keys.append((backend, shape, flows))
                for rep in range(args.repeats):
                    load = os.getloadavg()[0]
                    t = time.monotonic()
                    if backend == "inproc":
                        r = run_inproc(shape, flows, args.hz, args.inproc_steps, args.warmup)
                    else:
                        r = in_fresh_process(["--one", shape, str(flows), str(rep), "-", "--hz", str(args.hz),
                                              "--duration", str(args.duration), "--warmup", str(args.warmup),
                                              "--startup-timeout", str(args.startup_timeout)], args.timeout)
                    row = {k: "" for k in FIELDS} | {"backend": backend, "shape": shape, "flows": flows,
                                                     "repeat": rep + 1, "hz": args.hz, "load_1min": load}
                    if "error" in r:
                        row["error"] = r["error"]
                        print(f"  {backend} {shape} {flows} flows, run {rep + 1}: FAILED after "
                              f"{time.monotonic() - t:.0f} s: {r['error'][:300]}", flush=True)
                        rows.append(row)
                        break  # the next repeats of this size would fail the same way, as slowly
                    lat = r.pop("lat")
                    p10, p50, p90 = percentiles_us(lat)
                    row |= {k: v for k, v in r.items() if k in row} | {
                        "lat_n": len(lat), "lat_p10_us": p10, "lat_p50_us": p50, "lat_p90_us": p90}
                    rows.append(row)
                    print(f"  {backend} {shape} {flows:>3} flows, run {rep + 1}: {r['ticks_per_s']:,.0f} ticks/s, "
                          f"latency p50 {p50:,.1f} µs (n={len(lat)}), src {r['src_ticks']}/{r['src_due']}, "
                          f"{time.monotonic() - t:.1f} s", flush=True)
    load_end = loadavg()
    csv_path, png_path = args.out / "scale_latency.csv", args.out / "scale_latency.png"
    with open(csv_path, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=FIELDS)
        w.writeheader()
        w.writerows(rows)
    print()
    print_table(rows, keys)
    print()
    print("ticks/s: inproc = steps / wall s (virtual time, as fast as it goes); zenoh = steps / s at the fixed rate")
    print("latency: source event publish_ns → wall_start_ns of the last flow's step that consumed it (fan: its last")
    print("copy); per run p10/p50/p90, median over runs. src ticks = source ticks run / due; reached = source events")
    print("whose every copy reached the last flow; overrun/incompl/late = the runtime's counters, summed over runs.")
    print(f"load average at start {load_start}, at end {load_end}; rows in {csv_path}, plot in {png_path}")
    plot(rows, png_path, f"{args.repeats} runs per point; source {args.hz:g} Hz; {os.cpu_count()} cpus; load "
                         f"{load_start.split()[0]} → {load_end.split()[0]}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
