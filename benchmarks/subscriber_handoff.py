"""What a zenoh-python subscriber's way of receiving costs in latency: three ways side by side.

One subscriber process with three subscribers, one per way, and one publisher process that puts
64 B samples to each in turn (``--gap-ms`` apart, so each way gets one every 3 gaps: after a
sleep, as at 20 Hz), with ``[seq, sent_ns]`` attached. Each way takes ``time.time_ns()`` after
``sample.payload.to_bytes()`` (as latency.py's raw subscribers do); latency is that minus sent.
Interleaved in the same processes, the three share the machine's load sample by sample.

- ``iter``: ``for sample in subscriber:`` in a Python thread (Zenoh's FIFO channel; latency.py's
  raw-iter side): Zenoh's receiving thread wakes that thread.
- ``indirect``: a Python callback as zenoh-python runs it by default (``Callback(f,
  indirect=True)``): on a Python thread zenoh-python starts for it, which Zenoh's thread wakes.
- ``direct``: ``Callback(f, indirect=False)``: on Zenoh's receiving thread itself, its Python thread
  state kept from one callback to the next (one PyGILState_Ensure never released), as the Zenoh
  backend's data subscribers do (retriever/backends/zenoh/node/transport.py); with
  ``--fresh-state``, not kept (zenoh-python's own way: a thread state made and deleted per call).

    .venv/bin/python benchmarks/subscriber_handoff.py --samples 300
"""

from __future__ import annotations

import argparse
import ctypes
import json
import statistics
import struct
import subprocess
import sys
import threading
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

from latency import _config, free_port  # noqa: E402

ATTACH = struct.Struct("<qq")
WAYS = ("iter", "indirect", "direct")


def sub(listen: str, total: int, keep: bool) -> int:
    import zenoh

    got: dict[str, list[tuple[int, int]]] = {way: [] for way in WAYS}
    done = threading.Event()
    kept: set[int] = set()

    def taker(way: str):
        out = got[way]

        def take(sample) -> None:
            if keep and way == "direct" and threading.get_ident() not in kept:
                ctypes.pythonapi.PyGILState_Ensure()
                kept.add(threading.get_ident())
            sample.payload.to_bytes()
            received = time.time_ns()
            seq, sent = ATTACH.unpack(sample.attachment.to_bytes())
            out.append((seq, received - sent))
            if all(len(v) >= total for v in got.values()):
                done.set()
        return take

    with zenoh.open(_config(listen=listen)) as session:
        subs = []
        it = session.declare_subscriber("handoff/iter")
        subs.append(it)

        def drain() -> None:
            take = taker("iter")
            for sample in it:
                take(sample)
        draining = threading.Thread(target=drain)
        draining.start()
        subs.append(session.declare_subscriber("handoff/indirect", taker("indirect")))
        subs.append(session.declare_subscriber("handoff/direct",
                                               zenoh.handlers.Callback(taker("direct"), indirect=False)))
        print("READY", flush=True)
        done.wait(600)
        for s in subs:
            s.undeclare()
        draining.join()  # (its channel ends with the subscriber: no Python thread is left in Zenoh's calls)
    print(json.dumps(got), flush=True)
    return 0


def pub(connect: str, total: int, gap_ns: int) -> int:
    import zenoh

    payload = bytes(64)
    with zenoh.open(_config(connect=connect)) as session:
        pubs = {way: session.declare_publisher(f"handoff/{way}") for way in WAYS}
        give_up = time.monotonic() + 20
        while not all(p.matching_status.matching for p in pubs.values()) and time.monotonic() < give_up:
            time.sleep(0.01)
        time.sleep(0.3)
        deadline = time.time_ns() + gap_ns
        for seq in range(total):
            order = WAYS[seq % 3:] + WAYS[:seq % 3]  # (each way first, second and third in turn)
            for way in order:
                wait = deadline - time.time_ns()
                if wait > 0:
                    time.sleep(wait / 1e9)
                pubs[way].put(payload, attachment=ATTACH.pack(seq, time.time_ns()))
                deadline += gap_ns
        time.sleep(0.3)
        for p in pubs.values():
            p.undeclare()
    return 0


def main(argv: list[str]) -> int:
    if argv and argv[0] == "--sub":
        return sub(argv[1], int(argv[2]), argv[3] == "keep")
    if argv and argv[0] == "--pub":
        return pub(argv[1], int(argv[2]), int(argv[3]))
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--samples", type=int, default=300, help="per way, after --warmup")
    p.add_argument("--warmup", type=int, default=10)
    p.add_argument("--gap-ms", type=float, default=50 / 3, help="between two puts (each way: 3 gaps)")
    p.add_argument("--fresh-state", action="store_true", help="direct: Python's thread state not kept")
    args = p.parse_args(argv)
    total = args.samples + args.warmup
    listen = f"tcp/127.0.0.1:{free_port()}"
    me = [sys.executable, __file__]
    with open("/proc/loadavg") as f:
        load = f.read().split()[:3]
    s = subprocess.Popen(me + ["--sub", listen, str(total), "fresh" if args.fresh_state else "keep"],
                         stdout=subprocess.PIPE, text=True)
    if s.stdout.readline().strip() != "READY":
        raise SystemExit("the subscriber did not start")
    subprocess.run(me + ["--pub", listen, str(total), str(round(args.gap_ms * 1e6))], check=True)
    got = json.loads(s.communicate()[0].strip().splitlines()[-1])
    print(f"64 B, {args.samples} samples per way, one every {3 * args.gap_ms:.1f} ms; direct's thread state "
          f"{'fresh per call' if args.fresh_state else 'kept'}; load at start {' '.join(load)}")
    meds = {}
    for way in WAYS:
        lat = sorted(d / 1e3 for seq, d in got[way] if seq >= args.warmup)
        q = statistics.quantiles(lat, n=4)
        meds[way] = q[1]
        print(f"  {way:>8}: median {q[1]:6.1f} µs (quartiles {q[0]:.1f}–{q[2]:.1f}), {len(lat)} received")
    print(f"  direct − indirect: {meds['direct'] - meds['indirect']:+.1f} µs; "
          f"direct − iter: {meds['direct'] - meds['iter']:+.1f} µs")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
