"""Latency benchmark with dora, publisher: 100 payloads of each size, 64 B ... 16 MiB, at 20 Hz."""

import os
import time

import numpy as np
import pyarrow as pa
from dora import Node

SIZES = [2**i for i in range(6, 25)]
POINTS = int(os.environ.get("POINTS", "100"))

node = Node()
sent = 0
for event in node:
    if event["type"] != "INPUT":
        continue
    if sent == POINTS * len(SIZES):
        break
    data = np.zeros(SIZES[sent // POINTS], dtype=np.uint8)
    node.send_output("payload", pa.array(data), {"sent_ns": time.time_ns()})
    sent += 1
