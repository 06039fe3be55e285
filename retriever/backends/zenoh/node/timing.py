"""Being on time: warming up the send and receive paths before a predictable moment, and the
loop's sleep to its next wake (Pacer).

After a sleep of ~10 ms or more, the code and data of the send and receive paths are out of the
CPU's caches, and that cold run is most of a small message's latency (benchmarks/reports/
latency.md). So before a moment that is predictable (the next Rate tick of a node with
consumers, the next arrival on a periodic input stream) that follows such a sleep, the loop
wakes WARM_AHEAD_NS early and runs its encoder on the last event it sent, reads the HLC, and, if
it publishes, puts an empty message on its ``warm/<node>`` key; and it rehearses the receive
path on the last message it got (:class:`Rehearsal`: decoded, taken in order, delivered and
selected on scratch copies of its inputs; arrays are not copied for that). It changes only how
fast a tick starts, never what it reads or emits. Sleeps shorter than WARM_AFTER_IDLE_NS leave
the caches warm.

The empty message goes to the producer's consumers that may step on their receiving thread
(node/loop.py, INLINE_STEP_NS), over the link its next data message takes, about WARM_AHEAD_NS
ahead of it. Each rehearses there, on the thread that will receive that message, the arrival of
the producer's last one (:meth:`Warmup.rehearse`, if its main thread is waiting): the whole way,
the producer's send down to its socket, Zenoh's receive and that thread's Python, runs once
just before the message does; a rehearsal on the consumer's main thread warmed neither Zenoh's
threads nor, maybe, their core (benchmarks/reports/latency.md, 2026-12-05 lat14). Its content is
never read: anyone may put there, and it costs a rehearsal at most.
"""

from __future__ import annotations

import queue
import threading
from collections import Counter
from typing import Protocol

from ....clocks import Clock
from ....sync import PortBuffer
from ....tick import select_inputs
from ..wire import decode_events
from .clock import RunClock
from .frontiers import InEdge, Streams
from .notes import Notes
from .schedule import Schedule

WARM_AHEAD_NS = 1_000_000
WARM_AFTER_IDLE_NS = 4_000_000


class _Rehearsed:
    """A rehearsed input's port spec for select_inputs: MISSING is only noted, never its fallback
    made (a default factory is the flow's code, which a rehearsal does not run)."""

    required = True


_REHEARSED = _Rehearsed()


class Rehearsal:
    """A node's receive path run on scratch copies of its inputs, up to the flow's step, which it
    never calls: a message decoded, its claims checked, taken in order and delivered to scratch
    buffers (with their policies) by a :class:`Streams` of its own, on a schedule of its own, and
    each input selected at its tag, as a tick would. Decoding alone left most of that path cold
    (benchmarks/reports/latency.md). Nothing of the loop's is written; the scratch is emptied after."""

    def __init__(self, node_id: str, node_clock: Clock, edges: list[InEdge], inputs: list[tuple], clock: RunClock):
        scratch = {port: PortBuffer(buf.trim_batch, policy) for port, buf, policy, _ in inputs}
        self.inputs = [(port, scratch[port], policy, _REHEARSED) for port, _, policy, _ in inputs]
        lock = threading.Lock()
        self.schedule = Schedule(node_clock, lock)
        self.streams = Streams(node_id, [InEdge(e.src, e.src_port, e.port, scratch[e.port], e.delay_ns, e.triggers,
                                                e.deadline_ns, e.src_latency_ns) for e in edges],
                               self.schedule, clock, Notes(node_id), lock)

    def run(self, message: bytes) -> None:
        """Rehearse the arrival of ``message`` (one event; a burst is only decoded)."""
        events = decode_events(message)
        streams, msg = self.streams, events[0]
        stream = (msg.producer, msg.port)
        if len(events) != 1 or stream not in streams.expect:
            return
        try:
            streams.expect[stream] = msg.seq  # (taken in order: the next one expected)
            streams.check_claims(stream, msg.seq, msg.frontier)
            streams.in_order(stream, msg)
            select_inputs(self.inputs, msg.tag)
        finally:
            for _, buf, _, _ in self.inputs:
                buf.entries.clear()
                buf.visible = buf.cursor = 0
                buf.last_id = None
            self.schedule.pending.clear()
            self.schedule.pending_set.clear()


