"""The cost of determinism on Zenoh (issue 22 §4): latency and throughput with event-time waiting
and the event log each on and off, the four combinations, the same graph.

The graph is ``scale_latency.py``'s fan: ``src = Counter() @ Rate(hz)`` → ``--branches`` flows
``Keep() @ Trigger("count")`` → ``join = Join() @ Trigger("count")`` over ``Queue()``, one worker
process per flow. Fan-in is where event time makes a consumer wait: the join's tick at the tag of
one branch's event runs only once every other branch has promised (its frontier) that no event
with a tag at or below it is still coming, so that the tick sees exactly the events with tag ≤ τ
(docs/realtime.md). A single-input Trigger chain does not wait at all: the producer's frontier comes on
the very message that triggers the tick.

- waiting **on**: the default, ``Pipeline(deadline=0.1)``: a tick waits for its producers'
  frontiers up to 100 ms.
- waiting **off**: ``Pipeline(deadline=0.0)``: no tick ever waits for a frontier; it runs as soon
  as it is due (a Trigger tick when its event arrives) with whatever has arrived, still selected by
  tag (tag ≤ τ), and its record says which edges were incomplete. It is the same runtime, the same
  wire, stamping, step records and reports, with the waiting taken out and nothing else, which is
  what "the cost of waiting" asks. (A raw zenoh-python pub/sub program would also take out the
  encoding, the step records and the reports: that comparison is ``latency.py``/``throughput.py``.)
  Determinism goes with it: a branch's event that arrives after the join ran a later tag is late
  (counted: ``late``), and what each join tick saw depends on arrival order.
- logging **off**: ``pipe.run(..., log=None)``; **on**: ``log="<tmp>/run.mcap"`` (the coordinator
  writes every event and step record to the MCAP log as the workers report them).

Measured per combination, each run a fresh process (``scale_latency.in_fresh_process``):

- latency: the source at ``--hz`` for ``--duration`` s; per source event, the wall time from its
  publication to the start of the join's step that consumed the last of its copies
  (``scale_latency.e2e_latency_ns``); median, p10, p90 per run.
- throughput: the source at rising rates ``--rates`` (``--tp-duration`` s each) until a rate is not
  kept up; the highest kept up is the run's throughput. Kept up = the source ran every due tick
  (one short at most), no flow overran its period, and every source event but the last two reached
  the join in full. Reported also: steps/s and messages/s (events published) at that rate.

The combinations are interleaved within each repeat, so that the machine's drift (it is shared)
falls on all four alike. Medians over ``--repeats`` with [min–max] of the runs.

    .venv/bin/python benchmarks/determinism_cost.py               # 3 repeats, ~10 min
    .venv/bin/python benchmarks/determinism_cost.py --quick       # one short latency run of each, ~15 s
    .venv/bin/python benchmarks/determinism_cost.py --branches 8 --rates 50 100 200 400
"""

from __future__ import annotations

import argparse
import csv
import datetime
import json
import os
import platform
import statistics
import sys
import tempfile
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent))  # run from a checkout without installing
sys.path.insert(0, str(HERE))  # zenoh_flows: the workers get this path from the coordinator

from scale_latency import in_fresh_process, loadavg, med_range, percentiles_us, run_zenoh  # noqa: E402

OUT = HERE / "determinism_cost_results"
COMBOS = [("on", "off"), ("off", "off"), ("on", "on"), ("off", "on")]  # (waiting, logging)
FIELDS = ("kind", "waiting", "logging", "repeat", "hz", "duration_s", "steps", "steps_per_s", "msgs_per_s",
          "src_ticks", "src_due", "complete", "complete_early", "overrun", "incomplete", "late", "kept_up", "lat_n",
          "lat_p10_us", "lat_p50_us", "lat_p90_us", "load_1min", "error")


def one(waiting: str, logging: str, branches: int, hz: float, duration: float, warmup: int,
        startup_timeout: float) -> dict:
    """In this process: one run of the fan on zenoh with the given switches."""
    with tempfile.TemporaryDirectory(prefix="retriever-detcost-") as tmp:
        log = str(Path(tmp) / "run.mcap") if logging == "on" else None
        r = run_zenoh("fan", branches + 2, hz, duration, warmup, startup_timeout, log=log,
                      deadline=0.1 if waiting == "on" else 0.0)
        if log is not None:
            r["log_bytes"] = Path(log).stat().st_size
    return r


def kept_up(r: dict) -> bool:
    return r["src_ticks"] >= r["src_due"] - 1 and not r["overrun"] and r["complete_early"] == 1.0


def measure(waiting: str, logging: str, branches: int, hz: float, duration: float, warmup: int, args) -> dict:
    return in_fresh_process(["--one", waiting, logging, str(branches), "--hz", str(hz), "--duration", str(duration),
                             "--warmup", str(warmup), "--startup-timeout", str(args.startup_timeout)],
                            args.timeout, script=__file__)


