"""A node's events and progress over dora: the transport a node loop is handed in a dora run.

    dora inputs ──receiving thread: node.next()──▶ the loop's inbox (or handled right there, as a
                                                   Zenoh subscriber's callback would: INLINE_STEP_NS)
    loop ──send_output(port | "progress")──▶ dora ──▶ the consumers' inputs

A receiving thread that dies hands its error to the loop (inbox.FAILED), which raises it: the
run fails naming it, where the node would otherwise hear nothing more, and never step again.

Everything else is the node loop's (backends/zenoh/node/): clocks, frontiers, deadlines, LET,
step records. The run's control plane stays on the run's private Zenoh hub: ``start`` and
``stop``, the reports that become the trace and the log, and the answers to a consumer that asks
a producer for its frontier (dora has no queries).
"""

from __future__ import annotations

import threading
import time
from typing import Callable

from ..zenoh.node import DATA, FAILED, PROGRESS, Transport
from .dataflow import PROGRESS as PROGRESS_OUTPUT
from .dataflow import DoraNames

#: how long the receiving thread waits in ``node.next()`` before it looks whether to stop
RECEIVE_TIMEOUT_S = 0.1

#: An empty message: a producer's greeting, sent once on each of its dora outputs when it declares
#: them. A consumer says ready only once a greeting came through each of its inputs: dora's routes
#: are set up lazily, and without this the first events of a run can take a good part of a second
#: to arrive (a LET run would then differ from in-process: its first ticks would run without them).
GREETING = b""


class DoraOutput:
    """One dora output of this node, put to as a Zenoh publisher is."""

    __slots__ = ("node", "output")

    def __init__(self, node, output: str):
        self.node, self.output = node, output

    def put(self, message: bytes) -> None:
        self.node.send_output(self.output, message)


class Nowhere:
    """An output port no edge names (an untyped flow's extra key): nobody consumes it, and the
    dataflow has no such output; its events still reach the log through the reports."""

    def put(self, message: bytes) -> None:
        pass


class DoraTransport(Transport):
    """Events and progress of the node ``node_id`` with this process's dora node."""

    def __init__(self, names: DoraNames, node_id: str):
        self.names, self.id = names, node_id
        self.routes = {input_id: (src, port) for input_id, (src, port) in names.inputs[node_id].items()}
        self.dora_node = None
        self.receiver: threading.Thread | None = None
        self.receiving = False
        self.greeted: set[str] = set()  # inputs a producer's greeting came through
        self.greetings = threading.Condition()
        self.failure: Exception | None = None  # what ended the receiving thread, if it died

    def _dora(self):
        """This process's dora node (created once: dora starts the dataflow when every node has one)."""
        if self.dora_node is None:
            from dora import Node

            self.dora_node = Node()
        return self.dora_node

    def declare_inputs(self, streams, sources, inline, put) -> None:
        node = self._dora()
        if self.receiver is None and self.routes:
            self.receiving = True
            self.receiver = threading.Thread(target=self._receive, args=(node, inline or put, put), daemon=True,
                                             name=f"retriever-dora-{self.id}")
            self.receiver.start()

    def declare_outputs(self, ports, consumed):
        node = self._dora()
        outputs = self.names.outputs[self.id]
        publishers = {port: DoraOutput(node, outputs[port]) if port in outputs else Nowhere() for port in ports}
        progress = DoraOutput(node, PROGRESS_OUTPUT) if consumed else Nowhere()
        for output in {*outputs.values(), *([PROGRESS_OUTPUT] if consumed else [])}:
            node.send_output(output, GREETING)
        return publishers, progress, None

    def publisher(self, port: str) -> Nowhere:
        return Nowhere()

    def await_routes(self, timeout: float, stopping: Callable[[], bool]) -> None:
        give_up, wanted = time.monotonic() + timeout, set(self.routes)
        with self.greetings:  # (in short waits: a stop, from a signal handler, notifies no one)
            while not (stopping() or self.greeted >= wanted or self.failure) and time.monotonic() < give_up:
                self.greetings.wait(0.1)
        if self.failure is not None:  # no greeting can come any more
            raise self.failure

    def undeclare(self) -> None:
        self.receiving = False
        if self.receiver is not None and self.receiver is not threading.current_thread():
            self.receiver.join()
        self.receiver = None

    def _receive(self, node, receive, put) -> None:
        """The receiving thread: every input event, in dora's order, to the loop (until dora says
        every sender is gone, or the transport is undeclared); if it dies, its error, to the loop."""
        try:
            self._take_events(node, receive, put)
        except Exception as exc:
            with self.greetings:
                self.failure = exc
                self.greetings.notify_all()
            put((FAILED, None, exc))

    def _take_events(self, node, receive, put) -> None:
        routes = self.routes
        while self.receiving:
            event = node.next(timeout=RECEIVE_TIMEOUT_S)
            if event is None:  # the stream ended: after a STOP, or dora run (its daemon) is gone
                return
            if event["type"] != "INPUT":  # a timeout (ERROR), INPUT_CLOSED, STOP: queued inputs still follow
                continue
            route = routes.get(event["id"])
            if route is None:
                continue
            # a view of dora's buffer, which it holds: dora reuses none while a view of it lives
            data = memoryview(event["value"].to_numpy(zero_copy_only=False))
            if not len(data):  # a greeting (no Retriever message is empty)
                with self.greetings:
                    self.greeted.add(event["id"])
                    self.greetings.notify_all()
                continue
            src, port = route
            if port is None:
                put((PROGRESS, src, data))
            else:
                receive((DATA, (src, port), data))
