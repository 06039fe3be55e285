"""The run's steps with and without the Rerun live view: a 30 Hz camera of 230 kB frames and a
100 Hz number on zenoh, 8 s; for each mode given (``none``, ``rerun``: to an .rrd in a temporary
folder), each node's ticks, steps, mean step time in µs and the backend's counts, and the
coordinating process's CPU time.

    PYTHONPATH=CODE python benchmarks/rerun_live_steps.py none rerun
"""

from __future__ import annotations

import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from retriever import Flow, Pipeline, Rate


class Cam(Flow):
    def __init__(self):
        self.frame = np.random.default_rng(0).integers(0, 256, (240, 320, 3), dtype=np.uint8)

    def step(self):
        return {"rgb": self.frame}


class Num(Flow):
    def __init__(self):
        self.k = 0

    def step(self):
        self.k += 1
        return {"x": float(self.k)}


def pipeline() -> Pipeline:
    with Pipeline("rate") as pipe:
        Cam().configure(name="cam") @ Rate(hz=30)
        Num().configure(name="num") @ Rate(hz=100)
    return pipe


def main() -> None:
    for mode in sys.argv[1:]:
        with tempfile.TemporaryDirectory() as folder:
            pipe = pipeline()
            options = {"rerun": Path(folder) / "live.rrd"} if mode == "rerun" else {}
            cpu = time.process_time()
            pipe.run(duration=8.0, backend="zenoh", quiet=True, keep="trace", **options)
            cpu = time.process_time() - cpu
            print(mode, {node: (s.ticks, s.steps, round(s.mean_step_s * 1e6), s.counts)
                         for node, s in pipe.stats().items()}, f"coordinator CPU {cpu:.2f} s")


if __name__ == "__main__":
    main()
