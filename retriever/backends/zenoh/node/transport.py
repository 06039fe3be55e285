"""How a node's events and progress messages travel: the seam a transport fills.

A node loop speaks to its consumers through publishers (``put(bytes)``) and hears its producers
through two callbacks: ``receive`` for data messages, ``put`` for progress messages (both take
an inbox item, see inbox.py). The run's control plane is not a transport's: the loop subscribes
to the run's control and answers progress queries on the run's Zenoh session whatever carries
its events. :class:`ZenohTransport` carries them on that session; :class:`~.linked.LinkedTransport`
(linked.py) carries those between processes of one host over same-host links (backends/zenoh/link/)
and the others on that session; the dora backend's transport (backends/dora/link.py) carries them
over dora.
"""

from __future__ import annotations

import ctypes
import weakref
from threading import get_ident
from typing import Callable

import zenoh

from ..wire import RELIABLE, KeySpace
from .inbox import DATA, PROGRESS


class Transport:
    """The base: what a node loop asks of the way its events travel."""

    def declare_inputs(self, streams: list[tuple[str, str]], sources: list[str],
                       inline: Callable[[tuple], None] | None, put: Callable[[tuple], None]) -> None:
        """Start hearing the input ``streams`` (producer, port) and the ``sources``' progress:
        each data message to ``inline`` (to run on the receiving thread), or to ``put`` when
        ``inline`` is None; each progress message to ``put``."""
        raise NotImplementedError

    def declare_warm(self, sources: list[str], warmed: Callable[[str], None]) -> None:
        """Hear the ``sources``' warm-up messages (a producer's, 1 ms before a tick it foresees,
        timing.py): each calls ``warmed(source)`` on the thread that receives their data
        messages, if the transport has one that may step (else: nothing to warm, no call)."""

    def declare_outputs(self, ports: list[str], consumed: bool) -> tuple[dict, object, object | None]:
        """Start speaking: a publisher per output port, one for progress, and one to warm the put
        path with (see timing.WARM_AHEAD_NS), or None if the transport has none."""
        raise NotImplementedError

    def publisher(self, port: str):
        """A publisher for an output port no edge uses (an untyped flow's extra key)."""
        raise NotImplementedError

    def redeclare_inputs(self) -> None:
        """Declare the input subscriptions again, then drop the old ones (see NodeLoop.redeclare)."""

    def await_routes(self, timeout: float, stopping: Callable[[], bool]) -> None:
        """Before the node says ready: wait until its events' routes carry."""

    def join_links(self, timeout: float, stopping: Callable[[], bool],
                   gone: Callable[[], set[str]] | None = None) -> None:
        """Connect the events' routes that are made once every end is up (same-host links:
        node/linked.py), ``timeout`` at most: at a node's first start (``gone`` None) after
        the start's barrier, at a restarted one's as it comes. Nothing by default."""

    def end_of_stream(self) -> None:
        """The node's loop finished: nothing more comes from this process (a consumer then does
        not wait for a new one). Nothing by default."""

    def undeclare(self) -> None:
        """Stop hearing and speaking: everything declared goes."""
        raise NotImplementedError


class Tap:
    """What a diagnostic sees of the Zenoh transports of its process (:func:`tap_transports`): each
    publisher a loop puts to, and each callback a data subscriber calls, handed back as they are
    or wrapped (benchmarks/zenoh_probe.py stamps the puts and the callbacks)."""

    def publisher(self, key: str, publisher):
        return publisher

    def callback(self, key: str, callback: Callable):
        return callback


_tap: Tap | None = None


def tap_transports(tap: Tap | None) -> None:
    """Hand what each :class:`ZenohTransport` built from now on in this process declares through
    ``tap`` (None: no tap)."""
    global _tap
    _tap = tap


