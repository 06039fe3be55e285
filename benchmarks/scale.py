"""Flows vs startup time, CPU, memory and ticks on the zenoh backend (issue 17, section 3).

A fan of N flows: one ``Counter() @ Rate(--source-hz)`` (a camera) and N-1 ``Keep()`` consumers
``@ Rate(--hz)``, each joined to it by ``Latest()`` (``benchmarks/zenoh_flows.py``). Each run is
a fresh process (``--one N``), so its figures are its own:

- ``spawn``: opening the session (hub, spec, N worker processes started), s;
- ``ready``: from then until every worker said ``ready`` (joined the hub and a direct link to
  every other worker, subscriptions declared, shared-memory pool written): the coordinator puts
  the start; ``to T0`` adds the start margin;
- CPU s of the coordinator (``RUSAGE_SELF``) and of all workers (``RUSAGE_CHILDREN``, reaped),
  over the whole run (startup, ``--duration`` s of ticking, stop);
- memory: the coordinator's peak RSS, and the workers' summed and largest private RSS
  (``RssAnon`` in ``/proc/<pid>/status``) when the start is put. Their VmRSS also counts the
  pages of the shared-memory pool each wrote (``RssShmem``, hub.shm_pool_bytes): /dev/shm use;
- ticks: recorded by the coordinator vs due in the run's window (``coordinator.ticks_due``).

    .venv/bin/python benchmarks/scale.py                    # 10 25 50 100 flows, 3 repeats each
    .venv/bin/python benchmarks/scale.py --flows 10 50 --repeats 5 --csv scale.csv
    .venv/bin/python benchmarks/scale.py --flows 100 500 --per-process 50   # configure(process=): 50 flows a process

``--per-process K`` puts the flows K to a worker process (``configure(process=...)``, in order:
the camera with the first K-1 consumers); 0, the default, one process per flow.
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import resource
import statistics
import subprocess
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent))  # run from a checkout without installing
sys.path.insert(0, str(HERE))  # zenoh_flows: the workers get this path from the coordinator

PAGE_KB = 1024
FIELDS = ("flows", "per_process", "processes", "spawn_s", "ready_s", "t0_s", "run_s", "coord_cpu_s", "workers_cpu_s", "coord_rss_mb",
          "workers_anon_mb", "worker_anon_max_mb", "ticks", "due")


def _rss_kb(pid: int) -> int:
    """A process's private resident memory, KiB."""
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("RssAnon:"):
                return int(line.split()[1])
    except OSError:
        pass
    return 0


