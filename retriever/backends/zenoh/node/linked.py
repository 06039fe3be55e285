"""A node's events and progress over same-host links (backends/zenoh/link/), the rest on Zenoh.

:class:`LinkedTransport` is a :class:`ZenohTransport` given the node's :class:`LinkPlan`: the
edges whose both ends are processes of this host (worker/links.py decides, from the spec, the
same way at both ends). As a producer with such consumers it makes its :class:`LinkServer` at
``link-<node>.sock`` in the run's folder when it declares its outputs (before it says ready), and
sends on it each data message (kind ``1 + port``'s index among its sorted output ports) and its
progress (kind PROGRESS), in one order: a watermark never overtakes the data it covers. Zenoh
still gets each message when a consumer hears it there (a group's process), else only while the
Zenoh publisher's matching status says someone matches its key (a ``data/**`` watcher): with
only linked consumers and no watcher, no Zenoh put. As a consumer
it subscribes on Zenoh to none of a linked producer's data and progress keys; a
:class:`LinkClient` per linked producer hands its messages to the loop as the Zenoh callbacks
do (inline on the client's thread when the loop may step there, else queued).

When the links connect (:meth:`LinkedTransport.join_links`, worker/starts.py): a node's first
process after the start's barrier (every producer ready, its server made), before T0; a
restarted one as it comes (its producers run). A producer's first send waits for its planned
consumers there. A planned link that cannot connect at the start fails the run, naming the edge
and the socket. A link that closes under a consumer (its producer's process ended: handed over,
or died) is connected again as soon as the producer's new process listens at the same path,
unless the producer said it ended (END: its loop finished, nothing more comes).
"""

from __future__ import annotations

import sys
import threading
import time
import weakref
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

from ....errors import LinkError
from ..link import LinkClient, LinkServer
from .inbox import DATA, PROGRESS
from .transport import ZenohTransport

#: the kinds of a link's messages: progress, the end of the producer's stream, a warm-up (timing.py),
#: data (1 + the port's index)
PROGRESS_KIND, END_KIND, WARM_KIND, FIRST_DATA_KIND = 0, 255, 254, 1
MAX_LINKED_PORTS = WARM_KIND - FIRST_DATA_KIND
#: how often a consumer tries its producer's socket again while it is not there (the first try,
#: then at most this apart)
RECONNECT_FIRST_S, RECONNECT_MAX_S = 0.005, 0.1
#: after how long without its producer a consumer says so on stderr (once; and when it is back)
RECONNECT_SAY_S = 10.0


@dataclass(frozen=True)
class LinkPlan:
    """A node's same-host links: ``run`` (the namespace, which both ends check), ``path`` its own
    socket (None: no linked consumer), ``consumers`` the nodes that connect to it, ``producers``
    each linked producer's socket and sorted output ports, ``ports`` this node's own, and
    ``on_zenoh`` whether a consumer of it hears it on Zenoh (a group's process): then each of its
    messages is put there too, whatever Zenoh's matching status says."""

    run: str
    path: Path | None
    consumers: frozenset[str] = frozenset()
    producers: dict[str, tuple[Path, tuple[str, ...]]] = field(default_factory=dict)
    ports: tuple[str, ...] = ()
    on_zenoh: bool = False


class LinkPublisher:
    """An output port's (or the progress') publisher on a link: each message to the link's
    consumers with ``kind``, and to Zenoh too: always when ``always`` (a consumer there, which
    must miss none), else while something there matches its key (a watcher). Zenoh tells the
    matching listener on a task of its own, after its routes carry a new subscriber: a put made
    meanwhile would have reached it, and is not made (a watcher may miss its first messages; a
    consumer, whose missed message is a seq gap its stream holds open, must not: ``always``)."""

    __slots__ = ("server", "kind", "zenoh", "watched", "listener")

    def __init__(self, server: LinkServer, kind: int, zenoh_publisher, always: bool = False):
        self.server, self.kind, self.zenoh = server, kind, zenoh_publisher
        self.watched = always or zenoh_publisher.matching_status.matching
        self.listener = None if always else zenoh_publisher.declare_matching_listener(self._matching)

    def _matching(self, status) -> None:  # on a thread of Zenoh's
        self.watched = status.matching

    def put(self, message: bytes) -> None:
        self.server.send((message,), self.kind)
        if self.watched:
            self.zenoh.put(message)


