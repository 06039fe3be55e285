"""Diagnostic probes for latency.py --breakdown: where a message's time goes in the zenoh worker path.

A probe flow built in a worker process (``ProbeSource``, ``ProbeSink``, ``ProbeTicker``) stamps,
with ``time.time_ns()``, the stages of that process's node loop (``retriever.backends.zenoh.node``)
from outside it: the puts and the data callbacks through the transport's public tap
(``tap_transports``), the rest by a profile function (``sys.setprofile``) on the loop's threads
that looks for the entry or the return of a few of the loop's methods (by their code objects)
and changes nothing they do. It runs on every Python call of those threads, so each stage is a
little longer than unprobed (about a microsecond per call it makes). Nothing is probed in the
coordinator's process: only a worker runs a node loop. Stamps (wall ns, the same clock in every
process):

    source worker                                    sink worker
    sent      step() takes time.time_ns()            cb_in     zenoh callback entered (network thread)
    publish   Outputs.publish entered                cb_out    payload.to_bytes() returned
    encoded   Outputs.encode returned                handle    NodeLoop.handle entered (callback or main thread)
    put_in    Publisher.put called                    decoded   wire.decode_events returned
    put_out   Publisher.put returned                  delivered Streams.deliver returned (PortBuffer.insert)
                                                      received  sink's step() starts

``decoded`` is taken as ``Streams.check_claims`` is entered, which the loop calls on the decoded
events first. Page faults (``ru_minflt`` of the process) are counted around encode, to_bytes and
decode: a first touch of fresh memory costs a few µs per 4 KiB page, so fresh buffers dominate
the cost of large copies.

The source has its stamps of message k only after sending it, so message k+1 carries them
(``frame["probe_prev"]``); the sink outputs its own stamps with each measurement.
"""

from __future__ import annotations

import resource
import sys
import threading
import time
from collections import deque

from zenoh_flows import Frame, Lat, PayloadSource

from retriever import Flow
from retriever.backends.zenoh import node
from retriever.backends.zenoh.node.frontiers import Streams
from retriever.backends.zenoh.node.outputs import Outputs
from retriever.backends.zenoh.node.reports import Reports
from retriever.backends.zenoh.node.transport import Tap, tap_transports

STAMPS: dict[str, int] = {}
FAULTS: dict[str, int] = {}  # minor page faults of the process (ru_minflt) at some of the stamps
# sink side, one dict of stamps per data message, in arrival order (a burst of messages handled
# before the next tick must not overwrite each other's stamps)
ARRIVED: deque = deque()  # callback done, not handled yet
HANDLED: deque = deque()  # handled (callback or main thread), its step not yet run
_current: list = [None]
_now = time.time_ns
#: what this process probes already (each is installed once per process)
_installed: dict[str, bool] = {}
#: what the profile function does as a watched function is entered, or returns: by code object
ON_CALL: dict = {}
ON_RETURN: dict = {}


def _flt() -> int:
    return resource.getrusage(resource.RUSAGE_SELF).ru_minflt


def _in_worker() -> bool:
    spec = getattr(sys.modules["__main__"], "__spec__", None)
    # `python -m retriever.backends.zenoh.worker` runs the package's __main__
    return spec is not None and spec.name == "retriever.backends.zenoh.worker.__main__"


def _profile(frame, event, arg) -> None:
    """The profile function: on the entry or return of a watched function, what is watched for it."""
    if event == "call":
        then = ON_CALL.get(frame.f_code)
    elif event == "return":
        then = ON_RETURN.get(frame.f_code)
    else:
        return
    if then is not None:
        then(frame)


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


class StampingTap(Tap):
    """Data publishers' puts stamped; data callbacks stamped on entry (cb_in), their payload's
    ``to_bytes`` (cb_out), and the loop's stages they run (handle, decoded, delivered) profiled."""

    def publisher(self, key, publisher):
        return TimedPublisher(publisher) if "/data/" in key else publisher

    def callback(self, key, callback):
        def timed(sample):
            rec = {"f_cb_in": _flt(), "cb_in": _now()}
            sys.setprofile(_profile)
            try:
                callback(SampleProxy(sample, rec))
            finally:
                sys.setprofile(None)

        return timed


def _published(frame) -> None:
    if frame.f_locals["batch"]:
        FAULTS["publish"] = _flt()
        STAMPS["publish"] = _now()


def _encoded(frame) -> None:
    STAMPS["encoded"] = _now()
    FAULTS["encoded"] = _flt()


def _handling(frame) -> None:
    if frame.f_locals["item"][0] == node.DATA:
        rec = ARRIVED.popleft() if ARRIVED else {}
        rec["f_handle"] = _flt()
        rec["handle"] = _now()
        _current[0] = rec


def _handled(frame) -> None:
    if frame.f_locals["item"][0] == node.DATA and _current[0] is not None:
        HANDLED.append(_current[0])
        _current[0] = None


def _checking_claims(frame) -> None:
    rec = _current[0]
    if rec is not None and "decoded" not in rec:  # (a data message's: the first after decode_events)
        rec["decoded"] = _now()
        rec["f_decoded"] = _flt()


