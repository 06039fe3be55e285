"""Diagnostic probes for latency.py --breakdown: where a message's time goes in the zenoh worker path.

Importing this module in a worker process (the workers import it to rebuild ``ProbeSource`` and
``ProbeSink``) wraps a few methods of the worker's node loop with ``time.time_ns()`` stamps. It
does not change what they do, and the coordinator never runs a node loop, so the patches matter
only inside the workers of a probed run. Stamps (wall ns, the same clock in every process):

    source worker                                    sink worker
    sent      step() takes time.time_ns()            cb_in     zenoh callback entered (network thread)
    publish   NodeLoop._publish entered               cb_out    payload.to_bytes() returned
    encoded   WireEncoder.data returned               handle    NodeLoop._handle entered (callback or main thread)
    put_in    Publisher.put called                    decoded   wire.decode_events returned
    put_out   Publisher.put returned                  delivered NodeLoop._deliver returned (PortBuffer.insert)
                                                      received  sink's step() starts

Page faults (``ru_minflt`` of the process) are counted around encode, to_bytes and decode: on
this VM a first touch of fresh memory costs a few µs per 4 KiB page, so fresh buffers dominate
the cost of large copies.

The source has its stamps of message k only after sending it, so message k+1 carries them
(``frame["probe_prev"]``); the sink outputs its own stamps with each measurement.
"""

from __future__ import annotations

import resource
import time
from collections import deque

from zenoh_flows import Frame, Lat, PayloadSource

import retriever.backends.zenoh.loop as _loop
from retriever import Flow

STAMPS: dict[str, int] = {}
FAULTS: dict[str, int] = {}  # minor page faults of the process (ru_minflt) at some of the stamps
# sink side, one dict of stamps per data message, in arrival order (a burst of messages handled
# before the next tick must not overwrite each other's stamps)
ARRIVED: deque = deque()  # callback done, not handled yet
HANDLED: deque = deque()  # handled (callback or main thread), its step not yet run
_current: list = [None]
_now = time.time_ns


def _flt() -> int:
    return resource.getrusage(resource.RUSAGE_SELF).ru_minflt


def _install() -> None:
    if getattr(_loop, "_bench_probed", False):
        return
    _loop._bench_probed = True
    NodeLoop = _loop.NodeLoop

    # --- source side -----------------------------------------------------------------------
    orig_publish = NodeLoop._publish

    def _publish(self, batch):
        if batch:
            FAULTS["publish"] = _flt()
            STAMPS["publish"] = _now()
        return orig_publish(self, batch)

    NodeLoop._publish = _publish

    orig_data = _loop.WireEncoder.data

    def data(self, *args):
        out = orig_data(self, *args)
        STAMPS["encoded"] = _now()
        FAULTS["encoded"] = _flt()
        return out

    _loop.WireEncoder.data = data

    class TimedPublisher:
        def __init__(self, pub):
            self._pub = pub

        def put(self, payload, **kw):
            STAMPS["put_in"] = _now()
            self._pub.put(payload, **kw)
            STAMPS["put_out"] = _now()

        def undeclare(self):
            self._pub.undeclare()

    # --- sink side -------------------------------------------------------------------------
    class PayloadProxy:
        def __init__(self, payload):
            self._p = payload

        def to_bytes(self):
            out = self._p.to_bytes()
            self.rec["cb_out"] = _now()  # then the callback handles it, or queues it for the main thread
            self.rec["f_cb_out"] = _flt()
            ARRIVED.append(self.rec)
            return out

    class SampleProxy:
        def __init__(self, sample, rec):
            self.payload = PayloadProxy(sample.payload)
            self.payload.rec = rec

    class SessionProxy:
        """Wraps data-subscriber callbacks with entry/exit stamps during declare()."""

        def __init__(self, session, data_prefix):
            self._s, self._prefix = session, data_prefix

        def __getattr__(self, name):
            return getattr(self._s, name)

        def declare_subscriber(self, key, cb, **kw):
            if not str(key).startswith(self._prefix):
                return self._s.declare_subscriber(key, cb, **kw)

            def timed(sample, cb=cb):
                rec = {"f_cb_in": _flt(), "cb_in": _now()}
                cb(SampleProxy(sample, rec))

            return self._s.declare_subscriber(key, timed, **kw)

    orig_declare = NodeLoop.declare

    def declare(self):
        real = self.session
        self.session = SessionProxy(real, self.keys.prefix + "/data/")
        try:
            orig_declare(self)
        finally:
            self.session = real
        self.publishers = {port: TimedPublisher(p) for port, p in self.publishers.items()}

    NodeLoop.declare = declare

    orig_handle = NodeLoop._handle

    def _handle(self, item):
        if item[0] == _loop._DATA:
            rec = ARRIVED.popleft() if ARRIVED else {}
            rec["f_handle"] = _flt()
            rec["handle"] = _now()
            _current[0] = rec
            orig_handle(self, item)
            rec["delivered"] = _now()
            _current[0] = None
            HANDLED.append(rec)
        else:
            orig_handle(self, item)

    NodeLoop._handle = _handle

    orig_decode = _loop.decode_events

    def decode_events(data, expected=None):
        out = orig_decode(data, expected=expected)
        rec = _current[0]
        if rec is not None:
            rec["decoded"] = _now()
            rec["f_decoded"] = _flt()
        return out

    _loop.decode_events = decode_events

    # --- timed waits (control_jitter.py --breakdown) -------------------------------------------
    orig_wait = NodeLoop._wait

    def _wait(self, ns):
        STAMPS["wait_for"] = ns
        STAMPS["wait_until"] = _now() + ns if ns > 0 else 0
        orig_wait(self, ns)
        STAMPS["woke"] = _now()

    NodeLoop._wait = _wait


