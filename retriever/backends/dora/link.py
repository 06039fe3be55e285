"""A node's events and progress over dora: the transport a node loop is handed in a dora run.

    dora inputs ──DoraLink's receiving thread: node.next()──▶ each listening loop's inbox (or
                                                 handled right there, as a Zenoh subscriber's
                                                 callback would: INLINE_STEP_NS)
                  (a producer's warm-up message: the listening loop's ``warmed(producer)``, right
                   there: it rehearses the producer's last message on that thread, as on Zenoh;
                   for a stream without them, WARM_AHEAD_NS before an input's next event it
                   foresees, its own work once on the last event, results unused: the view of
                   its bytes and, where the loop takes it on this thread, their decoding)
    loop ──send_output(port | progress)──▶ dora ──▶ the consumers' inputs
         ──send_output(warm, b"")──▶ dora ──▶ the consumers' warm-up inputs, WARM_AHEAD_NS
                                   before a moment it foresees (timing.py: Warmup)

A process has one dora node, and so one :class:`DoraLink`: its receiving thread hands each
input's events to every node of the process that listens to that input (a group's members,
``configure(process=)``, share one process: backends/zenoh/node/group.py; each has a
:class:`DoraTransport` of its own on the one link). A receiving thread that dies hands its error
to every listening loop (inbox.FAILED), which raises it: the run fails naming it, where the node
would otherwise hear nothing more, and never step again.

Everything else is the node loop's (backends/zenoh/node/): clocks, frontiers, deadlines, LET,
step records. The run's control plane stays on the run's private Zenoh hub: ``start`` and
``stop``, the reports that become the trace and the log, and the answers to a consumer that asks
a producer for its frontier (dora has no queries).
"""

from __future__ import annotations

import functools
import threading
import time
from typing import Callable

from ...errors import WireError
from ..zenoh.node import DATA, FAILED, PROGRESS, WARM_AFTER_IDLE_NS, WARM_AHEAD_NS, Transport
from ..zenoh.wire import decode_events
from .dataflow import DoraNames

#: how long the receiving thread waits in ``node.next()`` before it looks whether to stop
RECEIVE_TIMEOUT_S = 0.1

#: An empty message: a producer's greeting, sent once on each of its dora outputs when it declares
#: them. A consumer says ready only once a greeting came through each of its inputs: dora's routes
#: are set up lazily, and without this the first events of a run can take a good part of a second
#: to arrive (a LET run would then differ from in-process: its first ticks would run without them).
GREETING = b""


class DoraOutput:
    """One dora output of this node, put to as a Zenoh publisher is: ``put(message)`` is the
    node's ``send_output`` bound to the output (no Python frame of its own per message sent)."""

    __slots__ = ("put",)

    def __init__(self, node, output: str):
        self.put = functools.partial(node.send_output, output)


class Nowhere:
    """An output port no edge names (an untyped flow's extra key): nobody consumes it, and the
    dataflow has no such output; its events still reach the log through the reports."""

    def put(self, message: bytes) -> None:
        pass