def _delivered(frame) -> None:
    rec = _current[0]
    if rec is not None:
        rec["delivered"] = _now()


def _waiting(frame) -> None:  # a timed wait (control_jitter.py --breakdown)
    ns = frame.f_locals["ns"]
    STAMPS["wait_for"] = ns
    STAMPS["wait_until"] = _now() + ns if ns > 0 else 0


def _woke(frame) -> None:
    STAMPS["woke"] = _now()


def install_stamps() -> None:
    """Stamp this worker's node loop: the transport's tap, the profile function on this thread."""
    if _installed.get("stamps") or not _in_worker():
        return
    _installed["stamps"] = True
    tap_transports(StampingTap())
    loop = node.NodeLoop
    ON_CALL.update({Outputs.publish.__code__: _published, loop.handle.__code__: _handling,
                    Streams.check_claims.__code__: _checking_claims, loop.wait.__code__: _waiting})
    ON_RETURN.update({Outputs.encode.__code__: _encoded, loop.handle.__code__: _handled,
                      Streams.deliver.__code__: _delivered, loop.wait.__code__: _woke})
    sys.setprofile(_profile)


SOURCE_KEYS = ("publish", "encoded", "put_in", "put_out")
SINK_KEYS = ("cb_in", "cb_out", "handle", "decoded", "delivered")


class ProbeSource(PayloadSource):
    def __init__(self, size: int):
        super().__init__(size)
        install_stamps()

    def step(self) -> Frame:
        data = self.fresh()
        prev = [STAMPS.get(k, 0) for k in SOURCE_KEYS] + [FAULTS.get("encoded", 0) - FAULTS.get("publish", 0)]
        return Frame(frame={"data": data, "k": self.k, "probe_prev": prev, "sent_ns": time.time_ns()})


class ProbeSink(Flow[Frame, Lat]):
    """Outputs [sent, received, size, k, source stamps (+ encode faults) of message k-1,
    sink stamps (+ to_bytes and decode faults) of message k]."""

    def __init__(self):
        install_stamps()

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
    names (outermost call only), through the profile function, and write it as JSON to ``path``
    when the worker exits. The figures include the profile function's own cost on each call of
    the main thread (about a microsecond): they are higher than unprobed, and compare with each
    other."""
    import atexit
    import json

    classes = {"NodeLoop": node.NodeLoop, "Outputs": Outputs, "Reports": Reports}
    main = threading.main_thread()
    outer: list = []  # the outermost profiled call going on: its label and CPU at its start

    def entered(label):
        def then(frame):
            if not outer and threading.current_thread() is main:
                outer.append((frame, label, time.thread_time_ns()))
        return then

    def returned(frame):
        if outer and outer[0][0] is frame:
            _, label, t = outer.pop()
            CPU_NS[label] = CPU_NS.get(label, 0) + time.thread_time_ns() - t
            CALLS[label] = CALLS.get(label, 0) + 1

    for label, cls, name in PROFILED:
        code = getattr(classes[cls], name).__code__
        ON_CALL[code], ON_RETURN[code] = entered(label), returned
    run, began = node.NodeLoop.run.__code__, {}

    def run_entered(frame):
        began[frame] = (time.thread_time_ns(), time.monotonic_ns())

    def run_returned(frame):
        t, w = began.pop(frame)
        CPU_NS["run (main thread, total)"] = time.thread_time_ns() - t
        CPU_NS["run (wall)"] = time.monotonic_ns() - w
        CALLS["ticks"] = frame.f_locals["self"].schedule.k

    ON_CALL[run], ON_RETURN[run] = run_entered, run_returned
    sys.setprofile(_profile)

    def dump():
        with open(path, "w") as f:
            json.dump({"cpu_ns": CPU_NS, "calls": CALLS}, f)

    atexit.register(dump)


class ProbeIdle(Flow):
    """Idle (does nothing, outputs nothing); in a worker, with RETRIEVER_BENCH_CPU_PROFILE=<dir>
    set, it profiles the node loop's main thread (install_cpu_profile) into <dir>/<pid>.json."""

    def __init__(self):
        import os

        out = os.environ.get("RETRIEVER_BENCH_CPU_PROFILE")
        if out and _in_worker() and not _installed.get("profile"):
            _installed["profile"] = True
            install_cpu_profile(os.path.join(out, f"{os.getpid()}.json"))

    def step(self):
        return None


class ProbeTicker(Flow[None, Lat]):
    """For control_jitter.py --breakdown: outputs, each tick, [wait_until, woke, step_start] of the
    node loop's last timed wait before this step (wall ns; wait_until 0 if it did not wait)."""

    def __init__(self):
        install_stamps()

    def step(self) -> Lat:
        start = time.time_ns()
        return Lat(lat=[STAMPS.get("wait_until", 0), STAMPS.get("woke", 0), start])


__all__ = ["PROFILED", "ProbeIdle", "ProbeSink", "ProbeSource", "ProbeTicker", "install_cpu_profile"]
