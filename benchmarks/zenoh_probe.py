"""Diagnostic probes for latency.py --breakdown: where a message's time goes in the zenoh worker path.

Importing this module in a worker process (the workers import it to rebuild ``ProbeSource`` and
``ProbeSink``) wraps a few public methods of the node loop's parts (``retriever.backends.zenoh.node``)
with ``time.time_ns()`` stamps. It does not change what they do, and the coordinator never runs a
node loop, so the wrappers matter only inside the workers of a probed run. Stamps (wall ns, the
same clock in every process):

    source worker                                    sink worker
    sent      step() takes time.time_ns()            cb_in     zenoh callback entered (network thread)
    publish   Outputs.publish entered                cb_out    payload.to_bytes() returned
    encoded   WireEncoder.data returned               handle    NodeLoop.handle entered (callback or main thread)
    put_in    Publisher.put called                    decoded   wire.decode_events returned
    put_out   Publisher.put returned                  delivered Streams.deliver returned (PortBuffer.insert)
                                                      received  sink's step() starts

``decoded`` is taken as ``Streams.check_claims`` is entered, which the loop calls on the decoded
events first. The publishers and subscriptions are the node's transport's (``ZenohTransport.declare_outputs``
and ``declare_inputs``): the probe times what those return and the callbacks they install.
Page faults (``ru_minflt`` of the process) are counted around encode, to_bytes and decode: a first
touch of fresh memory costs a few µs per 4 KiB page, so fresh buffers dominate the cost of large
copies.

The source has its stamps of message k only after sending it, so message k+1 carries them
(``frame["probe_prev"]``); the sink outputs its own stamps with each measurement.
"""

from __future__ import annotations

import resource
import time
from collections import deque

from zenoh_flows import Frame, Lat, PayloadSource

from retriever import Flow
from retriever.backends.zenoh import node, wire
from retriever.backends.zenoh.node.frontiers import Streams
from retriever.backends.zenoh.node.outputs import Outputs
from retriever.backends.zenoh.node.reports import Reports

STAMPS: dict[str, int] = {}
FAULTS: dict[str, int] = {}  # minor page faults of the process (ru_minflt) at some of the stamps
# sink side, one dict of stamps per data message, in arrival order (a burst of messages handled
# before the next tick must not overwrite each other's stamps)
ARRIVED: deque = deque()  # callback done, not handled yet
HANDLED: deque = deque()  # handled (callback or main thread), its step not yet run
_current: list = [None]
_now = time.time_ns
#: whether this process's node loop classes are wrapped already (install once per process)
_installed: dict[str, bool] = {}


def _flt() -> int:
    return resource.getrusage(resource.RUSAGE_SELF).ru_minflt


class TimedPublisher:
    """A transport's publisher, its puts stamped (put_in, put_out)."""

    def __init__(self, pub):
        self.pub = pub

    def put(self, payload, **kw):
        STAMPS["put_in"] = _now()
        self.pub.put(payload, **kw)
        STAMPS["put_out"] = _now()

    def undeclare(self):
        self.pub.undeclare()


class PayloadProxy:
    """A received sample's payload: ``to_bytes`` returning is cb_out."""

    def __init__(self, payload, rec: dict):
        self.payload, self.rec = payload, rec

    def to_bytes(self):
        out = self.payload.to_bytes()
        self.rec["cb_out"] = _now()  # then the callback handles it, or queues it for the main thread
        self.rec["f_cb_out"] = _flt()
        ARRIVED.append(self.rec)
        return out


class SampleProxy:
    def __init__(self, sample, rec: dict):
        self.payload = PayloadProxy(sample.payload, rec)


class SessionProxy:
    """The transport's session while it declares its inputs: data subscribers' callbacks stamped
    on entry (cb_in); everything else the session's own."""

    def __init__(self, session, data_prefix: str):
        self.session, self.prefix = session, data_prefix

    def __getattr__(self, name):
        return getattr(self.session, name)

    def declare_subscriber(self, key, cb, **kw):
        if not str(key).startswith(self.prefix):
            return self.session.declare_subscriber(key, cb, **kw)

        def timed(sample, cb=cb):
            rec = {"f_cb_in": _flt(), "cb_in": _now()}
            cb(SampleProxy(sample, rec))

        return self.session.declare_subscriber(key, timed, **kw)


