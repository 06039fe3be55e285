"""Latency benchmark with Retriever: 100 payloads of each size, 64 B ... 16 MiB, at 20 Hz."""

import csv
import os
import sys
import time
from dataclasses import dataclass

import numpy as np

from retriever import Flow, Pipeline, Rate, Trigger, io

SIZES = [2**i for i in range(6, 25)]
POINTS = int(os.environ.get("POINTS", "100"))


@io
@dataclass
class Payload:
    data: np.ndarray
    sent_ns: int


class Source(Flow[None, Payload]):
    def __init__(self):
        self.k = 0

    def step(self, _):
        if self.k == POINTS * len(SIZES):
            sys.exit(0)  # done: ends the run
        data = np.zeros(SIZES[self.k // POINTS], dtype=np.uint8)
        self.k += 1
        return Payload(data=data, sent_ns=time.time_ns())


class Sink(Flow[Payload, None]):
    def __init__(self, out: str):
        self.out = out

    def setup(self):
        self.file = open(self.out, "w", newline="")
        self.rows = csv.writer(self.file)
        self.rows.writerow(["size", "latency_ns"])

    def step(self, p: Payload):
        self.rows.writerow([p.data.size, time.time_ns() - p.sent_ns])

    def teardown(self):
        self.file.close()


if __name__ == "__main__":
    with Pipeline("latency", deadline=5.0) as pipe:  # frames still in flight at the end: wait up to 5 s
        (Source() @ Rate(hz=20)).then(Sink(os.environ.get("OUT", "latency.csv")) @ Trigger("data"))
    pipe.run(duration=3600, backend=os.environ.get("BACKEND", "zenoh"))
