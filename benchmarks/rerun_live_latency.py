"""How late the Rerun live view's small rows reach its sink beside a camera of big frames.

A 30 Hz camera of 230 kB frames (320x240 RGB) and a 100 Hz number are fed, in real time, to a
RerunLiveView saving to an .rrd (the coordinator's calls: ``view.event``), for DURATION seconds.
Each chunk's id is a TUID whose first 8 bytes are when Rerun's batcher made it (flushed it); the
chunks of an entity hold its rows in the order logged, so row j of the number reached the sink
at its chunk's time: its latency is that minus when it was logged. Also the CPU time of the
feeding thread per event (what the view costs the coordinator).

    PYTHONPATH=CODE python benchmarks/rerun_live_latency.py [--duration 6]
"""

from __future__ import annotations

import argparse
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from retriever.log.rerun_live import RerunLiveView


def chunks(rrd: Path, entity: str) -> list[tuple[int, int]]:
    """(made at, ns since the epoch; rows) of each chunk of ``entity``, in the file's order."""
    listing = subprocess.run([sys.executable, "-m", "rerun_cli", "rrd", "print", str(rrd)], capture_output=True,
                             text=True, check=True).stdout
    return [(int(m[1][:16], 16), int(m[2])) for m in
            re.finditer(rf"^Chunk\(chunk_([0-9A-Fa-f]+)\) with (\d+) rows \(.*\) - {re.escape(entity)} - ",
                        listing, re.MULTILINE)]


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--duration", type=float, default=6.0)
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as folder:
        measure(Path(folder) / "live.rrd", args.duration)


def measure(out: Path, duration: float) -> None:
    view = RerunLiveView(out, "latency")
    frame = np.random.default_rng(0).integers(0, 256, (240, 320, 3), dtype=np.uint8)
    logged: list[int] = []
    cpu = 0.0
    start = time.monotonic()
    t0 = time.time_ns()
    i = 0
    while (due := start + i * 0.01) < start + duration:
        time.sleep(max(0.0, due - time.monotonic()))
        now = time.time_ns()
        c = time.thread_time()
        view.event("sensor", "x", (now - t0, 0), i, float(i), now)
        if i % 3 == 0:  # 33 Hz
            view.event("cam", "rgb", (now - t0, 0), i // 3, frame, now)
        cpu += time.thread_time() - c
        logged.append(now)
        i += 1
    c = time.thread_time()
    view.close()
    close_cpu = time.thread_time() - c
    latencies = []
    j = 0
    numbers = chunks(out, "/sensor/x")
    for made, rows in numbers:
        latencies += [made - logged[k] for k in range(j, j + rows)]
        j += rows
    assert j == len(logged), (j, len(logged))
    ms = np.asarray(latencies) / 1e6
    frames = chunks(out, "/cam/rgb")
    print(f"numbers {len(logged)}, chunks {len(numbers)}; latency ms p50 {np.median(ms):.0f} "
          f"p95 {np.percentile(ms, 95):.0f} max {ms.max():.0f}; frame chunks {len(frames)} "
          f"(rows {min(r for _, r in frames)}-{max(r for _, r in frames)}); "
          f"feeding CPU {cpu / (len(logged) + len(logged[::3])) * 1e6:.0f} us/event, close {close_cpu * 1e3:.0f} ms")


if __name__ == "__main__":
    main()