class ZenohTransport(Transport):
    """Events and progress on the run's Zenoh session, under ``keys``."""

    def __init__(self, session: zenoh.Session, keys: KeySpace, node_id: str):
        self.session, self.keys, self.id = session, keys, node_id
        self.tap = _tap
        self.subscribers: list = []
        self.publishers: list = []  # every one undeclared at the end (see undeclare)
        self.inputs: tuple | None = None  # declare_inputs' arguments, for redeclare_inputs
        self.warm: tuple | None = None  # declare_warm's, for redeclare_inputs
        self.warm_subscribers: list = []

    def declare_inputs(self, streams, sources, inline, put) -> None:
        self.inputs = (streams, sources, inline, put)
        s, keys = self.session, self.keys
        for src, src_port in streams:
            key = keys.data(src, src_port)
            callback = _data_callback((src, src_port), inline, put)
            if self.tap is not None:
                callback = self.tap.callback(key, callback)
            if inline is not None:
                # called on Zenoh's receiving thread itself (indirect=False), not on the Python
                # thread zenoh-python would start for the callback and wake for each sample: that
                # wake-up was one hand-off more per message than `for sample in subscriber:`
                # (benchmarks/reports/latency.md, 2026-12-05 lat12). Zenoh's thread then takes
                # the GIL itself: while the main thread runs Python it waits, up to the
                # interpreter's switch interval (5 ms), and receives nothing meanwhile. So only
                # for a loop that may run ticks on the receiving thread (NodeLoop's
                # INLINE_STEP_NS: short steps, no cycle, no setup); a loop that only queues
                # keeps zenoh-python's thread between Zenoh's and its long steps.
                callback = zenoh.handlers.Callback(callback, indirect=False)
            self.subscribers.append(s.declare_subscriber(key, callback))
        for src in sources:
            self.subscribers.append(s.declare_subscriber(
                keys.progress(src), lambda sample, k=src: put((PROGRESS, k, sample.payload.to_bytes()))))

    def declare_warm(self, sources, warmed) -> None:
        # on Zenoh's receiving thread, as the data callbacks of a loop that may step there: the
        # warm-up message comes over the link its data messages come over, so it warms that
        # thread, its core and Zenoh's receive path (which a rehearsal on the main thread does
        # not), and the producer's send path down to the socket (benchmarks/reports/latency.md)
        self.warm = (sources, warmed)
        loop = weakref.WeakMethod(warmed)
        for src in sources:
            def callback(sample, src=src):
                if get_ident() not in _kept:
                    _keep_thread_state()
                sample.payload.to_bytes()  # (as a data message's callback does; its content is never read)
                bound = loop()
                if bound is not None:
                    bound(src)

            self.warm_subscribers.append(self.session.declare_subscriber(
                self.keys.warm(src), zenoh.handlers.Callback(callback, indirect=False)))

    def declare_outputs(self, ports, consumed):
        keys = self.keys
        publishers = {port: self._declare(keys.data(self.id, port)) for port in ports}
        progress = self._declare(keys.progress(self.id))
        warm = self.session.declare_publisher(keys.warm(self.id), express=True)
        self.publishers.append(warm)
        return publishers, progress, warm

    def publisher(self, port: str):
        return self._declare(self.keys.data(self.id, port))

    def _declare(self, key: str) -> zenoh.Publisher:
        # BLOCK, not Zenoh's default DROP: a dropped event would leave a gap in its stream's seqs
        # that no frontier can cross (a slow consumer backs its producer up instead)
        publisher = self.session.declare_publisher(key, express=True, congestion_control=RELIABLE)
        self.publishers.append(publisher)
        return publisher if self.tap is None else self.tap.publisher(key, publisher)

    def redeclare_inputs(self) -> None:
        if self.inputs is None:
            return
        old, self.subscribers = self.subscribers, []
        self.declare_inputs(*self.inputs)
        if self.warm is not None:
            old, self.warm_subscribers = old + self.warm_subscribers, []
            self.declare_warm(*self.warm)
        for d in old:
            d.undeclare()

    def undeclare(self) -> None:
        # every declaration undeclared: one left holds the session, and with it its shared
        # memory, which then outlives the process in /dev/shm (Zenoh's exit() skips it)
        for d in [*self.subscribers, *self.warm_subscribers, *self.publishers]:
            d.undeclare()
        self.subscribers, self.warm_subscribers, self.publishers = [], [], []


def _data_callback(stream: tuple[str, str], inline: Callable[[tuple], None] | None,
                   put: Callable[[tuple], None]) -> Callable:
    """The Zenoh callback of ``stream``'s data messages: each to ``inline``, held weakly as
    hub.weak_callback holds a method (why: there) but without its wrapper's call (one call less
    per message received), or to ``put`` when ``inline`` is None."""
    if inline is None:
        def queue(sample):
            put((DATA, stream, sample.payload.to_bytes()))

        return queue
    loop = weakref.WeakMethod(inline)

    def receive(sample):
        if get_ident() not in _kept:
            _keep_thread_state()
        bound = loop()
        if bound is not None:
            bound((DATA, stream, sample.payload.to_bytes()))

    return receive


#: the threads of Zenoh's whose Python thread state is kept (:func:`_keep_thread_state`)
_kept: set[int] = set()


def _keep_thread_state() -> None:
    """Keep the Python thread state of the Zenoh thread this runs on (in a callback with
    indirect=False) from one callback to the next. zenoh-python takes the GIL for each callback
    with PyGILState_Ensure, which, on a thread Python did not start, makes a new thread state
    and deletes it after: each message then paid for a thread state made and freed, its frame
    stack's 16 KiB chunk mapped and unmapped (mmap, munmap, a page fault) and run cold. One
    PyGILState_Ensure of our own, never released, keeps the count above zero, so the state
    stays, as a Python thread's does. It goes with the interpreter; a thread that ends leaves
    it unused (Zenoh's threads end with the session, at the process's end)."""
    ctypes.pythonapi.PyGILState_Ensure()
    _kept.add(get_ident())