class DoraLink:
    """This process's dora node and its receiving thread, shared by the transports of the nodes
    the process serves. ``listen`` adds a node's routes (dora input id -> (producer, port or None
    for its progress)); the thread runs while any node listens."""

    def __init__(self):
        self.dora_node = None
        self.receiver: threading.Thread | None = None
        self.receiving = False
        #: per dora input, who hears it: (handler, kind, key, put) of each listening node, which
        #: hands each event's (kind, key, data) to handler (its receive for data, its put for
        #: progress), and its failure to put
        self.listeners: dict[str, list[tuple[Callable, str, object, Callable]]] = {}
        #: per warm-up input (DoraNames.warm_inputs), who hears it: (warmed, producers) of each
        #: listening node, which calls warmed(producer) for each of the producers it brings
        self.heralds: dict[str, list[tuple[Callable, list[str]]]] = {}
        self.greeted: set[str] = set()  # inputs a producer's greeting came through
        self.greetings = threading.Condition()
        self.failure: Exception | None = None  # what ended the receiving thread, if it died
        self.clock: Callable[[], int] = time.monotonic_ns  # when events come (to foresee the next)

    def node(self):
        """This process's dora node (created once: dora starts the dataflow when every node has one)."""
        if self.dora_node is None:
            from dora import Node

            self.dora_node = Node()
        return self.dora_node

    def listen(self, routes: dict[str, tuple], receive: Callable, put: Callable) -> list:
        """Hand each event of ``routes``' inputs to ``receive`` (data) or ``put`` (progress, and
        the thread's failure); the thread starts with the first listener. What to ``leave``."""
        node = self.node()
        entries = []
        with self.greetings:  # (a new list per input: the thread reads them without the lock)
            for input_id, (src, port) in routes.items():
                # what the thread does with each event of the input: hand (kind, key, data) on
                entry = (put, PROGRESS, src, put) if port is None else (receive, DATA, (src, port), put)
                self.listeners[input_id] = [*self.listeners.get(input_id, ()), entry]
                entries.append((input_id, entry))
        if self.receiver is None:
            self.receiving = True
            self.receiver = threading.Thread(target=self._receive, args=(node,), daemon=True,
                                             name="retriever-dora-receiver")
            self.receiver.start()
        return entries

    def listen_warm(self, warm_inputs: dict[str, list[str]], warmed: Callable) -> list:
        """Call ``warmed(producer)`` on the receiving thread for each warm-up message of
        ``warm_inputs`` (dora input id -> the producers it brings). What to ``leave``."""
        entries = []
        with self.greetings:  # (a new list per input: the thread reads them without the lock)
            for input_id, producers in warm_inputs.items():
                entry = (warmed, producers)
                self.heralds[input_id] = [*self.heralds.get(input_id, ()), entry]
                entries.append((input_id, entry))
        return entries

    def leave(self, entries: list) -> None:
        """Hear no more what ``listen`` added; the last listener gone, the thread ends."""
        with self.greetings:
            for input_id, entry in entries:
                table = self.heralds if len(entry) == 2 else self.listeners  # (listen_warm's: (warmed, producers))
                left = [e for e in table.get(input_id, ()) if e is not entry]
                if left:
                    table[input_id] = left
                else:
                    table.pop(input_id, None)
            last = not self.listeners
        if last and self.receiver is not None:
            self.receiving = False
            if self.receiver is not threading.current_thread():
                self.receiver.join()
            self.receiver = None

    def await_greetings(self, wanted: set[str], timeout: float, stopping: Callable[[], bool]) -> None:
        """Until a greeting came through each input of ``wanted`` (or stopping, or ``timeout``);
        the receiving thread's error if it died."""
        give_up = time.monotonic() + timeout
        with self.greetings:  # (in short waits: a stop, from a signal handler, notifies no one)
            while not (stopping() or self.greeted >= wanted or self.failure) and time.monotonic() < give_up:
                self.greetings.wait(0.1)
        if self.failure is not None:  # no greeting can come any more
            raise self.failure

    def _receive(self, node) -> None:
        """The receiving thread: every input event, in dora's order, to its listeners (until dora
        says every sender is gone, or no one listens); if it dies, its error, to every listener."""
        try:
            self._take_events(node)
        except Exception as exc:
            with self.greetings:
                self.failure = exc
                self.greetings.notify_all()
                puts = {id(put): put for entries in self.listeners.values() for *_, put in entries}
            for put in puts.values():
                put((FAILED, None, exc))

    def _take_events(self, node) -> None:
        """Each input event to its listeners. Before the next event of the input the last one
        came on, foreseen from the gap between that input's last two (when the gap is a sleep
        long enough to leave the caches cold: WARM_AFTER_IDLE_NS), the thread wakes
        WARM_AHEAD_NS early and does its work on that event once more, results unused
        (:func:`_warm`): cold, after a sleep of 50 ms, ``len``, ``buffers`` and the view took ~20
        µs of a message's latency, warmed ~6 (benchmarks/reports/fig7a.md, 2026-12-05, dora12).
        It changes no event, nor when one is handed on."""
        listeners, heralds, clock = self.listeners, self.heralds, self.clock
        heralded: dict[str, int] = {}  # per producer, when its last warm-up message came
        last: dict[str, int] = {}  # per input, when its last event came
        due, warm = None, None  # when to warm up next, and on which event: (its value, its input's listeners)
        while self.receiving:
            timeout = RECEIVE_TIMEOUT_S
            if due is not None:
                wait = due - clock()
                if wait <= 0:
                    _warm(*warm)
                    due = None
                    continue
                timeout = min(timeout, wait / 1e9)
            event = node.next(timeout=timeout)
            if event is None:  # the stream ended: after a STOP, or dora run (its daemon) is gone
                return
            if event["type"] != "INPUT":  # a timeout (ERROR), INPUT_CLOSED, STOP: queued inputs still follow
                continue
            value = event["value"]  # a uint8 array: what send_output made of a message's bytes
            size = len(value)
            input_id = event["id"]
            if input_id in heralds:  # a producer's warm-up message (its content is never read)
                now = clock()
                for warmed, producers in heralds.get(input_id, ()):
                    for producer in producers:
                        heralded[producer] = now
                        warmed(producer)
                continue
            if not size:  # a greeting (no Retriever message is empty), maybe before its listener; or a
                # warm-up message no loop here listens to (a group's members rehearse on their own)
                if input_id not in self.greeted:
                    with self.greetings:
                        self.greeted.add(input_id)
                        self.greetings.notify_all()
                continue
            data = _bytes_of(value, size)
            entries = listeners.get(input_id, ())
            for handler, kind, key, _ in entries:
                handler((kind, key, data))
            now = clock()
            before = last.get(input_id, now)
            last[input_id] = now
            # (not if each producer's warm-up message came since the input's last event: the
            # producer warms this thread up for its next one itself, the whole way: warmed)
            if now - before >= WARM_AFTER_IDLE_NS and not all(heralded.get(key[0] if kind == DATA else key, -1) > before
                                                              for _, kind, key, _ in entries):
                due, warm = now + now - before - WARM_AHEAD_NS, (value, entries)
            else:
                due, warm = None, None


