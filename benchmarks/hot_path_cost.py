"""What a node's per-message path costs, counted rather than timed (issue 42).

The latency benchmark's pipeline (``PayloadSource`` → ``StampedSink`` on ``Trigger("frame")``,
``Latest()``, 64 B frames), its nodes' real NodeLoops rebuilt from the IR as a worker does, on
a real, unconnected Zenoh session, driven by hand from this thread (as receive_cold.py does):

- ``sink``: ``NodeLoop.receive`` of a data message, as the receiving thread calls it, through
  the sink's ``step()``, its record and its output's put; then, as the main thread does between
  two frames at 20 Hz, the report flushed and the coordinator's ``have``;
- ``source``: the source's ticks due, through ``NodeLoop.one_pass`` (the plain source's way):
  its step, the stamp, the encoding, the put and the record, then the report flushed.

Each runs ``--messages`` of them after 20 to warm up. Run it under valgrind with N and 2N
messages: the difference in instructions is the cost of N messages through the path, whatever
the machine's load::

    OPENBLAS_NUM_THREADS=1 PYTHONHASHSEED=0 valgrind --tool=cachegrind --cache-sim=no \\
        --cachegrind-out-file=/dev/null .venv/bin/python benchmarks/hot_path_cost.py --side sink --messages 500

Or count the path alone, under callgrind: only what runs inside ``operator.call`` (the path's
call, nothing around it), with ``--evict-mib`` its cache misses as after a sleep::

    OPENBLAS_NUM_THREADS=1 PYTHONHASHSEED=0 valgrind --tool=callgrind --toggle-collect=_operator_call \\
        --cache-sim=yes --LL=4194304,16,64 --callgrind-out-file=OUT .venv/bin/python \\
        benchmarks/hot_path_cost.py --side sink --messages 200 --evict-mib 16

``--calls``: instead, list the functions called for one message (sys.setprofile), from the
path's entry to the flow's step (``sink``: ``receive`` → ``step``; ``source``: ``step``
returned → ``put``), and after it up to the path's end, with their count and the lock sections
among them (benchmarks/reports/latency.md has the counts).
"""

from __future__ import annotations

import argparse
import operator
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
from retriever.backends.zenoh.wire import WireEncoder  # noqa: E402
from retriever.backends.zenoh.worker.build import build_loop  # noqa: E402
from retriever.ir import IR  # noqa: E402
from retriever.plan import plan_ir  # noqa: E402

WARMUP = 20


def build(session, node: str):
    with Pipeline("hot_path_cost") as pipe:
        src = PayloadSource(64).configure(name="src") @ Rate(hz=20)
        src.then(StampedSink().configure(name="sink") @ Trigger("frame"), sync=Latest())
    doc = pipe.compile().to_ir().doc
    spec = RunSpec(ir=doc, plan=plan_ir(IR(doc)).to_data(), namespace="hot-path-cost", hub=None,
                   startup_timeout=60.0, zids={}, hub_zid=None, virtual_time=False)
    loop = build_loop(spec, node, session)
    loop.declare()
    return loop


def sink(session, messages: int, calls: bool, evict) -> None:
    loop = build(session, "sink")
    loop.run_clock.t0, loop.run_clock.end, loop.run_clock.started = time.time_ns() - 10**12, 1 << 62, True
    loop.run_clock.promised_end = 1 << 61
    loop.turn.release()  # the main thread waits: a message is handled on the receiving thread
    encoder, array = WireEncoder(), np.zeros(64, np.uint8)

    def message(seq: int) -> tuple:
        tag = 10**9 + seq * 50_000_000
        return (DATA, ("src", "frame"), encoder.data((tag, 0), seq, (tag + 1, 0), "src", "frame",
                                                      {"data": array, "sent_ns": 0}))

    items = [message(seq) for seq in range(WARMUP + messages)]
    try:
        for seq, item in enumerate(items):
            loop.last_wall = 0  # as after a short step: it runs on the receiving thread
            if calls and seq == len(items) - 1:
                listed(lambda: loop.receive(item), start="receive", middle="step", end=None)
            else:
                evict()
                operator.call(loop.receive, item)  # (the window callgrind's --toggle-collect counts)
            while not loop.inbox.empty():  # (the nudge for the main thread)
                loop.inbox.get_nowait()
            # what the main thread then does, at 20 Hz: the records and events reported, and the
            # coordinator says it has them (else the records held for them pile up)
            loop.reports.flush()
            loop.reports.coordinator_has({("src", "frame"): seq})
        assert loop.streams.expect[("src", "frame")] == len(items)
        assert loop.reports.recorded == len(items), loop.reports.recorded
    finally:
        loop.turn.acquire()
        loop.undeclare()


