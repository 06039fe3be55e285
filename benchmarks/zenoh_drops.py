"""Message loss on Zenoh under CPU saturation: raw zenoh-python DROP vs BLOCK, and a Retriever run.

Zenoh's default congestion control is ``DROP``: a put that finds its transmission queue full waits
briefly, then drops the message. Retriever's zenoh backend declares its data publishers with
``express=True`` and the default congestion control, and puts step records and worker status with
``session.put`` defaults. This script shows what that does when the CPU is saturated:

- ``raw``: a publisher process puts ``--count`` 100-byte messages (express) at ``--hz`` to a
  subscriber process, while ``--burners`` plain Python busy loops run; once with
  ``CongestionControl.DROP`` (the default) and once with ``BLOCK``. Prints received / sent.
- ``retriever``: ``Counter() @ Rate(hz)`` (one small event per tick) next to ``--burners``
  ``Burner`` flows in the same pipeline, on the zenoh backend; compares the ticks the run should
  have with the step records and events the coordinator got. A lost ``done`` status shows up as
  "worker process ... exited with code 0 before it finished".

Nothing here is asserted; losses depend on the load, so run each mode a few times (``--repeats``).

    .venv/bin/python benchmarks/zenoh_drops.py                     # raw and retriever, about 1 min
    .venv/bin/python benchmarks/zenoh_drops.py --modes raw --repeats 3
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
sys.path.insert(0, str(HERE.parent))  # run from a checkout without installing
sys.path.insert(0, str(HERE))  # zenoh_flows: the workers get this path from the coordinator

from latency import free_port


def _config(listen: str | None = None, connect: str | None = None):
    import zenoh

    c = zenoh.Config()
    c.insert_json5("mode", '"peer"')
    c.insert_json5("scouting/multicast/enabled", "false")
    c.insert_json5("listen/endpoints", json.dumps([listen] if listen else []))
    c.insert_json5("connect/endpoints", json.dumps([connect] if connect else []))
    return c


def sub(listen: str, seconds: float) -> int:
    import zenoh

    got = [0]
    with zenoh.open(_config(listen=listen)) as session:
        s = session.declare_subscriber("bench/drops", lambda _: got.__setitem__(0, got[0] + 1))
        print("READY", flush=True)
        time.sleep(seconds)
        s.undeclare()
    print(got[0], flush=True)
    return 0


def pub(connect: str, mode: str, count: int, hz: float) -> int:
    import zenoh

    cc = zenoh.CongestionControl.BLOCK if mode == "block" else zenoh.CongestionControl.DROP
    with zenoh.open(_config(connect=connect)) as session:
        p = session.declare_publisher("bench/drops", express=True, congestion_control=cc)
        while not p.matching_status.matching:
            time.sleep(0.01)
        time.sleep(0.3)
        period = round(1e9 / hz)
        deadline = time.time_ns()
        payload = b"x" * 100
        for _ in range(count):
            wait = deadline - time.time_ns()
            if wait > 0:
                time.sleep(wait / 1e9)
            p.put(payload)
            deadline += period
        time.sleep(0.5)
        p.undeclare()
    return 0


def burn(seconds: float) -> int:
    end = time.perf_counter() + seconds
    while time.perf_counter() < end:
        pass
    return 0


def run_raw(mode: str, args) -> str:
    me = [sys.executable, str(Path(__file__).resolve())]
    listen = f"tcp/127.0.0.1:{free_port()}"
    seconds = args.count / args.hz
    burners = [subprocess.Popen(me + ["--burn", str(seconds + 6)]) for _ in range(args.burners)]
    try:
        s = subprocess.Popen(me + ["--sub", listen, str(seconds + 4)], stdout=subprocess.PIPE, text=True)
        s.stdout.readline()
        subprocess.run(me + ["--pub", listen, mode, str(args.count), str(args.hz)], check=True)
        got = int(s.communicate()[0].strip().splitlines()[-1])
    finally:
        for b in burners:
            b.kill()
            b.wait()
    return f"raw {mode:<5}: received {got} of {args.count} ({args.count - got} lost)"


def run_retriever(args) -> str:
    from zenoh_flows import Burner, Counter

    from retriever import Pipeline, Rate

    with Pipeline("zenoh_drops") as pipe:
        Counter().named("ctrl") @ Rate(hz=args.hz)
        for i in range(args.burners):
            Burner(0.099).named(f"burn{i}") @ Rate(hz=10)
    seconds = args.count / args.hz
    try:
        trace = pipe.run(duration=seconds, backend="zenoh", quiet=True)
    except Exception as e:  # noqa: BLE001 - a lost status message fails the run: that is a result
        first = str(e).splitlines()[0]
        return f"retriever  : run failed: {first}"
    finally:
        pipe.reset()
    ticks = round(seconds * args.hz)
    recs = [r for r in trace.steps if r.node == "ctrl"]
    skipped = sum(r.detail.get("overrun_skipped", 0) for r in recs if r.detail)  # ticks not run, by design
    produced = {eid for r in recs for eid in r.produced}
    seqs = sorted(e.seq for e in trace.events if e.node == "ctrl")
    # an event the worker sent has a seq below the last one seen; a seq gap is a lost event
    gaps = (seqs[-1] + 1 - len(seqs)) if seqs else 0
    orphans = sum(1 for e in trace.events if e.node == "ctrl" and e.id not in produced)
    ran = (seqs[-1] + 1) if seqs else 0  # ticks that produced an event, by the seqs
    return (f"retriever  : {ticks} ticks, {skipped} skipped after overruns (by design); step records {len(recs)}, "
            f"events {len(seqs)}; events lost (seq gaps) {gaps}; step records lost (events without one) {orphans}; "
            f"ticks unaccounted for {ticks - skipped - max(ran, len(recs))}")


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if argv and argv[0] == "--sub":
        return sub(argv[1], float(argv[2]))
    if argv and argv[0] == "--pub":
        return pub(argv[1], argv[2], int(argv[3]), float(argv[4]))
    if argv and argv[0] == "--burn":
        return burn(float(argv[1]))
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--modes", default="raw,retriever", help="comma-separated: raw, retriever")
    p.add_argument("--count", type=int, default=6000, help="messages / ticks per run (default 6000)")
    p.add_argument("--hz", type=float, default=1000.0, help="publish / tick rate (default 1000)")
    p.add_argument("--burners", type=int, default=3, help="busy-loop processes or flows (default 3)")
    p.add_argument("--repeats", type=int, default=2, help="runs per mode (default 2)")
    args = p.parse_args(argv)
    modes = [m.strip() for m in args.modes.split(",") if m.strip()]
    print(f"zenoh message loss under CPU saturation: {args.count} at {args.hz:g} Hz, {args.burners} busy loops, "
          f"{os.cpu_count()} cpus; load average at start {' '.join(f'{x:.2f}' for x in os.getloadavg())}")
    for _ in range(args.repeats):
        if "raw" in modes:
            print(run_raw("drop", args), flush=True)
            print(run_raw("block", args), flush=True)
        if "retriever" in modes:
            print(run_retriever(args), flush=True)
    print(f"load average at end {' '.join(f'{x:.2f}' for x in os.getloadavg())}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