_install()

SOURCE_KEYS = ("publish", "encoded", "put_in", "put_out")
SINK_KEYS = ("cb_in", "cb_out", "handle", "decoded", "delivered")


class ProbeSource(PayloadSource):
    def step(self) -> Frame:
        self.k += 1
        self.data[: min(8, self.size)] = self.k % 256
        prev = [STAMPS.get(k, 0) for k in SOURCE_KEYS] + [FAULTS.get("encoded", 0) - FAULTS.get("publish", 0)]
        return Frame(frame={"data": self.data, "k": self.k, "probe_prev": prev, "sent_ns": time.time_ns()})


class ProbeSink(Flow[Frame, Lat]):
    """Outputs [sent, received, size, k, source stamps (+ encode faults) of message k-1,
    sink stamps (+ to_bytes and decode faults) of message k]."""

    def step(self, inp: Frame) -> Lat:
        received = time.time_ns()
        f = inp.frame
        rec = HANDLED.popleft() if HANDLED else {}
        while HANDLED and len(HANDLED) > 64:  # (never: one tick per handled message)
            HANDLED.popleft()
        return Lat(lat=[f["sent_ns"], received, int(f["data"].size), f["k"], f["probe_prev"],
                        [rec.get(k, 0) for k in SINK_KEYS]
                        + [rec.get("f_cb_out", 0) - rec.get("f_cb_in", 0),
                           rec.get("f_decoded", 0) - rec.get("f_handle", 0)]])



# --- idle_cpu.py --profile: main-thread CPU time per NodeLoop method ------------------------------
CPU_NS: dict[str, int] = {}
CALLS: dict[str, int] = {}


def install_cpu_profile(path: str) -> None:
    """Accumulate the main thread's CPU time (time.thread_time_ns) inside a few NodeLoop methods
    (outermost call only) and write it as JSON to ``path`` when the worker exits."""
    import atexit
    import json
    import threading

    NodeLoop = _loop.NodeLoop
    main = threading.main_thread()
    depth = [0]

    def wrap(name):
        orig = getattr(NodeLoop, name)

        def timed(self, *a, **kw):
            if threading.current_thread() is not main or depth[0]:
                return orig(self, *a, **kw)
            depth[0] += 1
            t = time.thread_time_ns()
            try:
                return orig(self, *a, **kw)
            finally:
                CPU_NS[name] = CPU_NS.get(name, 0) + time.thread_time_ns() - t
                CALLS[name] = CALLS.get(name, 0) + 1
                depth[0] -= 1

        setattr(NodeLoop, name, timed)

    for name in ("_drain", "_release", "_try_tick", "flush", "_wait"):
        wrap(name)
    orig_run = NodeLoop.run

    def run(self, *a, **kw):
        t, w = time.thread_time_ns(), time.monotonic_ns()
        try:
            return orig_run(self, *a, **kw)
        finally:
            CPU_NS["run (main thread, total)"] = time.thread_time_ns() - t
            CPU_NS["run (wall)"] = time.monotonic_ns() - w
            CALLS["ticks"] = self.k

    NodeLoop.run = run

    def dump():
        with open(path, "w") as f:
            json.dump({"cpu_ns": CPU_NS, "calls": CALLS}, f)

    atexit.register(dump)


class ProbeIdle(Flow):
    """Idle (does nothing, outputs nothing); in a worker, with RETRIEVER_BENCH_CPU_PROFILE=<dir>
    set, it profiles the node loop's main thread (install_cpu_profile) into <dir>/<pid>.json."""

    def __init__(self):
        import os
        import sys

        out = os.environ.get("RETRIEVER_BENCH_CPU_PROFILE")
        spec = getattr(sys.modules["__main__"], "__spec__", None)
        in_worker = spec is not None and spec.name == "retriever.backends.zenoh.worker"
        if out and in_worker and not getattr(_loop, "_bench_cpu_profiled", False):
            _loop._bench_cpu_profiled = True
            install_cpu_profile(os.path.join(out, f"{os.getpid()}.json"))

    def step(self):
        return None


class ProbeTicker(Flow[None, Lat]):
    """For control_jitter.py --breakdown: outputs, each tick, [wait_until, woke, step_start] of the
    node loop's last timed wait before this step (wall ns; wait_until 0 if it did not wait)."""

    def step(self) -> Lat:
        start = time.time_ns()
        return Lat(lat=[STAMPS.get("wait_until", 0), STAMPS.get("woke", 0), start])


__all__ = ["ProbeIdle", "ProbeSink", "ProbeSource", "ProbeTicker", "install_cpu_profile"]
