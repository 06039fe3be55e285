"""One-way latency vs payload size: Retriever on Zenoh, Retriever in-process, raw zenoh-python.

For each payload size (uint8 numpy arrays), in one run of this script:

- ``retriever-zenoh``: ``pipe.run(duration, backend="zenoh")`` of

      src = PayloadSource(size) @ Rate(hz) ──frame──▶ sink = LatencySink() @ Trigger("frame")

  (``benchmarks/zenoh_flows.py``; one worker process each). The source's output is one port,
  ``frame = {"data": array, "sent_ns": time.time_ns()}`` with ``sent_ns`` taken right before
  ``step`` returns; the sink takes ``time.time_ns()`` first thing in its ``step`` and outputs
  ``[sent_ns, received_ns, size]``. Latency = received − sent, measured inside the flows, read
  back from the sink's events in the trace. Both processes read the same system clock.
- ``retriever-inproc``: the same pipeline on the in-process backend (virtual time, one thread,
  as fast as it goes). The same two ``time.time_ns()`` calls measure the *hand-off*: the wall
  time from the source's ``step`` returning to the sink's ``step`` starting — the scheduler's
  work between the two steps (record, deliver, select, invoke). The array is handed over by
  reference: no copy, no encoding, no waiting. It is not a transport latency.
- ``raw-zenoh``: zenoh-python written the plainest way, two processes (this script with
  ``--raw-pub`` / ``--raw-sub``): the subscriber (callback) listens on a loopback TCP port, the
  publisher connects to it; at ``hz`` the publisher updates the array, takes ``time.time_ns()``
  and puts ``array.tobytes()`` with ``[seq, sent_ns]`` as the attachment; the subscriber turns
  the payload back into an array (``np.frombuffer(sample.payload.to_bytes())``) and takes
  ``time.time_ns()``. Same peer mode, same loopback TCP as the Retriever workers.
- ``grouped`` (``--sides ...,grouped``): the retriever-zenoh pipeline with both flows in one
  worker process (``configure(process="both")``): the source's array handed to the sink by
  reference on one thread (node/group.py), no Zenoh between them; the same two clock reads.
- ``raw-iter``: the same, with the plainest subscriber of all: ``for sample in subscriber:``
  over Zenoh's default FIFO channel instead of a callback (a thread hands each sample over).

Per size, each side runs ``--rounds`` times, interleaved (raw, zenoh, inproc, then the reverse
order, ...), so that the machine's drift over a minute falls on all sides alike; each run sends
``--warmup`` + ``--samples``/``--rounds`` messages at ``--hz`` and drops its first ``--warmup``.
Runs never overlap. Reported: median and p99 per side, and retriever-zenoh / raw with a 95%
bootstrap interval (how far the ratio of two medians of this many samples moves by sampling
alone). Target (the issue): retriever-zenoh median ≤ 1.2× raw zenoh at every size; it is judged
with ``--samples 500 --rounds 5``, since the ratio of 100-sample medians moves by ±10% on this VM
(``--control`` shows it on two identical sides). Separately, a source frame the sink did not step
on is listed with its tag against the run's end and its tick's lateness (sent after the end, or
lost), and the last line says whether there was any.

Retriever's coordinator (this process) is not on the frames' path: each worker reports the
data messages it published, with its step records, in a batch up to 20 ms later.
``--raw-hub`` adds a second plain subscriber process to the raw side, to see what a second
subscriber on the path would cost.

Diagnostics: ``--breakdown`` stamps each stage of the path per message (``zenoh_probe.py`` in the
workers; the raw side stamps its own); ``--codec`` times the copy steps of both paths in this
process, with minor page faults, and the cost of a cold call after an idle gap.

    .venv/bin/python benchmarks/latency.py                      # all sizes, about 100 s
    .venv/bin/python benchmarks/latency.py --samples 500 --rounds 5 --control   # the judging run, 11 min
    .venv/bin/python benchmarks/latency.py --sizes 64 1Mi --samples 200
    .venv/bin/python benchmarks/latency.py --breakdown          # where the time goes
    .venv/bin/python benchmarks/latency.py --codec              # copies and page faults, in-process
    .venv/bin/python benchmarks/latency.py --raw-hub --sides raw
    .venv/bin/python benchmarks/latency.py --control            # raw run twice: the run's own noise
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import platform
import socket
import struct
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Iterator

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent))  # run from a checkout without installing
sys.path.insert(0, str(HERE))  # zenoh_flows: the workers get this path from the coordinator

import numpy as np

TARGET_RATIO = 1.2
BOOTSTRAP_RESAMPLES = 2000
DEFAULT_SIZES = ["64", "1Ki", "16Ki", "256Ki", "1Mi", "4Mi", "16Mi"]
ATTACH = struct.Struct("<qq")  # seq, sent_ns


def parse_size(text: str) -> int:
    units = {"Ki": 1 << 10, "Mi": 1 << 20, "Gi": 1 << 30}
    for suffix, mult in units.items():
        if text.endswith(suffix):
            return int(text[: -len(suffix)]) * mult
    return int(text)


def fmt_size(n: int) -> str:
    for suffix, mult in (("MiB", 1 << 20), ("KiB", 1 << 10)):
        if n >= mult and n % mult == 0:
            return f"{n // mult} {suffix}"
    return f"{n} B"


def quantile(sorted_values: list, q: float) -> float:
    """Linear interpolation between closest ranks (numpy's default)."""
    if not sorted_values:
        return float("nan")
    pos = q * (len(sorted_values) - 1)
    lo = int(pos)
    hi = min(lo + 1, len(sorted_values) - 1)
    return sorted_values[lo] + (sorted_values[hi] - sorted_values[lo]) * (pos - lo)


def summary(lat_ns: list[int]) -> dict:
    s = sorted(lat_ns)
    return {"n": len(s), "med": quantile(s, 0.5) / 1e3, "p99": quantile(s, 0.99) / 1e3,
            "min": s[0] / 1e3 if s else float("nan"), "max": s[-1] / 1e3 if s else float("nan"),
            "lat": s}


def ratio_interval(num_ns: list[int], den_ns: list[int], resamples: int = BOOTSTRAP_RESAMPLES) -> tuple[float, float]:
    """95% bootstrap interval of median(num) / median(den): how far the ratio of two medians of
    this many samples moves by sampling alone (seeded, so a result reprints the same)."""
    if not num_ns or not den_ns:
        return float("nan"), float("nan")
    rng = np.random.default_rng(0)
    num, den = np.asarray(num_ns, dtype=float), np.asarray(den_ns, dtype=float)
    ratios = (np.median(rng.choice(num, (resamples, num.size)), axis=1)
              / np.median(rng.choice(den, (resamples, den.size)), axis=1))
    lo, hi = np.percentile(ratios, [2.5, 97.5])
    return float(lo), float(hi)


def free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


# ---------------------------------------------------------------------------------------------
# Raw zenoh-python: the two processes (run as this script with --raw-sub / --raw-pub)
# ---------------------------------------------------------------------------------------------
def _config(listen: str | None = None, connect: str | None = None):
    import zenoh

    c = zenoh.Config()
    c.insert_json5("mode", '"peer"')
    c.insert_json5("scouting/multicast/enabled", "false")
    c.insert_json5("listen/endpoints", json.dumps([listen] if listen else []))
    c.insert_json5("connect/endpoints", json.dumps(connect.split(",") if connect else []))
    pool = os.environ.get("LATENCY_RAW_SHM_POOL")  # --raw-shm-pool, handed to the raw processes
    if pool:
        c.insert_json5("transport/shared_memory/transport_optimization/pool_size", pool)
    return c


def raw_sub(key: str, listen: str, total: int, timeout: float, iterate: bool = False) -> int:
    """Subscribe; on each sample: array from the payload, then the receive time. Print JSON.
    ``iterate``: the plainest subscriber a user writes, ``for sample in subscriber:`` (Zenoh's
    default FIFO channel), rather than a callback."""
    import zenoh

    got: list[tuple[int, int, int, int, int]] = []
    done = threading.Event()

    def on_sample(sample) -> None:
        cb_in = time.time_ns()
        arr = np.frombuffer(sample.payload.to_bytes(), dtype=np.uint8)
        received = time.time_ns()
        seq, sent = ATTACH.unpack(sample.attachment.to_bytes())
        got.append((seq, sent, received, arr.size, cb_in))
        if seq == total - 1:
            done.set()

    with zenoh.open(_config(listen=listen)) as session:
        if iterate:
            sub = session.declare_subscriber(key)

            def drain() -> None:
                for sample in sub:
                    on_sample(sample)
                    if done.is_set():
                        return
            threading.Thread(target=drain, daemon=True).start()
        else:
            sub = session.declare_subscriber(key, on_sample)
        print("READY", flush=True)
        done.wait(timeout)
        sub.undeclare()
    print(json.dumps(got), flush=True)
    return 0


def paced(data: np.ndarray, total: int, hz: float) -> Iterator[tuple[int, int]]:
    """A publisher's ticks: for each seq, sleep to its deadline (every 1/``hz`` from now), mark
    the payload's first bytes with the seq, and give ``(seq, the send time)``."""
    period = round(1e9 / hz)
    deadline = time.time_ns() + period
    for seq in range(total):
        wait = deadline - time.time_ns()
        if wait > 0:
            time.sleep(wait / 1e9)
        data[: min(8, data.size)] = seq % 256
        yield seq, time.time_ns()
        deadline += period


def raw_pub(key: str, connect: str, size: int, total: int, hz: float, subscribers: int, express: bool) -> int:
    """Connect, wait until the subscriber(s) match, then put at ``hz`` to each next deadline."""
    import zenoh

    data = np.zeros(size, dtype=np.uint8)
    puts = []  # (seq, put called, put returned)
    with zenoh.open(_config(connect=connect)) as session:
        pub = session.declare_publisher(key, express=express)
        give_up = time.monotonic() + 20
        while not pub.matching_status.matching and time.monotonic() < give_up:
            time.sleep(0.01)
        time.sleep(0.2 * subscribers)  # let every subscriber's route settle
        for seq, sent in paced(data, total, hz):
            payload = data.tobytes()
            put_in = time.time_ns()  # (only to split tobytes from put in the breakdown)
            pub.put(payload, attachment=ATTACH.pack(seq, sent))
            puts.append((seq, put_in, time.time_ns()))
        time.sleep(0.3)  # let the last samples leave before the session closes
        pub.undeclare()
    print(json.dumps(puts), flush=True)
    return 0


def run_raw(size: int, total: int, hz: float, warmup: int, extra_sub: bool, express: bool = False,
            iterate: bool = False) -> dict:
    key = f"bench/latency/{os.getpid()}/{size}"
    port = free_port()
    listen = f"tcp/127.0.0.1:{port}"
    timeout = total / hz + 30
    me = [sys.executable, str(Path(__file__).resolve())]
    subs = [subprocess.Popen(me + ["--raw-sub-iter" if iterate else "--raw-sub", key, listen, str(total),
                                   str(timeout)], stdout=subprocess.PIPE, text=True)]
    if extra_sub:  # the "hub": a second subscriber, which the publisher also connects to
        port2 = free_port()
        subs.append(subprocess.Popen(me + ["--raw-sub", key, f"tcp/127.0.0.1:{port2}", str(total), str(timeout)],
                                     stdout=subprocess.PIPE, text=True))
    for s in subs:
        if s.stdout.readline().strip() != "READY":
            raise SystemExit("raw subscriber did not start")
    connect = listen + (f",tcp/127.0.0.1:{port2}" if extra_sub else "")
    pub = subprocess.Popen(me + ["--raw-pub", key, connect, str(size), str(total), str(hz), str(len(subs)),
                                 "express" if express else "batched"],
                           stdout=subprocess.PIPE, text=True)
    outs = [json.loads(s.communicate()[0].strip().splitlines()[-1]) for s in subs]
    puts = {seq: (put_in, put_out) for seq, put_in, put_out in json.loads(pub.communicate()[0].strip().splitlines()[-1])}
    got = sorted(outs[0])
    if any(n != size for _, _, _, n, _ in got):
        raise SystemExit("raw subscriber got a payload of the wrong size")
    kept = [g for g in got if g[0] >= warmup and g[0] in puts]
    stages = {  # per message, ns: the raw side's own breakdown (latency.py --breakdown)
        "tobytes": [puts[seq][0] - sent for seq, sent, *_ in kept],
        "put": [puts[seq][1] - puts[seq][0] for seq, *_ in kept],
        "put→callback": [cb_in - puts[seq][0] for seq, _, _, _, cb_in in kept],
        "to_bytes+frombuffer": [r - cb_in for _, _, r, _, cb_in in kept],
        "total": [r - s for _, s, r, _, _ in kept],
    }
    return {"lat": [r - s for _, s, r, _, _ in kept], "received": len(got), "stages": stages}


# ---------------------------------------------------------------------------------------------
# Retriever
# ---------------------------------------------------------------------------------------------
def build(size: int, hz: float, process: str | None = None):
    from zenoh_flows import LatencySink, PayloadSource

    from retriever import Pipeline, Rate, Trigger

    with Pipeline(f"latency_{size}") as pipe:
        PayloadSource(size).configure(name="src", process=process) @ Rate(hz=hz)
        LatencySink().configure(name="sink", process=process) @ Trigger("frame")
        pipe.connect(pipe.flows[0], pipe.flows[1])
    return pipe


def run_retriever(size: int, total: int, hz: float, warmup: int, backend: str) -> dict:
    """``backend``: zenoh, inproc, or grouped (zenoh, both flows in one process)."""
    pipe = build(size, hz, process="both" if backend == "grouped" else None)
    backend = "zenoh" if backend == "grouped" else backend
    options = {"quiet": True} if backend != "inproc" else {}
    trace = pipe.run(duration=total / hz, backend=backend, **options)
    events = sorted((ev for ev in trace.events if ev.node == "sink"), key=lambda ev: ev.seq)
    if any(ev.value[2] != size for ev in events):
        raise SystemExit(f"{backend}: the sink got a payload of the wrong size")
    lat = [ev.value[1] - ev.value[0] for ev in events[warmup:]]
    out = {"lat": lat, "received": len(events), "unseen": _unseen(pipe, trace, events) if backend == "zenoh" else []}
    pipe.reset()
    return out


def _unseen(pipe, trace, sink_events) -> list[str]:
    """Why the sink did not step on some of the source's frames: each such frame's seq, its tag
    against the run's end and how late its source tick started (ms); then how often and how long
    the loops waited for their reporters, if they did."""
    seen = {ev.value[0] for ev in sink_events}
    session = pipe.session
    starts = {st.tag: st.wall_start_ns for st in trace.steps if st.node == "src"}
    produced = {ids[2]: st.tag for st in trace.steps if st.node == "src" for ids in st.produced}
    why = []
    for ev in sorted((ev for ev in trace.events if ev.node == "src"), key=lambda ev: ev.seq):
        if ev.value["sent_ns"] in seen:
            continue
        tick = produced.get(ev.seq)
        late = (starts[tick] - session.t0 - tick[0]) / 1e6 if tick in starts else float("nan")
        why.append(f"retriever-zenoh did not step on frame {ev.seq}: tag {(ev.tag[0] - session.end_ns) / 1e6:+.1f} ms "
                   "from the run's end, "
                   f"its tick started {late:.1f} ms late")
    counts = pipe.counts()
    if why and counts.get("report_waits"):
        why.append(f"the loops waited for their reporters {counts['report_waits']} times, "
                   f"{counts['report_wait_ns'] / 1e6:.0f} ms in all")
    return why


# ---------------------------------------------------------------------------------------------
# --breakdown: the probed pipeline (benchmarks/zenoh_probe.py)
# ---------------------------------------------------------------------------------------------
ZENOH_STAGES = [  # (name, from stamp, to stamp, what happens there)
    ("step→publish", "sent", "publish", "step returns; outputs read; HLC stamp, seq; the tick's end, its frontier"),
    ("encode", "publish", "encoded", "Outputs.encode (codec)"),
    ("put", "put_in", "put_out", "Publisher.put (express) returns, in the source's main thread"),
    ("put→callback", "put_in", "cb_in", "zenoh: tx, loopback TCP, rx; the callback, on Zenoh's rx thread, gets the GIL"),
    ("to_bytes", "cb_in", "cb_out", "sample.payload.to_bytes() in the callback"),
    ("→handle", "cb_out", "handle", "the callback thread takes the idle loop (else inbox, main wakes)"),
    ("decode", "handle", "decoded", "wire.decode_events (msgpack + codec; arrays are views)"),
    ("deliver", "decoded", "delivered", "seq check, frontier, PortBuffer.insert, trigger tag queued"),
    ("→step()", "delivered", "received", "loop: drain, try_tick, waiting, select, invoke"),
    ("total", "sent", "received", "= the latency"),
]


def run_probed(size: int, total: int, hz: float, warmup: int) -> dict:
    from zenoh_probe import SINK_KEYS, SOURCE_KEYS, ProbeSink, ProbeSource

    from retriever import Pipeline, Rate, Trigger

    with Pipeline(f"latency_probe_{size}") as pipe:
        src = ProbeSource(size).named("src") @ Rate(hz=hz)
        sink = ProbeSink().named("sink") @ Trigger("frame")
        pipe.connect(src, sink)
    trace = pipe.run(duration=total / hz, backend="zenoh", quiet=True)
    rows = sorted((ev.value for ev in trace.events if ev.node == "sink"), key=lambda v: v[3])
    pipe.reset()
    src_of = {v[3] - 1: v[4] for v in rows}  # message k+1 carries k's stamps
    stages: dict[str, list[int]] = {name: [] for name, *_ in ZENOH_STAGES}
    faults: dict[str, list[int]] = {"encode": [], "to_bytes": [], "decode": []}
    for sent, received, _, k, _, sink_stamps in rows[warmup:]:
        if k not in src_of:
            continue
        st = {"sent": sent, "received": received, **dict(zip(SOURCE_KEYS, src_of[k])),
              **dict(zip(SINK_KEYS, sink_stamps))}
        for name, a, b, _ in ZENOH_STAGES:
            stages[name].append(st[b] - st[a])
        faults["encode"].append(src_of[k][len(SOURCE_KEYS)] * 1000)  # × 1000: printed by med() in µs units
        faults["to_bytes"].append(sink_stamps[len(SINK_KEYS)] * 1000)
        faults["decode"].append(sink_stamps[len(SINK_KEYS) + 1] * 1000)
    return {"stages": stages, "faults": faults}


def print_breakdown(sizes: list[int], probed: dict, raw: dict) -> None:
    def med(values):
        return quantile(sorted(values), 0.5) / 1e3 if values else float("nan")

    print("retriever-zenoh, per message: median µs of each stage (probed run, benchmarks/zenoh_probe.py)")
    head = f"{'stage':<16} │ " + " ".join(f"{fmt_size(sz):>8}" for sz in sizes) + " │ what"
    print(head)
    print("─" * (len(head) + 40))
    for name, _, _, what in ZENOH_STAGES:
        print(f"{name:<16} │ " + " ".join(f"{med(probed[sz]['stages'][name]):>8.0f}" for sz in sizes) + f" │ {what}")
    for name in ("encode", "to_bytes", "decode"):
        print(f"{'faults: ' + name:<16} │ " + " ".join(f"{med(probed[sz]['faults'][name]):>8.0f}" for sz in sizes)
              + " │ minor page faults of the process during that stage (count, not µs)")
    print("(stages are consecutive except 'put', which lies inside 'put→callback'; medians do not add up exactly)")
    print()
    raw_names = list(next(iter(raw.values()))["stages"])
    print("raw zenoh, per message: median µs of each stage")
    print(f"{'stage':<20} │ " + " ".join(f"{fmt_size(sz):>8}" for sz in sizes))
    print("─" * (23 + 9 * len(sizes)))
    for name in raw_names:
        print(f"{name:<20} │ " + " ".join(f"{med(raw[sz]['stages'][name]):>8.0f}" for sz in sizes))
    print()


# ---------------------------------------------------------------------------------------------
# --codec: the copies of the worker path, in-process
# ---------------------------------------------------------------------------------------------
def codec_costs(sizes: list[int], hz: float, n: int) -> None:
    """Per size, median wall µs and minor page faults of each copy step of both paths, one call
    every 1/hz s (as in the run: between messages the allocator may hand memory back)."""
    import resource

    import zenoh

    from retriever.backends.zenoh.wire import WireEncoder, decode_data

    def faults():
        return resource.getrusage(resource.RUSAGE_SELF).ru_minflt

    enc = WireEncoder()
    steps = [
        ("retriever: WireEncoder.data", "enc"), ("retriever: ZBytes(msg) (put's copy)", "zb"),
        ("retriever: payload.to_bytes()", "tb"), ("retriever: decode_data", "dec"),
        ("raw: arr.tobytes()", "raw_tobytes"), ("raw: ZBytes(bytes) (put's copy)", "raw_zb"),
        ("raw: to_bytes + frombuffer", "raw_recv"),
    ]
    results = {}
    for size in sizes:
        arr = np.zeros(size, dtype=np.uint8)
        times: dict[str, list[int]] = {k: [] for _, k in steps}
        flts: dict[str, list[int]] = {k: [] for _, k in steps}

        def timed(key, fn, *args, times=times, flts=flts):
            f0, t0 = faults(), time.perf_counter_ns()
            r = fn(*args)
            times[key].append(time.perf_counter_ns() - t0)
            flts[key].append(faults() - f0)
            return r

        for i in range(n):
            arr[:8] = i % 256
            value = {"data": arr, "sent_ns": time.time_ns()}
            msg = timed("enc", enc.data, (1, 0), i, (2, 0), "src", "frame", value)
            z = timed("zb", zenoh.ZBytes, msg)
            got = timed("tb", z.to_bytes)
            decoded = timed("dec", decode_data, got, ("src", "frame"))
            del msg, z, got, decoded
            raw = timed("raw_tobytes", arr.tobytes)
            z = timed("raw_zb", zenoh.ZBytes, raw)
            back = timed("raw_recv", lambda z: np.frombuffer(z.to_bytes(), dtype=np.uint8), z)
            del raw, z, back
            time.sleep(1 / hz)
        results[size] = ({k: quantile(sorted(v), 0.5) / 1e3 for k, v in times.items()},
                         {k: quantile(sorted(v), 0.5) for k, v in flts.items()})
        print(f"  {fmt_size(size)} done", flush=True)
    print()
    # the cold-call effect: the same small decode, right after an idle gap of various lengths
    small = enc.data((1, 0), 1, (2, 0), "src", "frame", {"data": np.zeros(64, dtype=np.uint8), "sent_ns": 0})
    cold = {}
    for gap in (0.0, 0.001, 0.01, 0.05):
        firsts, seconds = [], []
        for _ in range(n):
            if gap:
                time.sleep(gap)
            t0 = time.perf_counter_ns()
            decode_data(small)
            t1 = time.perf_counter_ns()
            decode_data(small)
            firsts.append(t1 - t0)
            seconds.append(time.perf_counter_ns() - t1)
        cold[gap] = (quantile(sorted(firsts), 0.5) / 1e3, quantile(sorted(seconds), 0.5) / 1e3)
    print(f"cold calls: decode_data of a 64 B message, median of {n}, after an idle gap (time.sleep) of")
    print("  " + "   ".join(f"{gap * 1e3:g} ms: 1st {a:.1f} µs, 2nd {b:.1f} µs" for gap, (a, b) in cold.items()))
    print()
    print(f"per call, median of {n} (one call every {1e3 / hz:g} ms): µs / minor page faults")
    head = f"{'step':<36} │ " + " ".join(f"{fmt_size(sz):>14}" for sz in sizes)
    print(head)
    print("─" * len(head))
    for name, key in steps:
        print(f"{name:<36} │ " + " ".join(f"{results[sz][0][key]:>8.0f} {results[sz][1][key]:>5.0f}" for sz in sizes))
    print()


# ---------------------------------------------------------------------------------------------
# Driver
# ---------------------------------------------------------------------------------------------
def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if argv and argv[0] in ("--raw-sub", "--raw-sub-iter"):
        return raw_sub(argv[1], argv[2], int(argv[3]), float(argv[4]), iterate=argv[0] == "--raw-sub-iter")
    if argv and argv[0] == "--raw-pub":
        return raw_pub(argv[1], argv[2], int(argv[3]), int(argv[4]), float(argv[5]), int(argv[6]), argv[7] == "express")

    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--sizes", nargs="+", default=DEFAULT_SIZES, metavar="N",
                   help="payload sizes in bytes; suffixes Ki, Mi (default: 64 1Ki 16Ki 256Ki 1Mi 4Mi 16Mi)")
    p.add_argument("--hz", type=float, default=20.0, help="publish rate (default 20)")
    p.add_argument("--samples", type=int, default=100, help="samples kept per size and side (default 100)")
    p.add_argument("--warmup", type=int, default=10, help="first messages dropped (default 10)")
    p.add_argument("--sides", default="raw,raw-iter,zenoh,inproc",
                   help="comma-separated: raw (a callback subscriber), raw-iter (`for sample in subscriber:`), "
                        "zenoh, inproc, grouped (zenoh, both flows in one process)")
    p.add_argument("--control", action="store_true",
                   help="also run raw zenoh a second time per round (side raw2, right after retriever-zenoh) and "
                        "print raw2/raw: the ratio two identical sides reach in this run, i.e. its noise")
    p.add_argument("--rounds", type=int, default=2,
                   help="runs per size and side, interleaved across sides (default 2); the samples are split "
                        "among them and each run drops its own warm-up")
    p.add_argument("--raw-hub", action="store_true",
                   help="diagnostic: a second raw subscriber process (Retriever's coordinator also subscribes)")
    p.add_argument("--raw-shm-pool", action="store_true",
                   help="diagnostic: the raw sessions get the shared-memory pool Retriever's get "
                        "(hub.shm_pool_bytes) instead of Zenoh's default 16 MiB")
    p.add_argument("--raw-express", action="store_true",
                   help="diagnostic: the raw publisher declared with express=True, as Retriever's are")
    p.add_argument("--breakdown", action="store_true",
                   help="diagnostic: instead of the comparison, time each stage of the path per message "
                        "(retriever-zenoh with benchmarks/zenoh_probe.py, and raw zenoh)")
    p.add_argument("--codec", action="store_true",
                   help="diagnostic: time the copy steps of both paths (encode, put's copy, to_bytes, decode) "
                        "in this process, with page fault counts")
    args = p.parse_args(argv)
    sizes = [parse_size(s) for s in args.sizes]
    if args.raw_shm_pool:
        from retriever.backends.zenoh.hub import shm_pool_bytes

        os.environ["LATENCY_RAW_SHM_POOL"] = str(shm_pool_bytes())
    if args.codec:
        print(f"codec and copy costs; load average at start {' '.join(f'{x:.2f}' for x in os.getloadavg())}")
        codec_costs(sizes, args.hz, min(args.samples, 40))
        print(f"load average at end {' '.join(f'{x:.2f}' for x in os.getloadavg())}")
        return 0
    sides = [s.strip() for s in args.sides.split(",") if s.strip()]
    if args.control:
        sides.append("raw2")
    total = args.warmup + args.samples
    if args.breakdown:
        print(f"latency breakdown, {args.hz:g} Hz, {args.warmup} warm-up + {args.samples} samples per size; "
              f"load average at start {' '.join(f'{x:.2f}' for x in os.getloadavg())}"
              + ("; raw side with a 2nd subscriber (--raw-hub)" if args.raw_hub else "")
              + ("; raw publisher express (--raw-express)" if args.raw_express else "")
              + ("; raw sessions with Retriever's shm pool (--raw-shm-pool)" if args.raw_shm_pool else ""))
        probed, raw = {}, {}
        for size in sizes:
            raw[size] = run_raw(size, total, args.hz, args.warmup, args.raw_hub, args.raw_express)
            probed[size] = run_probed(size, total, args.hz, args.warmup)
            print(f"  {fmt_size(size)} done", flush=True)
        print()
        print_breakdown(sizes, probed, raw)
        print(f"load average at end {' '.join(f'{x:.2f}' for x in os.getloadavg())}")
        return 0

    print("retriever latency: one-way, payload size sweep; retriever-zenoh vs raw zenoh-python vs inproc hand-off")
    from importlib.metadata import version

    print(f"python {platform.python_version()}, {platform.machine()}, {platform.system()}, {os.cpu_count()} cpus; "
          f"eclipse-zenoh {version('eclipse-zenoh')}; {datetime.datetime.now().isoformat(timespec='seconds')}")
    print(f"{args.hz:g} Hz, {args.rounds} interleaved rounds per size, each {args.warmup} warm-up + "
          f"{-(-args.samples // args.rounds)} samples per side; "
          f"load average at start {' '.join(f'{x:.2f}' for x in os.getloadavg())}"
          + ("; raw side with a 2nd subscriber (--raw-hub)" if args.raw_hub else "")
          + ("; raw publisher express (--raw-express)" if args.raw_express else "")
          + ("; raw sessions with Retriever's shm pool (--raw-shm-pool)" if args.raw_shm_pool else ""))
    print()

    rows = []
    order = [side for side in ("raw", "raw-iter", "zenoh", "raw2", "inproc", "grouped") if side in sides]
    per_round = args.warmup + -(-args.samples // args.rounds)
    total = per_round * args.rounds
    for size in sizes:
        row = {"size": size}
        t = time.perf_counter()
        lat: dict[str, list] = {side: [] for side in order}
        received = dict.fromkeys(order, 0)
        unseen: list[str] = []
        for r in range(args.rounds):  # interleaved, order reversed every other round: drift hits all sides
            for side in order if r % 2 == 0 else order[::-1]:
                out = (run_raw(size, per_round, args.hz, args.warmup, args.raw_hub, args.raw_express,
                               iterate=side == "raw-iter")
                       if side in ("raw", "raw2", "raw-iter")
                       else run_retriever(size, per_round, args.hz, args.warmup, side))
                lat[side] += out["lat"]
                received[side] += out["received"]
                unseen += out.get("unseen", [])
        for side in order:
            row[side] = {**summary(lat[side]), "received": received[side]}
        rows.append(row)
        parts = [f"{k} med {row[k]['med']:.0f} µs ({row[k]['received']}/{total} received)"
                 for k in ("raw", "raw-iter", "zenoh", "raw2", "inproc", "grouped") if k in row]
        print(f"  {fmt_size(size):>8}: " + ", ".join(parts) + f"  [{time.perf_counter() - t:.1f} s]", flush=True)
        for line in unseen:  # a frame the sink never stepped on: sent after the run's end, or lost?
            print(f"            {line}", flush=True)
    print()

    nan = float("nan")
    head = (f"{'payload':>8} │ {'raw zenoh µs':>15} │ {'retriever-zenoh µs':>18} │ {'zenoh/raw':>23} │ "
            f"{'inproc hand-off µs':>18} │ {'received':>9} │ ≤{TARGET_RATIO:g}× (median)")
    print(head)
    print(f"{'':>8} │ {'median':>7} {'p99':>7} │ {'median':>8} {'p99':>9} │ {'med':>5} {'95% CI':>11} {'p99':>5} │ "
          f"{'median':>8} {'p99':>9} │ {'raw':>4} {'ret':>4} │")
    print("─" * len(head))
    all_ok, short = True, []
    for r in rows:
        raw, zen, inp = (r.get(k, {"med": nan, "p99": nan, "n": 0, "received": 0}) for k in ("raw", "zenoh", "inproc"))
        ratio_med, ratio_p99 = zen["med"] / raw["med"], zen["p99"] / raw["p99"]
        lo, hi = ratio_interval(zen.get("lat", []), raw.get("lat", []))
        both = "raw" in r and "zenoh" in r
        ok = ratio_med <= TARGET_RATIO
        all_ok &= ok or not both
        if both and zen["received"] < raw["received"]:
            short.append(f"{fmt_size(r['size'])}: {zen['received']} of {raw['received']}")
        print(f"{fmt_size(r['size']):>8} │ {raw['med']:>7.0f} {raw['p99']:>7.0f} │ {zen['med']:>8.0f} {zen['p99']:>9.0f} │ "
              f"{ratio_med:>5.2f} {f'{lo:.2f}–{hi:.2f}':>11} {ratio_p99:>5.2f} │ {inp['med']:>8.1f} {inp['p99']:>9.1f} │ "
              f"{raw['received']:>4} {zen['received']:>4} │ {('PASS' if ok else 'MISS') if both else '-'}")
    print()
    if "grouped" in sides:  # (one process: a hand-off on one thread, beside the two processes' latency)
        print("grouped: both flows in one worker process (configure(process=)), the array handed over by reference")
        for r in rows:
            g, zen = r["grouped"], r.get("zenoh", {"med": float("nan")})
            print(f"{fmt_size(r['size']):>8}: median {g['med']:.1f} µs, p99 {g['p99']:.1f} µs "
                  f"({g['received']} received); retriever-zenoh across two processes: median {zen['med']:.0f} µs")
        print()
    if args.control and "raw" in sides:
        print("control: raw zenoh run twice per round (raw2 right after retriever-zenoh); the ratio of two identical")
        print("sides shows how far one run's medians move by themselves:")
        print(f"{'payload':>8} │ {'raw µs':>7} {'raw2 µs':>7} │ {'raw2/raw':>8} {'95% CI':>11} │ {'zenoh/raw2':>10}")
        for r in rows:
            raw, raw2, zen = r["raw"], r["raw2"], r.get("zenoh", {"med": nan})
            lo, hi = ratio_interval(raw2["lat"], raw["lat"])
            print(f"{fmt_size(r['size']):>8} │ {raw['med']:>7.0f} {raw2['med']:>7.0f} │ {raw2['med'] / raw['med']:>8.2f} "
                  f"{f'{lo:.2f}–{hi:.2f}':>11} │ {zen['med'] / raw2['med']:>10.2f}")
        print()
    iter_ok = True
    if "raw-iter" in sides and "zenoh" in sides:
        print("against the plainest subscriber a user writes (`for sample in subscriber:`, Zenoh's FIFO channel):")
        print(f"{'payload':>8} │ {'raw-iter µs':>11} {'raw µs':>7} │ {'zenoh/raw-iter':>14} {'95% CI':>11} │ "
              f"≤{TARGET_RATIO:g}× (median)")
        for r in rows:
            it, raw, zen = r["raw-iter"], r.get("raw", {"med": nan}), r["zenoh"]
            lo, hi = ratio_interval(zen["lat"], it["lat"])
            ok = zen["med"] / it["med"] <= TARGET_RATIO
            iter_ok &= ok
            print(f"{fmt_size(r['size']):>8} │ {it['med']:>11.0f} {raw['med']:>7.0f} │ {zen['med'] / it['med']:>14.2f} "
                  f"{f'{lo:.2f}–{hi:.2f}':>11} │ {'PASS' if ok else 'MISS'}")
        print()
    print("latency = receiver's time.time_ns() with the array in hand − sender's time.time_ns() before the send;")
    print("inproc hand-off = wall time from the source's step returning to the sink's step starting (virtual time,")
    print("one thread, array passed by reference): the in-process scheduler's cost, not a transport latency.")
    print(f"received = messages that arrived, of {total} sent (the first {args.warmup} of each round are dropped "
          "as warm-up);")
    print(f"95% CI = bootstrap interval of the ratio of medians ({BOOTSTRAP_RESAMPLES} resamples of each side's "
          "samples): its spread by sampling alone.")
    print(f"load average at end {' '.join(f'{x:.2f}' for x in os.getloadavg())}")
    if "raw" in sides and "zenoh" in sides:
        print(f"target: retriever-zenoh median <= {TARGET_RATIO:g}x raw zenoh at every size -> "
              f"{'met' if all_ok else 'NOT met'}")
        if "raw-iter" in sides:
            print(f"target: retriever-zenoh median <= {TARGET_RATIO:g}x raw-iter zenoh at every size -> "
                  f"{'met' if iter_ok else 'NOT met'}")
        # not the target, but no less a fault: each is listed above with its cause
        print("every frame stepped on by retriever-zenoh's sink -> "
              + (f"NO ({'; '.join(short)} received)" if short else "yes"))
    return 0


if __name__ == "__main__":
    sys.exit(main())