class Warmup:
    """Per input stream, its last arrival (ns since T0), the gap before it, and its last message;
    ``warmed_for``: the moment last warmed up for (once per moment). What it warms on the send
    side is the ``outputs``' last event and warm publisher; on the receive side, ``rehearsal``
    runs on the last message of the stream foreseen. ``heralds``: per producer, when its last
    warm-up message came (ns since T0); ``heralded``: the streams whose last message came after
    one, which the receiving thread rehearses for (:meth:`rehearse`), so the main thread does not."""

    def __init__(self, outputs, schedule, clock: RunClock, rehearsal: Rehearsal):
        self.outputs, self.schedule, self.clock, self.rehearsal = outputs, schedule, clock, rehearsal
        self.arrivals: dict[tuple[str, str], tuple[int, int, bytes]] = {}
        self.warmed_for: int | None = None
        self.heralds: dict[str, int] = {}
        self.heralded: set[tuple[str, str]] = set()

    def arrived(self, stream: tuple[str, str], data: bytes | None, now: int) -> None:
        """Note when a stream's message came, to foresee its next one (or to leave it to its
        producer's warm-up message, if one came since the stream's last message)."""
        last = self.arrivals.get(stream)
        gap = now - last[0] if last is not None else 0
        self.arrivals[stream] = (now, gap, data)
        if last is not None and self.heralds.get(stream[0], -1) > last[0]:
            self.heralded.add(stream)
        else:
            self.heralded.discard(stream)

    def target(self, now: int, wake: int) -> tuple[int | None, bytes | None]:
        """The predictable moment before ``wake`` to warm up for, after a long enough sleep, and
        the received message to decode then; ``(None, None)`` if there is none."""
        target, message = None, None
        if self.outputs.warm_publish is not None and self.schedule.next_rate is not None:
            target = self.schedule.next_rate[0]
        heralded = self.heralded
        for stream, (last, gap, data) in self.arrivals.items():
            if stream in heralded:  # (its producer's warm-up message will have it rehearsed)
                continue
            expected = last + gap
            if now < expected and (target is None or expected < target):
                target, message = expected, data
        if target is None or target > wake or target - now < WARM_AFTER_IDLE_NS or target == self.warmed_for:
            return None, None
        return target, message

    def warm(self, message: bytes | None) -> None:
        """Run the encoder and the receive path once, results unused. Both did this work before;
        should it fail now (a flow changed a value it had emitted), the warm-up is simply
        skipped: it never stops a run."""
        outputs = self.outputs
        try:
            if outputs.warm_publish is not None:
                outputs.encoder.data_parts(*outputs.warm_publish)
                self.clock.hlc()
                if outputs.warm_publisher is not None:
                    outputs.warm_publisher.put(b"")
            if message is not None:
                self.rehearsal.run(message)
        except Exception:
            outputs.warm_publish = None

    def herald(self, producer: str, now: int) -> None:
        """``producer``'s warm-up message came at ``now`` (ns since T0): its next message is on
        its way (any thread: one dict item set)."""
        self.heralds[producer] = now

    def rehearse(self, producer: str) -> None:
        """Rehearse the arrival of the last message of each stream of ``producer`` (results
        unused; a failure skips it, as in :meth:`warm`)."""
        for (src, _), (_, _, data) in list(self.arrivals.items()):
            if src == producer and data is not None:
                try:
                    self.rehearsal.run(data)
                except Exception:
                    return


class PacerOwner(Protocol):
    """What :class:`Pacer` uses of the loop it serves (a NodeLoop)."""

    #: what a message comes into (read when spinning: a group gives its loops inboxes of their own)
    inbox: queue.SimpleQueue

    def wait(self, ns: int) -> bool:
        """Wait up to ``ns`` for a message and handle it; whether one came."""


class Pacer:
    """How a node loop sleeps until its next wake: warmed up for the moment it foresees
    (``warmup``), spinning the last ``spin_ns`` to a Rate tick of ``schedule`` (configure(spin=),
    the time spun counted in ``counts``), or plainly. A message ends any of them: the
    ``owner``'s ``wait`` handles it (:class:`PacerOwner`), and the loop looks again."""

    def __init__(self, owner: PacerOwner, *, warmup: Warmup, schedule: Schedule, clock: RunClock, spin_ns: int,
                 counts: Counter):
        self.owner, self.warmup, self.schedule, self.clock = owner, warmup, schedule, clock
        self.spin_ns, self.counts = spin_ns, counts

    def sleep(self, now: int, wake: int) -> None:
        """Until ``wake`` (ns since T0), or a message."""
        wait, warmup = self.owner.wait, self.warmup
        target, message = warmup.target(now, wake)
        if target is not None:
            early = target - WARM_AHEAD_NS
            # nothing came meanwhile, and the wait (at most 100 ms) lasted to the moment
            if not wait(early - now) and self.clock.now() >= early:
                warmup.warm(message)
                warmup.warmed_for = target
            return
        next_rate = self.schedule.next_rate
        if self.spin_ns and next_rate is not None and wake == next_rate[0]:
            self._spin_to(wake)
        else:
            wait(wake - self.clock.now())

    def _spin_to(self, wake: int) -> None:
        """Wait for the Rate tick at ``wake``: sleep until ``spin_ns`` before it, then busy-wait
        to it, unless a message comes (the loop then looks again)."""
        owner, now = self.owner, self.clock.now
        while (left := wake - self.spin_ns - now()) > 0:  # (one wait sleeps at most 100 ms)
            if owner.wait(left):
                return
        inbox = owner.inbox  # (read now: a GroupLoop gives its loops inboxes of its own)
        began = now()
        while now() < wake and not inbox.qsize():
            pass
        self.counts["spin_ns"] += now() - began
