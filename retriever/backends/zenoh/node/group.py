"""Several nodes in one process: their loops stepped by one thread, their events handed over by
reference.

A process per flow isolates a flow that crashes or holds the GIL, and costs an interpreter, a
Zenoh session and a link to every other process. A group of flows shares all three: one thread
runs each node's loop one pass at a time (``NodeLoop.one_pass``), earliest wake first, and sleeps
until the earliest wake or until a message rings the group's doorbell::

    transport threads, control ──▶ a loop's inbox ──▶ doorbell (which loop)
                                                         │
    GroupLoop.run ◀──────────────────────────────────────┘
      ┌─▶ the loops whose wake came, or that were rung: one pass each (NodeLoop.one_pass)
      │     TICKED: due again now (behind the others now due), a wake: due then, DONE: it ends
      └── sleep until the earliest wake, or the doorbell

Between loops of the group an event travels as it is (``LocalBus``): the producer's publisher
puts the event's ``DataMessage`` (its value by reference, as in-process) in each local
consumer's inbox, with nothing encoded, copied, decoded or checked; a port with a consumer in
another process also goes on Zenoh, as before. Progress messages between loops of the group are
small and go as their bytes. The run's control is heard once for the group (``hear_control``):
each message opened and decoded once, the same record queued to every loop. Every loop keeps
its own schedule, frontiers, outputs, reports and control state: what a tick reads and emits is
what it would be in a process of its own; only when it runs may differ, since one loop's step
holds up the others' (a flow that needs to be on time beside a slow one belongs in a process of
its own).
"""

from __future__ import annotations

import heapq
import itertools
import queue
from collections import defaultdict
from typing import Callable

from ..protocol import ControlOpener
from ..wire import DataMessage, KeySpace
from .control import opened_control
from .inbox import EVENTS, PROGRESS
from .schedule import DONE, TICKED
from .transport import Transport


class RingingInbox(queue.SimpleQueue):
    """A loop's inbox in a group: each item put also rings the group's doorbell with the loop."""

    def __init__(self, doorbell: queue.SimpleQueue, loop_id: str):
        self.doorbell, self.loop_id = doorbell, loop_id

    def put(self, item, block: bool = True, timeout: float | None = None) -> None:
        super().put(item)
        self.doorbell.put(self.loop_id)


class LocalBus:
    """Who in this process listens to which stream: ``members``, the group's node ids; per
    stream (producer, port), the inbox puts of its local consumers; per producer, the puts of
    those that hear its progress."""

    def __init__(self, members: set[str]):
        self.members = frozenset(members)
        self.consumers: dict[tuple[str, str], list[Callable]] = defaultdict(list)
        self.hearers: dict[str, list[Callable]] = defaultdict(list)


class LocalPublisher:
    """An output port's publisher in a group: its events to the local consumers, by reference,
    and to ``remote`` (a Zenoh publisher, or None when no consumer is elsewhere) as bytes."""

    def __init__(self, stream: tuple[str, str], puts: list[Callable], remote):
        self.stream, self.puts, self.remote = stream, puts, remote

    def hand(self, events: list[DataMessage]) -> None:
        item = (EVENTS, self.stream, events)
        for put in self.puts:
            put(item)

    def put(self, message: bytes) -> None:
        if self.remote is not None:
            self.remote.put(message)


class LocalProgress:
    """A node's progress publisher in a group: its bytes to each local hearer and to ``remote``."""

    def __init__(self, producer: str, puts: list[Callable], remote):
        self.producer, self.puts, self.remote = producer, puts, remote

    def put(self, message: bytes) -> None:
        item = (PROGRESS, self.producer, message)
        for put in self.puts:
            put(item)
        if self.remote is not None:
            self.remote.put(message)


