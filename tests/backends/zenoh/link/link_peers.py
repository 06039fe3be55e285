"""A link's producer or consumer in a process of its own, for the link's tests.

    python link_peers.py consume PATH RUN PRODUCER NAME
        prints "ready", then a JSON line per message ({"kind", "index", "len", "sha"}) and
        {"closed": why} at the end of the connection; ends at its stdin's end
    python link_peers.py produce PATH RUN PRODUCER CONSUMERS SIZE...
        prints "ready", waits for CONSUMERS consumers, sends message(i, size) for each size, prints
        "sent", then waits for its stdin's end
    python link_peers.py short-of-fds PATH RUN PRODUCER SPARE
        a producer (its handshakes' timeout 1 s) whose process may open SPARE more fds: prints
        "ready", then "admitted" once a consumer is, and waits for its stdin's end
"""

from __future__ import annotations

import hashlib
import json
import os
import resource
import sys

import numpy as np

from retriever.backends.zenoh.link import LinkClient, LinkServer


def message(index: int, size: int) -> list:
    """Message ``index`` of ``size`` bytes (>= 8), as parts: an 8-byte head and an array."""
    body = ((np.arange(size - 8, dtype=np.uint32) + index) % 251).astype(np.uint8)
    return [index.to_bytes(8, "little"), body]


def digest(index: int, size: int) -> str:
    return hashlib.sha256(b"".join(bytes(part) for part in message(index, size))).hexdigest()


def _print(line: object) -> None:
    sys.stdout.write((line if isinstance(line, str) else json.dumps(line)) + "\n")
    sys.stdout.flush()


def consume(path: str, run: str, producer: str, name: str) -> None:
    def on_message(kind: int, data: bytes) -> None:
        _print({"kind": kind, "index": int.from_bytes(data[:8], "little"), "len": len(data),
                "sha": hashlib.sha256(data).hexdigest()})

    client = LinkClient(path, run, producer, name, on_message, lambda why: _print({"closed": str(why)}))
    _print("ready")
    sys.stdin.read()
    client.close()


def produce(path: str, run: str, producer: str, consumers: int, sizes: list[int]) -> None:
    with LinkServer(path, run, producer, slots=2, capacity=max(sizes)) as server:
        _print("ready")
        if not server.wait_for(consumers, 30):
            raise SystemExit("no consumers")
        for index, size in enumerate(sizes):
            server.send(message(index, size), kind=index % 3)
        _print("sent")
        sys.stdin.read()


def short_of_fds(path: str, run: str, producer: str, spare: int) -> None:
    with LinkServer(path, run, producer, slots=2, capacity=4096, handshake_timeout=1.0) as server:
        highest = max(int(fd) for fd in os.listdir("/proc/self/fd"))
        resource.setrlimit(resource.RLIMIT_NOFILE, (highest + 1 + spare, resource.getrlimit(resource.RLIMIT_NOFILE)[1]))
        _print("ready")
        if not server.wait_for(1, 60):
            raise SystemExit("no consumer admitted")
        _print("admitted")
        sys.stdin.read()


if __name__ == "__main__":
    if sys.argv[1] == "consume":
        consume(*sys.argv[2:6])
    elif sys.argv[1] == "short-of-fds":
        short_of_fds(*sys.argv[2:5], int(sys.argv[5]))
    else:
        produce(*sys.argv[2:5], int(sys.argv[5]), [int(size) for size in sys.argv[6:]])
