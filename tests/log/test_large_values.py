"""A big array value goes into the log without holding the GIL for its copies: the run's other
threads (a coordinator's Zenoh thread answering a worker's ``finished`` query within 0.25 s)
keep running while it is written (issue 40, item 9)."""

from __future__ import annotations

import threading
import time

import numpy as np

from retriever import Flow, Pipeline, Rate, read_log
from retriever.log.writer import LogFile, LogWriter
from retriever.trace import Trace

MIB = 1 << 20
FRAME_MIB = 256


class BigFrames(Flow[None, np.ndarray]):
    """Two frames of FRAME_MIB, made before the run (making them is not what is measured)."""

    def __init__(self):
        self.frames = [np.full(FRAME_MIB * MIB, k, dtype=np.uint8) for k in (1, 2)]
        self.k = 0

    def step(self, inp: None) -> np.ndarray:
        self.k += 1
        return self.frames[(self.k - 1) % 2]


def _longest_pause(during) -> float:
    """The longest a thread that wakes every millisecond waited for its turn while ``during()`` ran."""
    stop, gaps = threading.Event(), [0.0]

    def wake() -> None:
        last = time.perf_counter()
        while not stop.is_set():
            time.sleep(0.001)
            now = time.perf_counter()
            gaps.append(now - last)
            last = now

    waker = threading.Thread(target=wake)
    waker.start()
    try:
        during()
    finally:
        stop.set()
        waker.join()
    return max(gaps)


def test_big_frames_are_logged_while_other_threads_run(tmp_path):
    with Pipeline("big_frames") as pipe:
        BigFrames() @ Rate(hz=10)
    graph = pipe.compile()
    [node] = graph.nodes.values()
    trace = Trace()
    for k, frame in enumerate(node.flow.frames, 1):
        trace.raw_events.append(((k * 100_000_000, 0), node.id, "out", k, frame, k))
    log = tmp_path / "big.mcap"
    writer = LogWriter(LogFile(log), graph, backend="inproc")

    def write() -> None:
        writer.write(trace)
        writer.close(trace, 300_000_000)

    pause = _longest_pause(write)
    # one copy of a frame under the GIL takes far longer than this; a switch between threads not
    assert pause < 0.1, f"another thread waited {pause * 1000:.0f} ms while the log was written"
    run = read_log(log)
    events = list(run.iter_events())
    assert len(events) == 2
    for k, event in enumerate(events, 1):
        value = run.value(event)
        assert value.shape == (FRAME_MIB * MIB,) and value[0] == k and value[-1] == k