def row_of(kind: str, waiting: str, logging: str, rep: int, hz: float, r: dict, branches: int) -> dict:
    row = {k: "" for k in FIELDS} | {"kind": kind, "waiting": waiting, "logging": logging, "repeat": rep + 1,
                                     "hz": hz, "load_1min": os.getloadavg()[0]}
    if "error" in r:
        return row | {"error": r["error"]}
    lat = r.pop("lat")
    p10, p50, p90 = percentiles_us(lat)
    # events published: the source's, one per branch per source tick; per second of the run
    msgs = r["src_ticks"] * (1 + branches) / r["duration_s"]
    return row | {k: v for k, v in r.items() if k in row} | {
        "steps_per_s": r["steps"] / r["duration_s"], "msgs_per_s": msgs, "kept_up": kept_up(r),
        "lat_n": len(lat), "lat_p10_us": p10, "lat_p50_us": p50, "lat_p90_us": p90}


def plot(lat_rows: list[dict], best: dict, path: Path, title: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(11, 4.4))
    labels = [f"wait {w}\nlog {g}" for w, g in COMBOS]
    for i, (w, g) in enumerate(COMBOS):
        ok = [r for r in lat_rows if (r["waiting"], r["logging"]) == (w, g) and not r["error"]]
        if not ok:
            continue
        p50 = [r["lat_p50_us"] / 1e3 for r in ok]
        m = statistics.median(p50)
        p10 = statistics.median(r["lat_p10_us"] for r in ok) / 1e3
        p90 = statistics.median(r["lat_p90_us"] for r in ok) / 1e3
        ax1.errorbar([i], [m], yerr=[[m - p10], [p90 - m]], fmt="o", color=f"C{i}", capsize=4)
        ax1.plot([i] * len(p50), p50, "x", color=f"C{i}", alpha=0.6)
        rates = best.get((w, g), [])
        if rates:
            ax2.bar([i], [statistics.median(rates)], color=f"C{i}", alpha=0.7)
            ax2.plot([i] * len(rates), rates, "k_", markersize=14)
    for ax in (ax1, ax2):
        ax.set_xticks(range(len(COMBOS)))
        ax.set_xticklabels(labels, fontsize=8)
        ax.grid(True, axis="y", alpha=0.3)
    ax1.set_ylabel("end-to-end latency, ms\n(dot: median of runs, bars: p10–p90, x: each run's median)")
    ax2.set_ylabel("highest source rate kept up, Hz\n(bar: median of runs, dashes: each run)")
    fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--branches", type=int, default=4, help="flows between source and join (default 4: 6 flows)")
    p.add_argument("--hz", type=float, default=50.0, help="latency runs: the source's rate (default 50)")
    p.add_argument("--duration", type=float, default=5.0, help="latency runs: seconds each (default 5)")
    p.add_argument("--rates", type=float, nargs="+", default=[100, 200, 300, 400, 600, 800],
                   help="throughput runs: source rates tried, rising (default 100 200 300 400 600 800)")
    p.add_argument("--tp-duration", type=float, default=3.0, help="throughput runs: seconds each (default 3)")
    p.add_argument("--repeats", type=int, default=3, help="runs per combination and measure (default 3)")
    p.add_argument("--warmup", type=int, default=5, help="first source events of a run not measured (default 5)")
    p.add_argument("--timeout", type=float, default=120.0, help="a run killed after this many s (default 120)")
    p.add_argument("--startup-timeout", type=float, default=60.0, help="the coordinator's wait for its workers")
    p.add_argument("--out", type=Path, default=OUT, help=f"directory for the CSV and PNG (default {OUT})")
    p.add_argument("--no-throughput", action="store_true", help="latency runs only")
    p.add_argument("--quick", action="store_true",
                   help="a smoke run: 2 branches, 1 repeat, 1 s latency runs at 20 Hz, no throughput runs")
    p.add_argument("--one", nargs=3, metavar=("WAITING", "LOGGING", "BRANCHES"), help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if args.one:
        w, g, branches = args.one
        print(json.dumps(one(w, g, int(branches), args.hz, args.duration, args.warmup, args.startup_timeout)))
        return 0
    if args.quick:
        args.branches, args.repeats, args.duration, args.hz, args.warmup = 2, 1, 1.0, 20.0, 2
        args.no_throughput = True
    args.out.mkdir(parents=True, exist_ok=True)
    from importlib.metadata import version

    load_start = loadavg()
    print("retriever determinism cost on zenoh: event-time waiting on/off x logging on/off; "
          f"python {platform.python_version()}, {os.cpu_count()} cpus, eclipse-zenoh {version('eclipse-zenoh')}; "
          f"{datetime.datetime.now().isoformat(timespec='seconds')}; load average at start {load_start}", flush=True)
    rates = ", ".join(f"{r:g}" for r in args.rates)
    print(f"fan: src -> {args.branches} branches -> join ({args.branches + 2} flows); latency at {args.hz:g} Hz for "
          f"{args.duration:g} s; " + ("no throughput runs; " if args.no_throughput else
                                      f"throughput at {rates} Hz for {args.tp_duration:g} s; ") +
          f"{args.repeats} repeats, combinations interleaved", flush=True)
    rows: list[dict] = []
    best: dict = {}  # (waiting, logging) -> each repeat's highest rate kept up
    best_rows: dict = {}
    for rep in range(args.repeats):
        order = COMBOS if rep % 2 == 0 else COMBOS[::-1]
        for w, g in order:
            r = row_of("latency", w, g, rep, args.hz,
                       measure(w, g, args.branches, args.hz, args.duration, args.warmup, args), args.branches)
            rows.append(r)
            print(f"  repeat {rep + 1} wait {w:>3} log {g:>3} latency: "
                  + (f"FAILED {r['error'][:300]}" if r["error"] else
                     f"p50 {r['lat_p50_us']:,.0f} µs (p10 {r['lat_p10_us']:,.0f}, p90 {r['lat_p90_us']:,.0f}, "
                     f"n={r['lat_n']}), incomplete {r['incomplete']}, late {r['late']}"), flush=True)
        for w, g in order if not args.no_throughput else ():
            top = 0.0
            for hz in args.rates:
                r = row_of("throughput", w, g, rep, hz,
                           measure(w, g, args.branches, hz, args.tp_duration, 0, args), args.branches)
                rows.append(r)
                print(f"  repeat {rep + 1} wait {w:>3} log {g:>3} @ {hz:>6g} Hz: "
                      + (f"FAILED {r['error'][:300]}" if r["error"] else
                         f"src {r['src_ticks']}/{r['src_due']}, reached {r['complete']:.1%} "
                         f"({r['complete_early']:.1%} of those 100 ms before the end), overrun {r['overrun']}, "
                         f"{r['steps_per_s']:,.0f} steps/s -> {'kept up' if r['kept_up'] else 'NOT kept up'}"),
                      flush=True)
                if r["error"] or not r["kept_up"]:
                    break
                top = hz
                best_rows.setdefault((w, g), []).append(r)
            best.setdefault((w, g), []).append(top)
    load_end = loadavg()
    csv_path, png_path = args.out / "determinism_cost.csv", args.out / "determinism_cost.png"
    with open(csv_path, "w", newline="") as f:
        wr = csv.DictWriter(f, fieldnames=FIELDS)
        wr.writeheader()
        wr.writerows(rows)

    print()
    head = (f"{'waiting':>7} {'log':>3} │ {'e2e latency µs: p50 [min–max]':>30} {'p10':>6} {'p90':>6} │ "
            f"{'incompl':>7} {'late':>5} │ {'max rate Hz [min–max]':>22} │ {'steps/s':>7} {'msgs/s':>7} │ {'runs':>4}")
    print(head)
    print("─" * len(head))
    for w, g in COMBOS:
        lat = [r for r in rows if r["kind"] == "latency" and (r["waiting"], r["logging"]) == (w, g) and not r["error"]]
        failed = sum(1 for r in rows if (r["waiting"], r["logging"]) == (w, g) and r["error"])
        rates = best.get((w, g), [])
        at_best = best_rows.get((w, g), [])
        top = statistics.median(rates) if rates else 0
        top_rows = [r for r in at_best if r["hz"] == top]
        lat_cells = (f"{med_range([r['lat_p50_us'] for r in lat]):>30} "
                     f"{statistics.median(r['lat_p10_us'] for r in lat):>6,.0f} "
                     f"{statistics.median(r['lat_p90_us'] for r in lat):>6,.0f} │ "
                     f"{sum(r['incomplete'] for r in lat):>7} {sum(r['late'] for r in lat):>5}") if lat else \
            f"{'every latency run failed':>46} │ {'':>13}"
        print(f"{w:>7} {g:>3} │ {lat_cells} │ {med_range(rates, '{:,.0f}'):>22} │ "
              f"{statistics.median(r['steps_per_s'] for r in top_rows) if top_rows else 0:>7,.0f} "
              f"{statistics.median(r['msgs_per_s'] for r in top_rows) if top_rows else 0:>7,.0f} │ "
              f"{len(lat):>4}" + (f"  ({failed} run(s) failed)" if failed else ""))
    print()
    print("latency: source event published -> start of the join's step that consumed the last of its copies; per run")
    print("p10/p50/p90, median over runs [min-max of the runs' medians]. incompl/late: the runtime's counters, summed")
    print("over the latency runs. max rate: the highest source rate tried at which every tick ran, nothing overran and")
    print("every source event (but those of the last 100 ms) reached the join; steps/s and msgs/s (events")
    print("published) at the median max rate.")
    print(f"load average at start {load_start}, at end {load_end}; rows in {csv_path}, plot in {png_path}")
    plot([r for r in rows if r["kind"] == "latency"], best, png_path,
         f"fan of {args.branches + 2} flows on zenoh; latency at {args.hz:g} Hz; {args.repeats} repeats; "
         f"{os.cpu_count()} cpus; load {load_start.split()[0]} → {load_end.split()[0]}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