class _Inbound:
    """One linked producer as this consumer hears it: its client, connected again after it
    closed (unless the producer ended)."""

    def __init__(self, transport: LinkedTransport, producer: str, path: Path, kinds: dict[int, tuple[str, str]],
                 progress: bool, inline: Callable | None, put: Callable):
        self.transport, self.producer, self.path = transport, producer, path
        self.client: LinkClient | None = None
        self.ended = False
        self.reconnecting: threading.Thread | None = None
        self.warmed = None  # declare_warm's: a weak method, called with the producer's name
        deliver = inline if inline is not None else put

        def on_message(kind: int, data: bytes) -> None:  # on the client's thread
            stream = kinds.get(kind)
            if stream is not None:
                deliver((DATA, stream, data))
            elif kind == PROGRESS_KIND:
                if progress:
                    put((PROGRESS, producer, data))
            elif kind == WARM_KIND:
                warmed = self.warmed() if self.warmed is not None else None
                if warmed is not None:
                    warmed(producer)
            elif kind == END_KIND:
                self.ended = True

        self.on_message = on_message

    def connect(self) -> None:
        """Connect now; LinkError if it cannot."""
        t = self.transport
        self.client = LinkClient(self.path, t.plan.run, self.producer, t.id, self.on_message, self.closed)

    def closed(self, why: LinkError | None) -> None:  # on the client's thread: its producer's end
        if self.ended or self.transport.closing.is_set():
            return
        self.reconnect()

    def reconnect(self) -> None:
        """From a thread of its own, try the socket until the producer's (new) process listens."""
        thread = threading.Thread(target=self._reconnect, name=f"link-{self.producer}-again", daemon=True)
        self.reconnecting = thread
        thread.start()

    def _reconnect(self) -> None:
        wait, closing = RECONNECT_FIRST_S, self.transport.closing
        say_at = time.monotonic() + RECONNECT_SAY_S
        while not closing.wait(wait):
            try:
                self.connect()
                if say_at is None:
                    print(f"retriever: worker '{self.transport.id}' reached its producer '{self.producer}' over its "
                          f"same-host link again", file=sys.stderr, flush=True)
                return
            except LinkError as e:
                wait = min(2 * wait, RECONNECT_MAX_S)
                if say_at is not None and time.monotonic() >= say_at:  # said once: nothing else would tell
                    say_at = None
                    print(f"retriever: worker '{self.transport.id}' has not reached its producer '{self.producer}' "
                          f"over its same-host link for {RECONNECT_SAY_S:g} s ({e}): it gets nothing from it "
                          f"until it does, and tries on", file=sys.stderr, flush=True)

    def close(self) -> None:
        """(after the transport's ``closing`` is set) The reconnecting thread ends first: a
        client it made meanwhile is then the one closed."""
        if self.reconnecting is not None and self.reconnecting is not threading.current_thread():
            self.reconnecting.join()
        if self.client is not None:
            self.client.close()


