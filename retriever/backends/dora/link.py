"""A node's loop whose events and progress go over dora (the zenoh backend's loop otherwise).

    dora inputs ──receiving thread: node.next()──▶ the loop's inbox (or handled right there, as a
                                                   Zenoh subscriber's callback would: INLINE_STEP_NS)
    loop ──send_output(port | "progress")──▶ dora ──▶ the consumers' inputs

Everything else is :class:`~retriever.backends.zenoh.loop.NodeLoop`'s: clocks, frontiers,
deadlines, LET, step records. The run's control plane stays on the run's private Zenoh hub:
``start`` and ``stop``, the reports that become the trace and the log, and the answers to a
consumer that asks a producer for its frontier (dora has no queries).
"""

from __future__ import annotations

import threading
import time

from ..zenoh.hub import weak_callback
from ..zenoh.loop import _CONTROL, _DATA, _PROGRESS, NodeLoop
from .dataflow import PROGRESS, DoraNames

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


class DoraNodeLoop(NodeLoop):
    """A :class:`NodeLoop` that publishes and receives events and progress with a dora node."""

    def __init__(self, *args, names: DoraNames, **kwargs):
        super().__init__(*args, **kwargs)
        self.names = names
        self.routes = {input_id: (src, port) for input_id, (src, port) in names.inputs[self.id].items()}
        self.dora_node = None
        self.receiver: threading.Thread | None = None
        self.receiving = False
        self.greeted: set[str] = set()  # inputs a producer's greeting came through
        self.greetings = threading.Condition()

    def _dora(self):
        """This process's dora node (created once: dora starts the dataflow when every node has one)."""
        if self.dora_node is None:
            from dora import Node

            self.dora_node = Node()
        return self.dora_node

    def declare_inputs(self) -> None:
        put = self.inbox.put
        self._declared.append(self.session.declare_subscriber(
            self.keys.run_control(), lambda sample: put((_CONTROL, None, sample.payload.to_bytes()))))
        node = self._dora()
        if self.receiver is None and self.routes:
            self.receiving = True
            self.receiver = threading.Thread(target=self._receive_dora, args=(node,), daemon=True,
                                             name=f"retriever-dora-{self.id}")
            self.receiver.start()

    def declare_outputs(self) -> None:
        self._declared.append(self.session.declare_queryable(self.keys.progress(self.id),
                                                          weak_callback(self._answer_progress)))
        node = self._dora()
        outputs = self.names.outputs[self.id]
        self.publishers = {port: DoraOutput(node, outputs[port]) if port in outputs else Nowhere()
                           for port in self.ports}
        self.progress_publisher = DoraOutput(node, PROGRESS) if self.consumed else Nowhere()
        self.warm_publisher = None
        for output in {*outputs.values(), *([PROGRESS] if self.consumed else [])}:
            node.send_output(output, GREETING)

    def await_routes(self, timeout: float) -> None:
        give_up, wanted = time.monotonic() + timeout, set(self.routes)
        with self.greetings:  # (in short waits: a stop, from a signal handler, notifies no one)
            while not (self.stopping or self.greeted >= wanted) and time.monotonic() < give_up:
                self.greetings.wait(0.1)

    def _publisher(self, key: str) -> Nowhere:
        return Nowhere()

    def undeclare(self) -> None:
        self.receiving = False
        if self.receiver is not None and self.receiver is not threading.current_thread():
            self.receiver.join()
        self.receiver = None
        for d in self._declared:
            d.undeclare()
        self._declared = []
        self.publishers = {}

    def _receive_dora(self, node) -> None:
        """The receiving thread: every input event, in dora's order, to the loop (until dora says
        every sender is gone, or the loop is undeclared)."""
        receive = self._receive if self.inline else self.inbox.put
        put, routes = self.inbox.put, self.routes
        while self.receiving:
            event = node.next(timeout=RECEIVE_TIMEOUT_S)
            if event is None:
                return
            if event["type"] != "INPUT":  # a timeout (ERROR), INPUT_CLOSED, STOP: queued inputs still follow
                continue
            route = routes.get(event["id"])
            if route is None:
                continue
            data = memoryview(event["value"].to_numpy(zero_copy_only=False))  # a view of dora's buffer
            if not len(data):  # a greeting (no Retriever message is empty)
                with self.greetings:
                    self.greeted.add(event["id"])
                    self.greetings.notify_all()
                continue
            src, port = route
            if port is None:
                put((_PROGRESS, src, data))
            else:
                receive((_DATA, (src, port), data))