def _warm(value, entries: list) -> None:
    """The receiving thread's own work on an input's event once more, results unused: the view
    of its bytes and, if a listener steps on this thread (its handler is its loop's ``receive``,
    not its queue's ``put``: NodeLoop.receive), their decoding, which the loop does first. The
    loop's Warmup rehearses the decoding too, but on the loop's main thread; the thread that
    will decode the event is this one, and it ran cold: warmed here, the sink's stage from dora's
    ``next()`` to the step went from ~85 to ~62 µs at 64 B, the medians of 13 interleaved runs
    (no change seen at 64 KiB: benchmarks/reports/fig7a.md, 2026-12-05, dora13). A message the
    loop refused as garbage when it came is refused again, and warms no further."""
    data = _bytes_of(value, len(value))
    for handler, kind, key, put in entries:
        if kind == DATA and handler is not put:
            try:
                decode_events(data, expected=key)
            except WireError:
                pass
            return


def _bytes_of(value, size: int) -> memoryview:
    """A view of the bytes of ``value``, a uint8 array of ``size`` elements: of dora's buffer
    (the array's values, as unsigned bytes: no copy), which it holds: dora reuses none while a
    view of it lives."""
    data = memoryview(value.buffers()[1]).cast("B")
    if len(data) != size:  # (a slice of a bigger buffer, at an offset or not: never seen)
        data = data[value.offset:value.offset + size]
    return data


class DoraTransport(Transport):
    """Events and progress of the node ``node_id`` on ``link``, its process's dora node."""

    def __init__(self, link: DoraLink, names: DoraNames, node_id: str):
        self.link, self.names, self.id = link, names, node_id
        self.routes = {input_id: tuple(stream) for input_id, stream in names.inputs[node_id].items()}
        self.listening: list | None = None

    def declare_inputs(self, streams, sources, inline, put) -> None:
        self.link.node()
        if self.listening is None and self.routes:
            self.listening = self.link.listen(self.routes, inline or put, put)

    def declare_warm(self, sources, warmed) -> None:
        # on the receiving thread, over the route the producers' events take (DoraNames.warm_inputs)
        wanted = set(sources)
        warm_inputs = {input_id: [p for p in producers if p in wanted]
                       for input_id, producers in self.names.warm_inputs(self.names.nodes[self.id]).items()}
        warm_inputs = {input_id: producers for input_id, producers in warm_inputs.items() if producers}
        if warm_inputs and self.listening is not None:
            self.listening += self.link.listen_warm(warm_inputs, warmed)

    def declare_outputs(self, ports, consumed):
        node = self.link.node()
        outputs, progress_output = self.names.outputs[self.id], self.names.progress.get(self.id)
        publishers = {port: DoraOutput(node, outputs[port]) if port in outputs else Nowhere() for port in ports}
        progress = DoraOutput(node, progress_output) if consumed and progress_output else Nowhere()
        for output in {*outputs.values(), *([progress_output] if progress_output else [])}:
            node.send_output(output, GREETING)
        # the empty message a loop puts before a moment it foresees (node/timing.py: Warmup) goes
        # to dora's daemon on an output no input takes: the send path up to the routing, warm
        warm = self.names.warm(self.names.nodes[self.id]) if consumed and progress_output else None
        return publishers, progress, None if warm is None else DoraOutput(node, warm)

    def publisher(self, port: str) -> Nowhere:
        return Nowhere()

    def await_routes(self, timeout: float, stopping: Callable[[], bool]) -> None:
        self.link.await_greetings(set(self.routes), timeout, stopping)

    def undeclare(self) -> None:
        if self.listening is not None:
            self.link.leave(self.listening)
        self.listening = None
