"""Throughput of small messages (64 B), one flow to another on ``zenoh``, against raw zenoh-python.

- ``raw``: zenoh-python written the plainest way, two processes over loopback TCP: a publisher
  putting ``array.tobytes()`` in a loop as fast as it goes for ``--seconds`` (congestion control
  BLOCK: it waits rather than drops), a subscriber iterating ``for sample in subscriber:`` and
  counting, checking every seq arrived. Rate = messages received / the time from the first to
  the last.
- ``retriever``, one event per tick: ``SmallSource() @ Rate(hz)`` → ``Tally() @ Trigger("data")``
  over ``Queue()`` (``benchmarks/zenoh_flows.py``), one worker each, for ``--seconds``, at rising
  rates (``--hz``). Its throughput is the highest tick rate at which every tick ran on time (no
  overrun skipped one) and the consumer took every event.
- ``retriever``, bursts: ``SmallBurst(n=--burst) @ Rate(hz)``, each tick a ``Burst`` of n 64 B
  arrays (n events, each its own seq and id, one message), to the same ``Tally``, at rising tick
  rates (``--burst-hz``); the same criterion.

Rate = events the consumer took / the run's seconds. Target (issue 21): Retriever ≥ 50 % of raw's
rate in the same run (raw measured before and after the Retriever runs, the mean of the two).

    .venv/bin/python benchmarks/throughput.py                       # about 2 min
    .venv/bin/python benchmarks/throughput.py --hz 1000 5000 --burst 100 --burst-hz 100 500 1000
    .venv/bin/python benchmarks/throughput.py --log --hz 1000 --burst-hz 100 200   # logged runs too
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent))
sys.path.insert(0, str(HERE))

from latency import _config, free_port  # noqa: E402  (the raw sides' zenoh config)

TARGET = 0.5
SIZE = 64


def raw_sub(key: str, listen: str, timeout: float) -> int:
    import threading

    import numpy as np
    import zenoh

    seen = {"n": 0, "first": None, "last": None, "top": -1, "gaps": 0}
    with zenoh.open(_config(listen=listen)) as session:
        sub = session.declare_subscriber(key)
        print("READY", flush=True)

        def drain() -> None:
            expect = 0
            for sample in sub:
                data = np.frombuffer(sample.payload.to_bytes(), np.uint8)
                seq = int.from_bytes(data[:8].tobytes(), "little")
                now = time.perf_counter()
                if seen["first"] is None:
                    seen["first"] = now
                seen["last"], seen["n"], seen["top"] = now, seen["n"] + 1, max(seen["top"], seq)
                if seq != expect:
                    seen["gaps"] += 1
                expect = seq + 1
        threading.Thread(target=drain, daemon=True).start()
        sys.stdin.readline()  # the publisher is done
        time.sleep(0.5)
        sub.undeclare()
    print(json.dumps(seen), flush=True)
    return 0


def raw_pub(key: str, connect: str, seconds: float) -> int:
    import numpy as np
    import zenoh

    data = np.zeros(SIZE, np.uint8)
    with zenoh.open(_config(connect=connect)) as session:
        pub = session.declare_publisher(key, congestion_control=zenoh.CongestionControl.BLOCK)
        give_up = time.monotonic() + 20
        while not pub.matching_status.matching and time.monotonic() < give_up:
            time.sleep(0.01)
        time.sleep(0.2)
        seq, end = 0, time.perf_counter() + seconds
        while time.perf_counter() < end:
            data[:8] = np.frombuffer(seq.to_bytes(8, "little"), np.uint8)
            pub.put(data.tobytes())
            seq += 1
        time.sleep(0.2)
    print(json.dumps({"sent": seq}), flush=True)
    return 0


def run_raw(seconds: float) -> dict:
    key, port = f"bench/throughput/{os.getpid()}", free_port()
    me = [sys.executable, str(Path(__file__).resolve())]
    sub = subprocess.Popen(me + ["--raw-sub", key, f"tcp/127.0.0.1:{port}", str(seconds + 30)],
                           stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    if sub.stdout.readline().strip() != "READY":
        raise SystemExit("raw subscriber did not start")
    pub = subprocess.run(me + ["--raw-pub", key, f"tcp/127.0.0.1:{port}", str(seconds)], capture_output=True,
                         text=True, timeout=seconds + 60)
    sent = json.loads(pub.stdout.strip().splitlines()[-1])["sent"]
    seen = json.loads(sub.communicate("done\n", timeout=60)[0].strip().splitlines()[-1])
    span = (seen["last"] or 0) - (seen["first"] or 0)
    return {"sent": sent, "received": seen["n"], "gaps": seen["gaps"], "rate": seen["n"] / span if span else 0.0}


def run_retriever(hz: float, seconds: float, burst: int = 0, log: bool = False) -> dict:
    """One event per tick (``burst=0``), or a Burst of ``burst`` events per tick; with ``log``,
    logged (to a temporary file), and the seconds the run took past its duration measured."""
    import tempfile
    from zenoh_flows import SmallBurst, SmallSource, Tally

    from retriever import Pipeline, Queue, Rate, Trigger

    with Pipeline("throughput", deadline=1.0) as pipe:
        producer = SmallBurst(SIZE, burst) if burst else SmallSource(SIZE)
        source = producer.configure(name="source") @ Rate(hz=hz)
        tally = Tally().configure(name="tally") @ Trigger("data")
        source.then(tally, sync=Queue(maxsize=1 << 22))
    with tempfile.TemporaryDirectory() as tmp:
        start = time.monotonic()
        trace = pipe.run(duration=seconds, backend="zenoh", quiet=True, keep="records",
                         log=os.path.join(tmp, "run.mcap") if log else None)
        late = time.monotonic() - start - seconds
    stats, counts = pipe.stats(), dict(pipe.counts())
    taken = sum(len(ids) for s in trace.steps_of("tally") for ids in s.consumed.values())
    ticks = stats["source"].steps
    per_tick = burst or 1
    return {"hz": hz, "ticks": ticks, "due": round(hz * seconds), "taken": taken, "counts": counts,
            "rate": taken / seconds, "late": late,
            "kept_up": taken == ticks * per_tick and ticks >= round(hz * seconds) - 1 and not counts.get("overrun")}


def sweep(label: str, rates: list[float], seconds: float, burst: int = 0, log: bool = False) -> dict | None:
    """Rising tick rates until one does not keep up: the best one that did (None if none)."""
    best = None
    for hz in rates:
        r = run_retriever(hz, seconds, burst, log)
        logged = f"; took {r['late']:.1f} s more than its duration (start-up, the log)" if log else ""
        print(f"retriever, {label} @ {hz:>7,.0f} Hz: {r['rate']:>9,.0f} events/s taken, {r['ticks']:,} of "
              f"{r['due']:,} ticks, {r['taken']:,} taken; counts {r['counts']}{logged} -> "
              f"{'kept up' if r['kept_up'] else 'did NOT keep up'}", flush=True)
        if not r["kept_up"]:
            break
        best = r
    return best


def main() -> int:
    argv = sys.argv[1:]
    if argv and argv[0] == "--raw-sub":
        return raw_sub(argv[1], argv[2], float(argv[3]))
    if argv and argv[0] == "--raw-pub":
        return raw_pub(argv[1], argv[2], float(argv[3]))
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--seconds", type=float, default=5.0)
    p.add_argument("--hz", type=float, nargs="+", default=[1000, 2000, 3000, 4000, 5000],
                   help="tick rates of the one-event-per-tick source")
    p.add_argument("--burst", type=int, default=1000, help="events per tick of the burst source (0: none)")
    p.add_argument("--burst-hz", type=float, nargs="+", default=[50, 100, 150, 200, 250, 300],
                   help="tick rates of the burst source")
    p.add_argument("--log", action="store_true", help="log the Retriever runs (not what the target is judged on)")
    args = p.parse_args()
    print(f"throughput of {SIZE} B messages, one flow to another; {args.seconds:g} s per run; "
          f"load average {' '.join(f'{x:.2f}' for x in os.getloadavg())}", flush=True)
    raw = run_raw(args.seconds)
    print(f"raw zenoh-python: {raw['rate']:,.0f} msg/s ({raw['received']:,} of {raw['sent']:,} received, "
          f"{raw['gaps']} gaps)", flush=True)
    single = sweep("one event per tick", args.hz, args.seconds, log=args.log)
    bursts = (sweep(f"bursts of {args.burst:,}", args.burst_hz, args.seconds, args.burst, args.log)
              if args.burst else None)
    again = run_raw(args.seconds)  # the machine's drift over the run, on the raw side
    raw_rate = (raw["rate"] + again["rate"]) / 2
    print(f"raw zenoh-python again: {again['rate']:,.0f} msg/s; mean of the two {raw_rate:,.0f}")
    results = [(label, r) for label, r in (("one event per tick", single), (f"bursts of {args.burst:,}", bursts))
               if r is not None]
    for label, r in results:
        print(f"retriever's best, {label}: {r['rate']:,.0f} events/s at {r['hz']:,.0f} Hz = "
              f"{r['rate'] / raw_rate:.1%} of raw")
    if not results:
        print("retriever kept up at no rate tried")
        return 1
    ratio = max(r["rate"] for _, r in results) / raw_rate
    print(f"best {ratio:.1%} of raw -> target >= {TARGET:.0%}: {'met' if ratio >= TARGET else 'NOT met'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
