"""A diagnostic for fig7a_latency.py: Retriever on Zenoh with the ring of shm_ring.py under its
transport, a prototype through the transport's public tap (``transport.tap_transports``): nothing
of retriever/ changed (benchmarks/reports/shm_channel.md).

    retriever-zenoh-ring-copy  latency.py's retriever-zenoh pipeline (PayloadSource @ Rate ->
                               LatencySink @ Trigger, a worker process each); in both workers
                               every data message of 64 KiB or more goes through a ring: the
                               source's publisher copies the message the loop encoded into a
                               slot and puts ``0xC1`` + the handle instead; the sink's data
                               callback copies the slot out to bytes (seqlock checked) and hands
                               those to the loop as the payload's ``to_bytes()``
    retriever-zenoh-ring-view  the same, the sink's loop given a memoryview of the slot (nothing
                               holds it: what a view would gain, not a safe design)
    retriever-unix-ring-copy   ring-copy with the handle sent over a Unix datagram socket the
                               sink's worker binds (abstract namespace, named from the run's
                               prefix and the key) instead of Zenoh: a thread of the sink's tap
                               receives it and calls the transport's data callback (the message
                               goes whole over Zenoh if no socket is bound)

The message is copied once more than the design would (the loop joins it, then the tap copies
it into the slot; the design joins into the slot): an upper bound of the design's latency.
Rings are unlinked by the workers at exit and, by the run's prefix, by the harness after the run.
"""

from __future__ import annotations

import os
import sys

import numpy as np
from shm_ring import SHM, Reader, Writer
from zenoh_flows import LatencySink, PayloadSource

MARK = b"\xc1"  # msgpack's never-used byte: no data message starts with it; a handle follows it
RING_FROM = 64 << 10  # messages at least this big go through the ring
_writers: list[Writer] = []
_installed: list[bool] = []


class _RingPublisher:
    """A data publisher of the node loop: a message of RING_FROM bytes or more is copied into a
    ring slot (once more: the loop joined it already; the design joins into the slot) and its
    handle put instead."""

    def __init__(self, publisher, prefix: bytes, address: bytes | None = None):
        self.publisher, self.prefix, self.ring = publisher, prefix, None
        self.address, self.sock = address, None
        if address is not None:
            import socket

            self.sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)

    def put(self, payload, **kw):
        if len(payload) < RING_FROM:
            return self.publisher.put(payload, **kw)
        ring = self.ring
        if ring is None or len(payload) > ring.capacity:
            ring = self.ring = Writer(self.prefix + os.urandom(16 - len(self.prefix)), len(payload))
            _writers.append(ring)
        handle = MARK + ring.write(np.frombuffer(payload, dtype=np.uint8))
        if self.sock is None:
            return self.publisher.put(handle, **kw)
        try:
            self.sock.sendto(handle, self.address)
        except OSError:  # no consumer bound: the message goes whole
            return self.publisher.put(payload, **kw)

    def undeclare(self):
        self.publisher.undeclare()


class _Payload:
    __slots__ = ("payload", "take")

    def __init__(self, payload, take):
        self.payload, self.take = payload, take

    def to_bytes(self):
        raw = self.payload.to_bytes()
        return self.take(raw[1:]) if raw[:1] == MARK else raw


class _Sample:
    __slots__ = ("payload",)

    def __init__(self, sample, take):
        self.payload = _Payload(sample.payload, take)


class _Taken:
    __slots__ = ("data",)

    def __init__(self, data):
        self.data = data

    def to_bytes(self):
        return self.data


class _Direct:
    __slots__ = ("payload",)

    def __init__(self, data):
        self.payload = _Taken(data)


def _address(prefix: bytes, key: str) -> bytes:
    import hashlib

    digest = hashlib.blake2b(key.encode(), digest_size=8).hexdigest()
    return f"\0retriever-ring-{prefix.hex()}-{digest}".encode()


def _pump(sock, callback, take) -> None:
    while True:
        message = sock.recv(256)
        callback(_Direct(take(message[1:])))


def _install_ring(prefix_hex: str, mode: str) -> None:
    """In a worker process (once): its data publishers write big messages into rings, its data
    callbacks read them (``mode`` copy: bytes of their own; view: a memoryview of the slot)."""
    import atexit

    from retriever.backends.zenoh.node.transport import Tap, tap_transports

    spec = getattr(sys.modules["__main__"], "__spec__", None)
    if spec is None or not spec.name.startswith("retriever.backends.zenoh.worker") or _installed:
        return
    _installed.append(True)
    prefix, reader = bytes.fromhex(prefix_hex), Reader()
    take = reader.view_memory if mode == "view" else reader.copy_bytes
    unix = mode == "unix"

    class RingTap(Tap):
        def publisher(self, key, publisher):
            if "/data/" not in key:
                return publisher
            return _RingPublisher(publisher, prefix, _address(prefix, key) if unix else None)

        def callback(self, key, callback):
            if unix:
                import socket
                import threading

                sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
                try:
                    sock.bind(_address(prefix, key))
                except OSError:  # (declared again: the first one's thread goes on)
                    sock.close()
                else:
                    threading.Thread(target=_pump, args=(sock, callback, take), daemon=True).start()
            return lambda sample: callback(_Sample(sample, take))

    tap_transports(RingTap())
    atexit.register(lambda: [w.close() for w in _writers])


class RingSource(PayloadSource):
    def __init__(self, size: int, prefix_hex: str, mode: str):
        super().__init__(size)
        _install_ring(prefix_hex, mode)


class RingSink(LatencySink):
    def __init__(self, prefix_hex: str, mode: str):
        super().__init__()
        _install_ring(prefix_hex, mode)


def run_retriever_ring(size: int, total: int, hz: float, warmup: int, mode: str) -> dict:
    """latency.run_retriever's pipeline with the ring tap in both workers; their rings removed after."""
    from retriever import Pipeline, Rate, Trigger

    prefix = os.urandom(8).hex()
    with Pipeline(f"latency_ring_{size}") as pipe:
        RingSource(size, prefix, mode).configure(name="src") @ Rate(hz=hz)
        RingSink(prefix, mode).configure(name="sink") @ Trigger("frame")
        pipe.connect(pipe.flows[0], pipe.flows[1])
    try:
        trace = pipe.run(duration=total / hz, backend="zenoh", quiet=True)
    finally:
        for left in SHM.glob(f"retriever-ring-{prefix}*"):
            left.unlink(missing_ok=True)
    events = sorted((ev for ev in trace.events if ev.node == "sink"), key=lambda ev: ev.seq)
    if any(ev.value[2] != size for ev in events):
        raise SystemExit("retriever-zenoh-ring: the sink got a payload of the wrong size")
    pipe.reset()
    return {"lat": [ev.value[1] - ev.value[0] for ev in events[warmup:]], "received": len(events)}