def source(session, messages: int, calls: bool, evict) -> None:
    loop = build(session, "src")
    loop.begin(time.time_ns() - 10**12, 1 << 62)  # every tick due at once
    loop.outputs.consumed = True
    try:
        while loop.reports.recorded < WARMUP + messages:  # (a pass may run two ticks)
            if calls and loop.reports.recorded >= WARMUP + messages - 2:
                listed(lambda: loop.one_pass(), start="step", middle="put", end="one_pass",
                       after_start=True)
                break
            evict()
            operator.call(loop.one_pass)  # (the window callgrind's --toggle-collect counts)
            loop.reports.flush()  # (at 20 Hz, each tick's event is reported before the next tick)
        assert loop.outputs.seqs["frame"] == loop.reports.recorded
    finally:
        loop.undeclare()


def listed(call, *, start: str, middle: str, end: str | None, after_start: bool = False) -> None:
    """Run ``call`` and print the functions it calls from ``start`` (``after_start``: from its
    return) to ``middle``, then the rest up to ``end`` (if it comes), with their count."""
    seen: list[tuple[str, str]] = []
    state = {"on": False, "part": "before"}

    def profile(frame, event, arg):
        name = frame.f_code.co_name if event in ("call", "return") else getattr(arg, "__qualname__", str(arg))
        if event == "call" and name == start and not after_start and not state["on"]:
            state.update(on=True, part="to " + middle)
        if state["on"] and event in ("call", "c_call"):
            where = f"{Path(frame.f_code.co_filename).name}:{name}" if event == "call" else f"C {name}"
            seen.append((state["part"], where))
            if name == middle or name.endswith("." + middle):
                state["part"] = "after " + middle
        if event == "call" and name == end and state["on"]:
            state["on"] = False
            state["ended"] = True
        if event == "return" and name == start and after_start and not state["on"] and "ended" not in state:
            state.update(on=True, part="to " + middle)

    sys.setprofile(profile)
    try:
        call()
    finally:
        sys.setprofile(None)
    for part in dict.fromkeys(p for p, _ in seen):
        names = [w for p, w in seen if p == part]
        python = sum(1 for w in names if not w.startswith("C "))
        locks = sum(1 for w in names if w == "C lock.__exit__")
        print(f"{part}: {python} Python calls, {len(names) - python} C calls ({locks} lock sections)")
        for w in names:
            print("    " + w)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--side", choices=("sink", "source"), default="sink")
    parser.add_argument("--messages", type=int, default=500)
    parser.add_argument("--calls", action="store_true", help="list the calls of the last message instead")
    parser.add_argument("--evict-mib", type=int, default=0,
                        help="before each message, write this many MiB elsewhere: the caches evicted, as by a sleep")
    args = parser.parse_args()
    other = np.zeros(args.evict_mib << 20, np.uint8)

    def evict() -> None:
        if args.evict_mib:
            np.add(other, 1, out=other)

    with zenoh.open(peer_config()) as session:
        (sink if args.side == "sink" else source)(session, args.messages, args.calls, evict)


if __name__ == "__main__":
    main()
