"""One run of the quickstart (or the typed chain) for counting the run's thread's instructions,
logged or not (benchmarks/reports/logging_overhead.md, "instructions of the run's thread").

    OPENBLAS_NUM_THREADS=1 PYTHONHASHSEED=0 valgrind --tool=callgrind --separate-threads=yes \\
        --callgrind-out-file=/tmp/cg.%p python benchmarks/log_instructions.py quickstart 100 --log

The run's thread is thread 1 (``/tmp/cg.PID-01``: its ``summary:`` line). It runs ``pipe.reset();
pipe.step(0.0)``, then one ``pipe.run(duration)``, with the hand-overs to the log writer 4096
steps apart as at full speed (valgrind's run is ~50x slower: with the 20 ms aimed for, it would
hand over every few dozen steps). A run of 1 s counted the same way gives what a run pays once:
``(I(100 s) - I(1 s)) / (steps(100 s) - steps(1 s))`` is the cost of a step (the quickstart: 23,200
and 232 step records, 22,968 apart; nothing here reads the trace, which would expand it).
Without valgrind, ``--cpu N`` times N alternating unlogged and logged runs instead
(``time.thread_time``, best of each, a full collection before each) and prints their ratio.
"""

from __future__ import annotations

import argparse
import gc
import os
import runpy
import sys
import tempfile
import time
from pathlib import Path
from unittest import mock

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from retriever.backends.base import Session  # noqa: E402


def build(workload: str):
    if workload == "quickstart":
        return runpy.run_path(str(ROOT / "examples" / "quickstart.py"), run_name="quickstart")["pipe"]
    sys.path.insert(0, str(ROOT / "benchmarks"))
    from step_overhead import Chain, build as build_chain  # noqa: PLC0415

    return build_chain(Chain("typed", "rate", 5), 1000)[0]  # logging_overhead.py's chain


def one_run(pipe, duration: float, log: bool, folder: str) -> float:
    """The run's thread CPU time. (Nothing reads the trace after: an unlogged run's tape is
    expanded when it is first read, which is no part of the run; a logged run's, by the writer.)"""
    pipe.reset()
    pipe.step(0.0)
    path = os.path.join(folder, "run.mcap")
    start = time.thread_time()
    pipe.run(duration, **({"log": path, "overwrite": True} if log else {}))
    return time.thread_time() - start


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("workload", choices=["quickstart", "chain"])
    parser.add_argument("duration", type=float, help="virtual seconds")
    parser.add_argument("--log", action="store_true", help="write the event log")
    parser.add_argument("--cpu", type=int, default=0, help="alternate this many unlogged and logged runs, timed")
    args = parser.parse_args()
    pipe = build(args.workload)
    # (as tests/backends/test_inproc_loop.py sets LOG_BATCH)
    with mock.patch.object(Session, "LOG_HANDOVER_S", 1000.0), tempfile.TemporaryDirectory() as folder:
        if not args.cpu:
            one_run(pipe, args.duration, args.log, folder)
            print(f"{args.workload} {args.duration:g} s {'logged' if args.log else 'unlogged'}")
            return
        off, on = [], []
        for _ in range(args.cpu):
            # a full collection owed by the earlier runs' traces, before the clock starts: else it
            # lands in a run's setup (the writer's, which comes before the run holds full
            # collections) or not by a few allocations' phase, +40-120 ms in a run
            gc.collect()
            off.append(one_run(pipe, args.duration, False, folder))
            gc.collect()
            on.append(one_run(pipe, args.duration, True, folder))
        steps = len(pipe.session.trace.raw_steps)
        print(f"{args.workload} {args.duration:g} s, best of {args.cpu}: off {min(off) * 1e3:.1f} ms, "
              f"on {min(on) * 1e3:.1f} ms, on/off {min(on) / min(off):.3f}, "
              f"+{(min(on) - min(off)) / steps * 1e6:.2f} us a step ({steps} steps)")


if __name__ == "__main__":
    main()
