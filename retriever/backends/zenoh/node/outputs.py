"""A node's outputs: stamping a step's events, holding LET outputs until their time, publishing,
and the node's own frontier, the promise its messages carry.

ASAP (no latency): events are stamped with the HLC time at completion, strictly increasing.
LET (``latency``): stamped ``τ + latency`` and held until then (``release``). Virtual time: as
in-process, ``(t, m + 1)`` or ``(t + latency, 0)``, published at once. On an instantaneous cycle
(docs/semantics.md, Causality) an ASAP output of a tick at (t, m) is stamped (HLC, m + 1): time
moves on at every hop in real time, so the microstep is what counts the hops of one instant, and
past max_microsteps an output that would trigger another tick (on one of ``instant_ports``)
stops the run, as in-process (a Zeno loop).
"""

from __future__ import annotations

import heapq
import threading
import time

from ....errors import CausalityError, CodecError, StopRun
from ....flow.burst import Burst
from ..wire import DataMessage, WireEncoder
from .clock import RunClock
from .frontiers import NEVER, Streams
from .reports import Reports
from .schedule import Schedule
from .transport import Transport
from .group import LocalPublisher


class Outputs:
    """``seqs``: per output port, the next event's seq; ``sent``: the last seq put; ``held``: LET
    outputs waiting for release, a heap of (tag, port, value, seq); ``sending``: the lowest tag
    of outputs being put right now. ``lock`` guards what the progress queryable reads."""

    def __init__(self, node_id: str, ports: list[str], *, consumed: bool, latency_ns: int, virtual: bool,
                 cycle: list[str] | None, instant_ports: frozenset, max_microsteps: int, lock: threading.Lock,
                 clock: RunClock, schedule: Schedule, streams: Streams, reports: Reports, transport: Transport):
        self.id, self.ports, self.single_port = node_id, ports, len(ports) == 1
        self.consumed = consumed  # whether any flow consumes this one (else no progress messages)
        self.latency_ns, self.virtual = latency_ns, virtual
        self.cycle, self.max_microsteps = cycle, max_microsteps
        self.instant_ports = instant_ports if cycle else frozenset()
        self.lock, self.clock, self.schedule, self.streams = lock, clock, schedule, streams
        self.reports, self.transport = reports, transport
        self.encoder = WireEncoder()
        self.seqs: dict[str, int] = {}
        self.sent: dict[str, int] = {}
        self.held: list[tuple] = []
        self.sending: tuple[int, int] | None = None
        self.last_stamp = 0  # ASAP: the last tick's output tag; each tick's is later
        self.publishers: dict = {}
        self.progress_publisher = None
        self.warm_publisher = None  # (timing.py) on warm/<node>, declared with the rest
        self.warm_publish: tuple | None = None  # the last event published, as encoder arguments

    def frontier(self, sent: bool = False) -> tuple[int, int]:
        """Every later output of this node will have a tag ≥ this (thread-safe). ``sent``: as
        if the outputs being put now were out already (the frontier they carry); the main
        thread, which just stamped them, then skips reading the HLC again."""
        with self.lock:
            return self.frontier_held(sent)

    def frontier_held(self, sent: bool = False) -> tuple[int, int]:
        """:meth:`frontier`, by a caller that holds ``lock`` (a step's end: the tick no longer
        running and its frontier read in one lock section)."""
        if not self.clock.started:  # its end not known yet: nothing promised past the run's start
            return (0, 0)
        running = self.schedule.running
        lower = running or self.streams.tick_bound()
        if lower >= (self.clock.end, 0) and running is None:
            own = NEVER
        elif self.latency_ns:
            own = (lower[0] + self.latency_ns, 0)
        elif self.virtual:
            own = (lower[0], lower[1] + 1)
        else:
            # the tick in progress, or the next, is stamped past the last stamp and the HLC now
            stamp = self.last_stamp + 1 if sent else max(self.clock.hlc(), self.last_stamp + 1)
            own = (stamp if stamp > lower[0] else lower[0] + 1, 0)  # (max, without its call: per publish)
        if self.held:
            own = min(own, self.held[0][0])
        if self.sending is not None and not sent:
            own = min(own, self.sending)
        return own

    def stamp(self, tau: tuple[int, int], events: list) -> tuple[tuple[int, int] | None, list, tuple]:
        """A step's events, stamped and numbered: their tag (None: no events, nothing stamped),
        the batch to publish or hold, (tag, port, value, first seq), and the event ids made."""
        if self.latency_ns:
            tag = (tau[0] + self.latency_ns, 0)
        elif self.virtual:  # as in-process: one microstep later
            if tau[1] + 1 > self.max_microsteps and any(port in self.instant_ports for port, _ in events):
                self.zeno(tau)
            tag = (tau[0], tau[1] + 1)
        elif events:
            microstep = tau[1] + 1 if self.instant_ports else 0
            if microstep > self.max_microsteps and any(port in self.instant_ports for port, _ in events):
                self.zeno(tau)
            # strictly increasing, so the frontier right after a publish is its tag + 1 ns even
            # when the node runs late (the tag then passes the next tick's time)
            # (RunClock.hlc, and max(hlc, tau[0] + 1, last_stamp + 1), inline: this runs per step
            # with events, and builtin max parses keywords at each call)
            clock = self.clock
            stamp = clock.session.new_timestamp().get_time_as_ntp64().as_nanos() - clock.t0
            if stamp <= tau[0]:
                stamp = tau[0] + 1
            if stamp <= self.last_stamp:
                stamp = self.last_stamp + 1
            self.last_stamp = stamp
            tag = (stamp, microstep)
        else:  # nothing to stamp: no clock read (a later stamp is past this one's all the same)
            tag = None
        batch, produced, seqs, me = [], [], self.seqs, self.id
        for port, value in events:
            seq = seqs.get(port, 0)
            if type(value) is Burst:  # its events go as one message: one batch item
                seqs[port] = seq + len(value.values)
                produced.extend((me, port, s) for s in range(seq, seq + len(value.values)))
            else:
                seqs[port] = seq + 1
                produced.append((me, port, seq))
            batch.append((tag, port, value, seq))
        return tag, batch, tuple(produced)

    def unnumber(self, batch: list) -> None:
        """Give back the seqs of a batch that is dropped, never published."""
        for _, port, _, seq in batch:  # (a burst's first seq)
            self.seqs[port] = min(self.seqs[port], seq)

    def zeno(self, tau: tuple[int, int]) -> None:
        """Stop the run: the instant of ``tau`` ran past max_microsteps. The tick's outputs are
        not published and it has no record, as in-process (the run's end record says why)."""
        with self.lock:
            self.schedule.running = None
        raise StopRun(str(CausalityError(self.cycle, tau, self.max_microsteps)), tau, zeno=True)

    def hold(self, batch: list) -> None:
        """LET outputs, to be published at their tag's time (``release``)."""
        with self.lock:
            for item in batch:
                heapq.heappush(self.held, item)

    def release(self, now: int) -> None:
        """Publish held LET outputs whose tag time has come."""
        if not self.held or self.held[0][0][0] > now:
            return
        batch = []
        with self.lock:
            while self.held and self.held[0][0][0] <= now:
                batch.append(heapq.heappop(self.held))
            self.sending = batch[0][0]
        self.publish(batch)

    def release_held(self) -> None:
        """Publish every held LET output now, before its time: this loop ends (the run's end, or
        its process restarts or stops). Their seqs are in step records already, and consumers
        take events by tag, not by arrival: early, they change no tick; missing, they would
        leave a gap in their stream that no consumer's edge completes past."""
        with self.lock:
            batch = sorted(self.held)
            self.held = []
            self.sending = batch[0][0] if batch else None
        self.publish(batch)

    def publish(self, batch: list, frontier: tuple[int, int] | None = None) -> None:
        """Send events (each but the last carries its own tag as frontier, the last the node's
        frontier), then a progress message if some consumer's port did not get the frontier.
        ``frontier``: ``frontier_held(sent=True)``, read by the caller under the lock (else here)."""
        if not batch and not self.consumed:  # (an idle tick of a flow no one consumes: nothing to say)
            return
        if frontier is None:
            frontier = self.frontier(sent=True)
        data, publishers, reports, me = self.encoder.data, self.publishers, self.reports, self.id
        last = len(batch) - 1
        for i, (tag, port, value, seq) in enumerate(batch):
            publisher = publishers.get(port)
            if publisher is None:  # an output port no edge uses (an untyped flow's extra key)
                publisher = publishers[port] = self.transport.publisher(port)
            burst, carries = type(value) is Burst, frontier if i == last else tag
            local = type(publisher) is LocalPublisher  # (consumers in this process: handed over as they are)
            message = None if local and publisher.remote is None else self.encode(tag, seq, carries, port, value)
            # counted as sent before the put, not after: a consumer that subscribes meanwhile and
            # asks where the stream stands (a node started afresh: sync_inputs) must not be told
            # to wait for this seq. Zenoh chose the put's subscribers when it began, and a put held
            # by a congested link (a consumer's host cut off, BLOCK) began long before it returns:
            # told 'sent up to seq - 1', the new consumer waited for a seq that never came to it,
            # every tick incomplete, for the rest of the run (issue 40)
            self.sent[port] = seq + len(value.values) - 1 if burst else seq
            if local:
                publisher.hand(_as_messages(tag, seq, carries, me, port, value, burst))
            if message is not None:
                publisher.put(message)
            if self.consumed and not burst:  # someone waits for this node's next event: warm its path first
                self.warm_publish = (tag, seq, frontier, me, port, value)
            if not reports.values:  # the coordinator records that it was sent, not what
                blank = Burst.unchecked((None,) * len(value.values)) if burst else None  # sent as nil
                message = data(tag, seq, carries, me, port, blank)
            elif message is None:  # (handed over in this process only: the coordinator still wants it)
                message = self.encode(tag, seq, carries, port, value)
            reports.published.append((time.time_ns(), message))
            reports.published_bytes += len(message)
            reports.published_seqs += len(value.values) if burst else 1
        if batch:
            reports.published_batch(self.clock.now())
        if self.sending is not None:
            with self.lock:
                self.sending = None  # only now may a progress query promise past these tags
        if self.consumed and not (batch and self.single_port):
            self.publish_progress(frontier)

    def encode(self, tag: tuple[int, int], seq: int, frontier: tuple[int, int], port: str, value) -> bytes:
        """One event's data message as it is sent; StopRun if its value cannot leave the process."""
        try:  # (WireEncoder.data's join, one call sooner: this runs per event sent)
            return b"".join(self.encoder.data_parts(tag, seq, frontier, self.id, port, value))
        except CodecError as e:  # the step returned it; in-process it would have gone by reference
            what = "the Burst (value[i]: its value i)" if type(value) is Burst else "the event"
            raise StopRun(f"{self.id}.{port}: {what} at t={tag[0] / 1e9:.6f} s cannot be sent to another "
                          f"process: {e}", tag) from None

    def publish_progress(self, frontier: tuple[int, int] | None = None) -> None:
        self.progress_publisher.put(self.encoder.progress(frontier or self.frontier(), self.id, self.sent))


def _as_messages(tag, seq: int, frontier, producer: str, port: str, value, burst: bool) -> list[DataMessage]:
    """An event as a consumer's decoder would give it (wire.decode_events), values by reference:
    a Burst's events each with its own seq, all but the last with their own tag as frontier."""
    if not burst:
        return [DataMessage(tag, seq, frontier, producer, port, value)]
    last = len(value.values) - 1
    return [DataMessage(tag, seq + i, frontier if i == last else tag, producer, port, item)
            for i, item in enumerate(value.values)]