def one(flows: int, duration: float, source_hz: float, hz: float, per_process: int = 0) -> dict:
    """One run of ``flows`` flows in this process; its figures."""
    from zenoh_flows import Counter, Keep

    from retriever import Latest, Pipeline, Rate
    from retriever.backends.zenoh.coordinator import ticks_due
    from retriever.backends.zenoh.protocol import Start

    def process(i: int) -> dict:  # the i-th flow's process, K to a process
        return {"process": f"p{i // per_process}"} if per_process else {}

    with Pipeline(f"scale{flows}") as pipe:
        camera = Counter().configure(**process(0)) @ Rate(hz=source_hz)
        for i in range(flows - 1):
            camera.then(Keep().configure(name=f"keep{i}", **process(i + 1)) @ Rate(hz=hz), sync=Latest())
    begin = time.monotonic()
    session = pipe.open("zenoh", quiet=True)
    spawned = time.monotonic()
    seen: dict = {}
    put = session.control.put

    def control(record) -> None:
        if type(record) is Start and "ready" not in seen:
            seen["ready"] = time.monotonic()
            seen["t0_wall_ns"] = record.t0 - time.time_ns()  # the start margin, from now
            rss = [_rss_kb(pid) for pid in set(session.worker_pids().values())]  # (a group's process once)
            seen["workers_rss_kb"], seen["worker_rss_max_kb"] = sum(rss), max(rss)
        put(record)

    session.control.put = control
    pipe.run(duration=duration, backend="zenoh")
    ended = time.monotonic()
    me, children = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    end_ns = round(duration * 1e9)
    return {"flows": flows, "per_process": per_process, "processes": len(set(session.worker_pids().values())),
            "spawn_s": spawned - begin, "ready_s": seen["ready"] - spawned,
            "t0_s": seen["ready"] - spawned + seen["t0_wall_ns"] / 1e9, "run_s": ended - begin,
            "coord_cpu_s": me.ru_utime + me.ru_stime, "workers_cpu_s": children.ru_utime + children.ru_stime,
            "coord_rss_mb": me.ru_maxrss / PAGE_KB, "workers_anon_mb": seen["workers_rss_kb"] / PAGE_KB,
            "worker_anon_max_mb": seen["worker_rss_max_kb"] / PAGE_KB,
            "ticks": sum(s.ticks for s in pipe.stats().values()),
            "due": sum(ticks_due(node.clock, end_ns) for node in session.graph.nodes.values())}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--flows", type=int, nargs="+", default=[10, 25, 50, 100])
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--duration", type=float, default=3.0, help="seconds of ticking per run")
    ap.add_argument("--source-hz", type=float, default=30.0)
    ap.add_argument("--hz", type=float, default=5.0, help="rate of each consumer")
    ap.add_argument("--csv", default="scale.csv", help="every run's row")
    ap.add_argument("--per-process", type=int, default=0, help="flows per worker process (0: one each)")
    ap.add_argument("--one", type=int, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.one is not None:
        print(json.dumps(one(args.one, args.duration, args.source_hz, args.hz, args.per_process)))
        return
    rows, failures = [], []
    for flows in args.flows:
        for r in range(args.repeats):
            cmd = [sys.executable, __file__, "--one", str(flows), "--duration", str(args.duration),
                   "--source-hz", str(args.source_hz), "--hz", str(args.hz), "--per-process", str(args.per_process)]
            proc = subprocess.run(cmd, capture_output=True, text=True, env={**os.environ, "PYTHONUNBUFFERED": "1"})
            if proc.returncode != 0:
                failures.append(f"{flows} flows, repeat {r + 1}: exit {proc.returncode}\n{proc.stderr[-2000:]}")
                print(failures[-1], file=sys.stderr)
                continue
            rows.append(json.loads(proc.stdout.strip().splitlines()[-1]))
            print(f"{flows:4d} flows, repeat {r + 1}: ready {rows[-1]['ready_s']:.1f} s, "
                  f"ticks {rows[-1]['ticks']}/{rows[-1]['due']}", file=sys.stderr, flush=True)
    with open(args.csv, "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=FIELDS)
        writer.writeheader()
        writer.writerows(rows)
    print(f"\nfan of N flows: 1 source @ {args.source_hz:g} Hz, N-1 consumers @ {args.hz:g} Hz, "
          f"{args.duration:g} s runs, {args.per_process or 1} flow(s) per process; median [min-max] of "
          f"{args.repeats} runs; rows in {args.csv}")
    cols = ("spawn_s", "ready_s", "t0_s", "run_s", "coord_cpu_s", "workers_cpu_s", "coord_rss_mb", "workers_anon_mb",
            "worker_anon_max_mb")
    print(f"{'flows':>5} │ " + " │ ".join(f"{c:>17}" for c in cols) + f" │ {'ticks/due':>11}")
    for flows in args.flows:
        mine = [row for row in rows if row["flows"] == flows]
        if not mine:
            print(f"{flows:>5} │ every run failed")
            continue
        cells = []
        for c in cols:
            values = [row[c] for row in mine]
            cells.append(f"{statistics.median(values):6.1f} [{min(values):.1f}-{max(values):.1f}]".rjust(17))
        ticks = statistics.median(row["ticks"] / row["due"] for row in mine)
        print(f"{flows:>5} │ " + " │ ".join(cells) + f" │ {ticks:10.1%} ")
    if failures:
        print(f"\n{len(failures)} run(s) failed (above)")
        sys.exit(1)


if __name__ == "__main__":
    main()