def _install() -> None:
    if _installed.get("stamps"):
        return
    _installed["stamps"] = True
    Transport, NodeLoop = node.ZenohTransport, node.NodeLoop

    # --- source side -----------------------------------------------------------------------
    publish = Outputs.publish

    def timed_publish(self, batch):
        if batch:
            FAULTS["publish"] = _flt()
            STAMPS["publish"] = _now()
        return publish(self, batch)

    Outputs.publish = timed_publish

    encode = wire.WireEncoder.data

    def timed_data(self, *args):
        out = encode(self, *args)
        STAMPS["encoded"] = _now()
        FAULTS["encoded"] = _flt()
        return out

    wire.WireEncoder.data = timed_data

    declare_outputs = Transport.declare_outputs

    def timed_outputs(self, ports, consumed):
        publishers, progress, warm = declare_outputs(self, ports, consumed)
        return {port: TimedPublisher(p) for port, p in publishers.items()}, progress, warm

    Transport.declare_outputs = timed_outputs

    # --- sink side -------------------------------------------------------------------------
    declare_inputs = Transport.declare_inputs

    def timed_inputs(self, streams, sources, inline, put):
        real = self.session
        self.session = SessionProxy(real, self.keys.prefix + "/data/")
        try:
            declare_inputs(self, streams, sources, inline, put)
        finally:
            self.session = real

    Transport.declare_inputs = timed_inputs

    handle = NodeLoop.handle

    def timed_handle(self, item):
        if item[0] != node.DATA:
            return handle(self, item)
        rec = ARRIVED.popleft() if ARRIVED else {}
        rec["f_handle"] = _flt()
        rec["handle"] = _now()
        _current[0] = rec
        try:
            return handle(self, item)
        finally:
            _current[0] = None
            HANDLED.append(rec)

    NodeLoop.handle = timed_handle

    check_claims = Streams.check_claims

    def timed_check_claims(self, stream, seq, frontier):
        rec = _current[0]
        if rec is not None and "decoded" not in rec:  # (a data message's: the first after decode_events)
            rec["decoded"] = _now()
            rec["f_decoded"] = _flt()
        return check_claims(self, stream, seq, frontier)

    Streams.check_claims = timed_check_claims

    deliver = Streams.deliver

    def timed_deliver(self, e, msg):
        deliver(self, e, msg)
        rec = _current[0]
        if rec is not None:
            rec["delivered"] = _now()

    Streams.deliver = timed_deliver

    # --- timed waits (control_jitter.py --breakdown) -------------------------------------------
    wait = NodeLoop.wait

    def timed_wait(self, ns):
        STAMPS["wait_for"] = ns
        STAMPS["wait_until"] = _now() + ns if ns > 0 else 0
        try:
            return wait(self, ns)
        finally:
            STAMPS["woke"] = _now()

    NodeLoop.wait = timed_wait


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



# --- idle_cpu.py --profile: main-thread CPU time per method of the node loop ------------------------
CPU_NS: dict[str, int] = {}
CALLS: dict[str, int] = {}
#: what the profile times: its name in the profile, the class, the method
PROFILED = (("drain", "NodeLoop", "drain"), ("release", "Outputs", "release"), ("try_tick", "NodeLoop", "try_tick"),
            ("flush", "Reports", "flush"), ("wait", "NodeLoop", "wait"))


def install_cpu_profile(path: str) -> None:
    """Accumulate the main thread's CPU time (time.thread_time_ns) inside the methods PROFILED
    names (outermost call only) and write it as JSON to ``path`` when the worker exits."""
    import atexit
    import json
    import threading

    classes = {"NodeLoop": node.NodeLoop, "Outputs": Outputs, "Reports": Reports}
    main = threading.main_thread()
    depth = [0]

    def wrap(label, cls, name):
        orig = getattr(cls, name)

        def timed(self, *a, **kw):
            if threading.current_thread() is not main or depth[0]:
                return orig(self, *a, **kw)
            depth[0] += 1
            t = time.thread_time_ns()
            try:
                return orig(self, *a, **kw)
            finally:
                CPU_NS[label] = CPU_NS.get(label, 0) + time.thread_time_ns() - t
                CALLS[label] = CALLS.get(label, 0) + 1
                depth[0] -= 1

        setattr(cls, name, timed)

    for label, cls, name in PROFILED:
        wrap(label, classes[cls], name)
    run = node.NodeLoop.run

    def timed_run(self, *a, **kw):
        t, w = time.thread_time_ns(), time.monotonic_ns()
        try:
            return run(self, *a, **kw)
        finally:
            CPU_NS["run (main thread, total)"] = time.thread_time_ns() - t
            CPU_NS["run (wall)"] = time.monotonic_ns() - w
            CALLS["ticks"] = self.schedule.k

    node.NodeLoop.run = timed_run

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
        if out and in_worker and not _installed.get("profile"):
            _installed["profile"] = True
            install_cpu_profile(os.path.join(out, f"{os.getpid()}.json"))

    def step(self):
        return None


class ProbeTicker(Flow[None, Lat]):
    """For control_jitter.py --breakdown: outputs, each tick, [wait_until, woke, step_start] of the
    node loop's last timed wait before this step (wall ns; wait_until 0 if it did not wait)."""

    def step(self) -> Lat:
        start = time.time_ns()
        return Lat(lat=[STAMPS.get("wait_until", 0), STAMPS.get("woke", 0), start])


__all__ = ["PROFILED", "ProbeIdle", "ProbeSink", "ProbeSource", "ProbeTicker", "install_cpu_profile"]