class GroupTransport(Transport):
    """A grouped node's transport: streams between members on ``bus``, the rest on ``inner``
    (the run's Zenoh transport for this node). ``remote_ports``: the output ports with a consumer
    outside the group; ``heard_elsewhere``: whether a node outside the group hears this one's
    progress."""

    def __init__(self, bus: LocalBus, inner: Transport, node_id: str, remote_ports: set[str],
                 heard_elsewhere: bool):
        self.bus, self.inner, self.id = bus, inner, node_id
        self.remote_ports, self.heard_elsewhere = remote_ports, heard_elsewhere

    def declare_inputs(self, streams, sources, inline, put) -> None:
        members = self.bus.members
        for stream in streams:
            if stream[0] in members:
                self.bus.consumers[stream].append(put)
        for src in sources:
            if src in members:
                self.bus.hearers[src].append(put)
        self.inner.declare_inputs([s for s in streams if s[0] not in members],
                                  [s for s in sources if s not in members], inline, put)

    def declare_outputs(self, ports, consumed):
        bus, me = self.bus, self.id
        # the remote side is declared only where a consumer elsewhere needs it: no Zenoh put otherwise
        remote, remote_progress, warm = self.inner.declare_outputs(sorted(self.remote_ports & set(ports)),
                                                                   consumed and self.heard_elsewhere)
        publishers = {port: LocalPublisher((me, port), bus.consumers[(me, port)], remote.get(port))
                      for port in ports}
        progress = LocalProgress(me, bus.hearers[me], remote_progress if self.heard_elsewhere else None)
        return publishers, progress, warm

    def publisher(self, port: str):
        return self.inner.publisher(port)

    def redeclare_inputs(self) -> None:
        self.inner.redeclare_inputs()

    def await_routes(self, timeout, stopping) -> None:
        self.inner.await_routes(timeout, stopping)

    def undeclare(self) -> None:
        self.inner.undeclare()


class GroupLoop:
    """Runs the node loops of a group from T0 to their end on the calling thread, one pass at a
    time. Make it before the loops declare anything: it gives each an inbox that rings its
    doorbell."""

    def __init__(self, loops: list):
        if any(loop.declared for loop in loops):
            raise RuntimeError("a GroupLoop takes its loops before they declare their inputs")
        self.loops = {loop.id: loop for loop in loops}
        self.doorbell: queue.SimpleQueue = queue.SimpleQueue()
        for loop in loops:
            loop.inbox = RingingInbox(self.doorbell, loop.id)
            loop.grouped = True  # no pass of it waits on its own inbox (the short ways of a lone loop)

    def hear_control(self, session, keys: KeySpace, opener: ControlOpener):
        """Declare the group's one subscriber to the run's control (its loops declare none): each
        message is opened with the process's key (``opener``) and decoded once, and the record
        queued to every loop. The subscriber: undeclare it when the loops are released."""
        inboxes = [loop.inbox for loop in self.loops.values()]

        def heard(sample) -> None:  # on Zenoh's thread
            item = opened_control(opener, sample)
            for inbox in inboxes:
                inbox.put(item)

        return session.declare_subscriber(keys.run_control(), heard)

    def run(self, t0: int, end: int, on_end: Callable[[object], None] | None = None
            ) -> tuple[str, BaseException] | None:
        """Every loop from T0 (HLC Unix ns) while ``t < end`` (ns since T0), each ended
        (``NodeLoop.end``) and handed to ``on_end`` as soon as it is done, while the others go on
        (its process says ``done`` for it then: in lockstep virtual time the coordinator waits
        for every node not done). A loop whose pass raised (StopRun, a bug) ends the group:
        ``(its id, the exception)``; the loops left are not ended (their process says what became
        of them). None: all ended."""
        loops, doorbell = self.loops, self.doorbell
        for loop in loops.values():
            loop.begin(t0, end)
        clock = next(iter(loops.values())).run_clock
        order = itertools.count()
        due: dict[str, int] = {}  # per live loop, when it looks again (ns since T0)
        heap: list[tuple[int, int, str]] = []  # (wake, order, loop id); an entry not in `due` is stale

        def wake_at(loop_id: str, at: int) -> None:
            if loop_id in due and due[loop_id] <= at:
                return
            due[loop_id] = at
            heapq.heappush(heap, (at, next(order), loop_id))

        for loop_id in loops:
            wake_at(loop_id, 0)
        while due:
            now = clock.now()
            while True:  # whatever rang: due now
                try:
                    rung = doorbell.get_nowait()
                except queue.Empty:
                    break
                if rung in due:
                    wake_at(rung, now)
            at, _, loop_id = heap[0]
            if due.get(loop_id) != at:
                heapq.heappop(heap)  # stale: the loop was rung, or ended
                continue
            if at > now:
                try:
                    rung = doorbell.get(timeout=min(at - now, 100_000_000) / 1e9)
                except queue.Empty:
                    continue
                if rung in due:
                    wake_at(rung, clock.now())
                continue
            heapq.heappop(heap)
            del due[loop_id]
            loop = loops[loop_id]
            try:
                when, wake = loop.one_pass()
                if wake is DONE or loop.stopping:
                    loop.end()
                    if on_end is not None:
                        on_end(loop)
                    continue
            except BaseException as exc:
                return loop_id, exc
            wake_at(loop_id, when if wake is TICKED else wake)
        return None
