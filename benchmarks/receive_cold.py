"""How long a node's receive path takes after a sleep, and what its warm-up buys (issue 42).

The latency benchmark's pipeline (``PayloadSource`` → ``LatencySink`` on ``Trigger("frame")``,
``Latest()``): the sink's real NodeLoop is rebuilt from the IR as a worker does, on a real,
unconnected Zenoh session, and driven by hand from this thread, which plays the receiving thread:
``NodeLoop.receive`` of a 64 B frame's data message until the sink's ``step()`` starts (no
transport: what the runtime itself does per message). Before each message, one of:

- ``hot``: nothing (the previous message just ran);
- ``cold``: 50 ms asleep, as between two frames at 20 Hz;
- ``rehearsed``: 50 ms asleep, then the loop's warm-up (``Warmup.warm``: the rehearsal of the
  receive path on the previous message), then at once the message;
- ``decoded``, ``decoded+SLEEP``: the same, the warm-up decoding the previous message only (what
  it did before the rehearsal);
- ``rehearsed+SLEEP``: the same with SLEEP µs asleep between the warm-up and the message (the
  loop wakes ``WARM_AHEAD_NS`` before a foreseen arrival);
- ``full+SLEEP``: 50 ms asleep, then a real message through the whole path (what no warm-up can
  do: it runs the step), SLEEP µs asleep, then the measured one: the bound of any warm-up.

    .venv/bin/python benchmarks/receive_cold.py                    # every mode, 40 messages each
    .venv/bin/python benchmarks/receive_cold.py --modes cold rehearsed --messages 100

Prints the median and quartiles per mode (µs), and the load average: on a shared machine the
sleeps let other processes evict the caches, and every mode but ``hot`` gets slower.
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import time
from pathlib import Path

import numpy as np
import zenoh

sys.path.insert(0, str(Path(__file__).resolve().parent))
from zenoh_flows import PayloadSource, StampedSink  # noqa: E402

from retriever import Latest, Pipeline, Rate, Trigger  # noqa: E402
from retriever.backends.zenoh.hub import peer_config  # noqa: E402
from retriever.backends.zenoh.node import DATA  # noqa: E402
from retriever.backends.zenoh.protocol import RunSpec  # noqa: E402
from retriever.backends.zenoh.wire import WireEncoder, decode_events  # noqa: E402
from retriever.backends.zenoh.worker.build import build_loop  # noqa: E402
from retriever.ir import IR  # noqa: E402
from retriever.plan import plan_ir  # noqa: E402

MODES = ["hot", "cold", "decoded", "decoded+1000", "rehearsed", "rehearsed+300", "rehearsed+1000", "full+0",
         "full+1000"]


def sink_loop(session):
    with Pipeline("receive_cold") as pipe:
        src = PayloadSource(64).configure(name="src") @ Rate(hz=20)
        src.then(StampedSink().configure(name="sink") @ Trigger("frame"), sync=Latest())
    doc = pipe.compile().to_ir().doc
    spec = RunSpec(ir=doc, plan=plan_ir(IR(doc)).to_data(), namespace="receive-cold", hub=None,
                   startup_timeout=60.0, zids={}, hub_zid=None, virtual_time=False)
    loop = build_loop(spec, "sink", session)
    loop.declare()
    loop.run_clock.t0, loop.run_clock.end, loop.run_clock.started = time.time_ns() - 10**9, 1 << 62, True
    return loop


def measure(mode: str, messages: int) -> list[int]:
    encoder, array = WireEncoder(), np.zeros(64, np.uint8)
    out: list[int] = []
    with zenoh.open(peer_config()) as session:
        loop = sink_loop(session)
        loop.turn.release()  # the main thread waits: a message is handled on the receiving thread

        def message(seq: int, tag: int) -> tuple:
            frame = {"data": array, "sent_ns": 0}
            return (DATA, ("src", "frame"), encoder.data((tag, 0), seq, (tag + 1, 0), "src", "frame", frame))

        def handle(item: tuple) -> None:
            loop.last_wall = 0  # as after a short step: it runs on the receiving thread
            loop.receive(item)
            while not loop.inbox.empty():  # (the nudge for the main thread)
                loop.inbox.get_nowait()

        seq, last = 0, None
        try:
            for k in range(messages + 5):
                now = time.time_ns() - loop.run_clock.t0
                kind, _, pause = mode.partition("+")
                if kind == "cold":
                    time.sleep(0.05)
                elif kind in ("rehearsed", "decoded"):
                    time.sleep(0.05)
                    if kind == "rehearsed":
                        loop.warmup.warm(last[2] if last is not None else None)
                    elif last is not None:
                        decode_events(last[2])
                    if pause:
                        time.sleep(int(pause) / 1e6)
                elif kind == "full":
                    time.sleep(0.05)
                    handle(message(seq, now - 2))
                    seq += 1
                    if int(pause):
                        time.sleep(int(pause) / 1e6)
                item = message(seq, now)
                seq += 1
                began = time.perf_counter_ns()
                handle(item)
                if k >= 5:  # (the first few build caches of their own)
                    out.append(StampedSink.starts[-1] - began)
                last = item
        finally:
            loop.turn.acquire()
            loop.undeclare()
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--modes", nargs="+", default=MODES, help=f"of {', '.join(MODES)} (default: all)")
    parser.add_argument("--messages", type=int, default=40, help="measured per mode (default 40)")
    args = parser.parse_args()
    print(f"receive() → step(), 64 B frame, µs; load average at start {' '.join(f'{x:.2f}' for x in os.getloadavg())}")
    for mode in args.modes:
        got = measure(mode, args.messages)
        q1, median, q3 = statistics.quantiles(got, n=4)
        print(f"  {mode:>16}: median {median / 1000:7.1f}   quartiles {q1 / 1000:7.1f} – {q3 / 1000:7.1f}   (n={len(got)})")
    print(f"load average at end {' '.join(f'{x:.2f}' for x in os.getloadavg())}")


if __name__ == "__main__":
    main()