class LinkedTransport(ZenohTransport):
    """Events and progress on same-host links where ``plan`` says, on Zenoh elsewhere."""

    def __init__(self, session, keys, node_id: str, plan: LinkPlan):
        super().__init__(session, keys, node_id)
        self.plan = plan
        self.server: LinkServer | None = None
        self.inbound: dict[str, _Inbound] = {}
        self.listeners: list = []  # the publishers' matching listeners: undeclared before them
        self.closing = threading.Event()

    def declare_inputs(self, streams, sources, inline, put) -> None:
        linked = self.plan.producers
        super().declare_inputs([s for s in streams if s[0] not in linked], [s for s in sources if s not in linked],
                               inline, put)
        if self.inbound:  # (redeclare_inputs: the links stay as they are)
            return
        for producer, (path, ports) in linked.items():
            kinds = {FIRST_DATA_KIND + i: (producer, port) for i, port in enumerate(ports)
                     if (producer, port) in streams}
            if kinds or producer in sources:
                self.inbound[producer] = _Inbound(self, producer, path, kinds, producer in sources, inline, put)

    def declare_warm(self, sources, warmed) -> None:
        # a linked producer's warm-up comes on its link, to the thread its data comes to
        super().declare_warm([s for s in sources if s not in self.plan.producers], warmed)
        for src in sources:
            if src in self.inbound:
                self.inbound[src].warmed = weakref.WeakMethod(warmed)

    def declare_outputs(self, ports, consumed):
        plan = self.plan
        if plan.path is None:
            return super().declare_outputs(ports, consumed)
        if self.server is None:
            self.server = LinkServer(plan.path, plan.run, self.id)
        kind = {port: FIRST_DATA_KIND + i for i, port in enumerate(plan.ports)}
        tap, self.tap = self.tap, None  # (a diagnostic's tap sees the link's publishers, not Zenoh's under them)
        try:
            publishers, progress, warm = super().declare_outputs(ports, consumed)
        finally:
            self.tap = tap
        always = plan.on_zenoh
        linked = {port: LinkPublisher(self.server, kind[port], publisher, always)
                  for port, publisher in publishers.items()}
        progress = LinkPublisher(self.server, PROGRESS_KIND, progress, always)
        warm = LinkPublisher(self.server, WARM_KIND, warm, always)
        self.listeners += [p.listener for p in (*linked.values(), progress, warm) if p.listener is not None]
        if tap is not None:
            linked = {port: tap.publisher(self.keys.data(self.id, port), p) for port, p in linked.items()}
        return linked, progress, warm

    def join_links(self, timeout: float, stopping: Callable[[], bool],
                   gone: Callable[[], set[str]] | None = None) -> None:
        """Connect to each linked producer, then wait for each linked consumer, ``timeout`` at
        most. ``gone``: None at a node's first start (every producer listens, every consumer
        comes, or the run fails with a LinkError naming the edge and the socket); else a restarted
        process's, asked now and then for the nodes that will not come (done, or starting afresh
        themselves): a producer that is not there yet is connected to when it comes, a consumer
        that does not come within ``timeout`` is not waited for."""
        deadline = time.monotonic() + timeout
        left = {p: inbound for p, inbound in self.inbound.items()
                if inbound.client is None and inbound.reconnecting is None}
        wait = RECONNECT_FIRST_S
        while left and not stopping():
            errors = {}
            for producer, inbound in list(left.items()):
                try:
                    inbound.connect()
                    del left[producer]
                except LinkError as e:
                    errors[producer] = e
            if not left:
                break
            if time.monotonic() >= deadline:
                if gone is None:
                    producer, e = next(iter(errors.items()))
                    raise LinkError(f"the same-host link {producer} -> {self.id} cannot connect: {e}\n"
                                    f"    hint: {producer}'s worker makes it before it says ready; to carry the "
                                    f"run's edges on Zenoh instead: pipe.run(..., same_host_links=False) "
                                    f"(retriever run --no-links)") from None
                for inbound in left.values():  # (done, or it comes later: connected to then)
                    inbound.reconnect()
                break
            if gone is not None:
                for producer in gone() & set(left):
                    del left[producer]
            time.sleep(wait)
            wait = min(2 * wait, RECONNECT_MAX_S)
        server = self.server
        if server is None:
            return
        while not stopping():
            missing = set(self.plan.consumers) - set(server.consumers) - (gone() if gone is not None else set())
            if not missing:
                return
            left_s = deadline - time.monotonic()
            if left_s <= 0:
                if gone is None:
                    raise LinkError(f"the same-host link(s) {self.id} -> {', '.join(sorted(missing))}: no consumer "
                                    f"connected to {self.plan.path} within {timeout:g}s\n    hint: to carry the "
                                    f"run's edges on Zenoh instead: pipe.run(..., same_host_links=False) "
                                    f"(retriever run --no-links)")
                return
            server.wait_for(len(server.consumers) + 1, min(left_s, 0.25))

    def end_of_stream(self) -> None:
        if self.server is not None:
            self.server.send((b"",), END_KIND)

    def undeclare(self) -> None:
        for listener in self.listeners:
            listener.undeclare()
        self.listeners = []
        super().undeclare()
        self.closing.set()
        for inbound in self.inbound.values():
            inbound.close()
        if self.server is not None:
            self.server.close()
            self.server = None
