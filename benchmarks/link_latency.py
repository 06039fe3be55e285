"""One-way latency of a same-host link (retriever/backends/zenoh/link/) against raw zenoh-python.

Two processes per run, one side at a time, the sides interleaved per size and round (the order
reversed in every other round), so the machine's drift falls on both alike:

- ``link``: the producer process makes a LinkServer in a private folder (8 slots of the payload's
  size, inline below 64 KiB); the consumer process connects with a LinkClient. At ``--hz`` the
  producer updates the array, takes ``time.time_ns()`` and sends the parts ``[seq and sent_ns
  (16 bytes), the array]`` (no join: the array is written into the ring's slot, or the socket,
  straight from its memory); the consumer's ``on_message`` (its receiving thread) makes the array
  back with ``np.frombuffer`` of the bytes it was handed (copied out of the slot) and takes
  ``time.time_ns()``.
- ``raw-zenoh``: latency.py's ``raw-iter``: peer mode, loopback TCP, multicast scouting off; the
  publisher puts ``array.tobytes()`` with ``[seq, sent_ns]`` as the attachment, the subscriber
  iterates ``for sample in subscriber:`` and makes the array with ``np.frombuffer(payload.to_bytes())``.

Latency = received - sent; each run drops its first ``--warmup`` messages. Printed per side and
size: the median of the runs' medians, each run's median, the p10-p90 of all samples, and
link / raw-zenoh per run.

    .venv/bin/python benchmarks/link_latency.py                       # 64 B, 64 KiB, 1 MiB, 4 MiB; ~1 min
    .venv/bin/python benchmarks/link_latency.py --sizes 1Mi --samples 300 --rounds 3
    .venv/bin/python benchmarks/link_latency.py --threshold --sizes 4Ki 16Ki 32Ki 64Ki 120Ki   # inline or ring
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import socket
import statistics
import struct
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent))  # run from a checkout without installing
sys.path.insert(0, str(HERE))

import numpy as np
from latency import _config, paced  # (raw-iter's session settings and pacing)

ATTACH = struct.Struct("<QQ")  # seq, sent_ns
RUN, PRODUCER = "bench", "source"
SIZES = {"64": 64, "64Ki": 64 << 10, "1Mi": 1 << 20, "4Mi": 4 << 20}
UNITS = {"Ki": 1 << 10, "Mi": 1 << 20}


def _collect(total: int):
    got: list[tuple[int, int, int]] = []
    done = threading.Event()

    def on(seq: int, sent: int, received: int) -> None:
        got.append((seq, sent, received))
        if seq == total - 1:
            done.set()
    return got, done, on


# ---------------------------------------------------------------------------------------------
# The link's two processes
# ---------------------------------------------------------------------------------------------
def link_pub(path: str, size: int, total: int, hz: float, inline_below: int) -> None:
    from retriever.backends.zenoh.link import LinkServer

    data = np.zeros(size, dtype=np.uint8)
    with LinkServer(path, RUN, PRODUCER, slots=8, capacity=size + ATTACH.size, inline_below=inline_below) as server:
        print("READY", flush=True)
        if not server.wait_for(1, 30):
            raise SystemExit("no consumer")

        for seq, sent in paced(data, total, hz):
            server.send([ATTACH.pack(seq, sent), data])
        sys.stdin.read()  # until the harness has the consumer's samples


def link_sub(path: str, total: int, timeout: float) -> None:
    from retriever.backends.zenoh.link import LinkClient

    got, done, on = _collect(total)

    def on_message(kind: int, message: bytes) -> None:
        array = np.frombuffer(message, dtype=np.uint8, offset=ATTACH.size)
        received = time.time_ns()
        seq, sent = ATTACH.unpack_from(message)
        assert array.size >= 0
        on(seq, sent, received)

    client = LinkClient(path, RUN, PRODUCER, "sink", on_message, lambda why: done.set())
    done.wait(timeout)
    client.close()
    print(json.dumps(got), flush=True)


# ---------------------------------------------------------------------------------------------
# Raw zenoh-python's two processes (latency.py's raw-iter)
# ---------------------------------------------------------------------------------------------
def zenoh_sub(key: str, listen: str, total: int, timeout: float) -> None:
    import zenoh

    got, done, on = _collect(total)
    with zenoh.open(_config(listen=listen)) as session:
        sub = session.declare_subscriber(key)

        def drain() -> None:
            for sample in sub:
                array = np.frombuffer(sample.payload.to_bytes(), dtype=np.uint8)
                received = time.time_ns()
                seq, sent = ATTACH.unpack(sample.attachment.to_bytes())
                assert array.size >= 0
                on(seq, sent, received)
                if done.is_set():
                    return
        threading.Thread(target=drain, daemon=True).start()
        print("READY", flush=True)
        done.wait(timeout)
        sub.undeclare()
    print(json.dumps(got), flush=True)


def zenoh_pub(key: str, connect: str, size: int, total: int, hz: float) -> None:
    import zenoh

    data = np.zeros(size, dtype=np.uint8)
    with zenoh.open(_config(connect=connect)) as session:
        pub = session.declare_publisher(key)
        give_up = time.monotonic() + 20
        while not pub.matching_status.matching and time.monotonic() < give_up:
            time.sleep(0.01)
        time.sleep(0.2)  # let the subscriber's route settle

        for seq, sent in paced(data, total, hz):
            pub.put(data.tobytes(), attachment=ATTACH.pack(seq, sent))
        time.sleep(0.3)  # let the last samples leave before the session closes
        pub.undeclare()


# ---------------------------------------------------------------------------------------------
# The harness
# ---------------------------------------------------------------------------------------------
def _me(*args: object) -> list[str]:
    return [sys.executable, str(Path(__file__).resolve()), *map(str, args)]


def _samples(out: str, warmup: int) -> tuple[list[int], int]:
    got = json.loads(out.strip().splitlines()[-1])
    return [received - sent for seq, sent, received in got if seq >= warmup], len(got)


def run_link(size: int, total: int, hz: float, warmup: int, inline_below: int = 64 << 10) -> tuple[list[int], int]:
    folder = tempfile.mkdtemp(prefix="link-bench-")
    path = os.path.join(folder, "p.sock")
    try:
        pub = subprocess.Popen(_me("--link-pub", path, size, total, hz, inline_below), stdin=subprocess.PIPE,
                               stdout=subprocess.PIPE, text=True)
        if pub.stdout.readline().strip() != "READY":
            raise SystemExit("the link's producer did not start")
        sub = subprocess.Popen(_me("--link-sub", path, total, total / hz + 30), stdout=subprocess.PIPE, text=True)
        out = sub.communicate()[0]
        pub.communicate("")
        return _samples(out, warmup)
    finally:
        shutil.rmtree(folder, ignore_errors=True)


def run_zenoh(size: int, total: int, hz: float, warmup: int) -> tuple[list[int], int]:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        listen = f"tcp/127.0.0.1:{s.getsockname()[1]}"
    key = f"bench/link/{os.getpid()}/{size}"
    sub = subprocess.Popen(_me("--zenoh-sub", key, listen, total, total / hz + 30), stdout=subprocess.PIPE, text=True)
    if sub.stdout.readline().strip() != "READY":
        raise SystemExit("the zenoh subscriber did not start")
    pub = subprocess.Popen(_me("--zenoh-pub", key, listen, size, total, hz))
    out = sub.communicate()[0]
    pub.wait()
    return _samples(out, warmup)


def _size(text: str) -> int:
    unit = UNITS.get(text[-2:], 1)
    return int(text[:-2] if unit > 1 else text) * unit


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--sizes", nargs="+", default=list(SIZES))
    p.add_argument("--samples", type=int, default=100, help="per side and size, over all rounds")
    p.add_argument("--rounds", type=int, default=2)
    p.add_argument("--hz", type=float, default=50.0)
    p.add_argument("--warmup", type=int, default=10)
    p.add_argument("--threshold", action="store_true",
                   help="compare the link's two routes instead: link-inline (every message through the socket) "
                        "against link-ring (every message through the ring), for sizes up to 128 KiB")
    args = p.parse_args()
    per_run = max(1, args.samples // args.rounds)
    total = args.warmup + per_run
    sides = {"link": run_link, "raw-zenoh": run_zenoh}
    if args.threshold:
        sides = {"link": lambda *a: run_link(*a, inline_below=0),  # the ring (the ratio's numerator)
                 "link-inline": lambda *a: run_link(*a, inline_below=128 << 10)}
    results: dict[tuple[str, str], list[tuple[list[int], int]]] = {}
    for size in args.sizes:
        for round_ in range(args.rounds):
            order = list(sides) if round_ % 2 == 0 else list(sides)[::-1]
            for side in order:
                results.setdefault((side, size), []).append(sides[side](_size(size), total, args.hz, args.warmup))
    print(f"load {os.getloadavg()[0]:.2f}; {per_run} samples per run, {args.rounds} rounds, {args.hz:g} Hz")
    other = list(sides)[1]
    print(f"{'size':>6} {'side':>11} │ {'median µs':>9} {'(per run)':<22} {'p10–p90 µs':>13} {'received':>9} │ "
          f"link/{other}" + (" (link: every message through the ring)" if args.threshold else ""))
    for size in args.sizes:
        medians = {}
        for side in sides:
            runs = results[(side, size)]
            medians[side] = [statistics.median(lat) / 1e3 for lat, _ in runs]
            every = sorted(x / 1e3 for lat, _ in runs for x in lat)
            p10, p90 = every[len(every) // 10], every[len(every) * 9 // 10]
            received = f"{sum(n for _, n in runs)}/{total * len(runs)}"
            per = ", ".join(f"{m:.0f}" for m in medians[side])
            ratio = "" if side == "link" else ", ".join(f"{a / b:.2f}" for a, b in zip(medians["link"], medians[side]))
            pad = " " * max(0, 20 - len(per))
            print(f"{size:>6} {side:>11} │ {statistics.median(medians[side]):9.0f} ({per}){pad} "
                  f"{p10:6.0f}–{p90:<6.0f} {received:>9} │ {ratio}")
    return 0


if __name__ == "__main__":
    if len(sys.argv) > 1 and sys.argv[1].startswith("--") and sys.argv[1][2:] in (
            "link-pub", "link-sub", "zenoh-pub", "zenoh-sub"):
        command, rest = sys.argv[1], sys.argv[2:]
        if command == "--link-pub":
            link_pub(rest[0], int(rest[1]), int(rest[2]), float(rest[3]), int(rest[4]))
        elif command == "--link-sub":
            link_sub(rest[0], int(rest[1]), float(rest[2]))
        elif command == "--zenoh-pub":
            zenoh_pub(rest[0], rest[1], int(rest[2]), int(rest[3]), float(rest[4]))
        else:
            zenoh_sub(rest[0], rest[1], int(rest[2]), float(rest[3]))
        raise SystemExit(0)
    raise SystemExit(main())
