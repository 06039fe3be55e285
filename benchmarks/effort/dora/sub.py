"""Latency benchmark with dora, subscriber: one CSV row per payload received."""

import csv
import os
import time

from dora import Node

node = Node()
with open(os.environ.get("OUT", "latency.csv"), "w", newline="") as file:
    rows = csv.writer(file)
    rows.writerow(["size", "latency_ns"])
    for event in node:
        if event["type"] == "INPUT":
            received = time.time_ns()
            rows.writerow([len(event["value"]), received - event["metadata"]["sent_ns"]])
