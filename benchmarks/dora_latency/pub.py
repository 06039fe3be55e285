"""dora-rs, written the plainest way: on each timer tick, send a uint8 array of SIZE bytes with
its send time (``time.time_ns()``) in the metadata; stop after TOTAL messages."""

import os
import time

import numpy as np
import pyarrow as pa
from dora import Node

SIZE, TOTAL = int(os.environ["SIZE"]), int(os.environ["TOTAL"])

node = Node()
data = np.zeros(SIZE, dtype=np.uint8)
seq = 0
for event in node:
    if event["type"] == "INPUT" and event["id"] == "tick":
        data[: min(8, SIZE)] = seq % 256
        node.send_output("data", pa.array(data), {"seq": seq, "sent_ns": time.time_ns()})
        seq += 1
        if seq == TOTAL:
            break
