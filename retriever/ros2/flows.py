"""``Ros2Subscriber`` and ``Ros2Publisher``: a ROS 2 topic as a source or a sink of a pipeline,
over rmw_zenoh, with no ROS installed.

::

    with Pipeline("teleop") as pipe:
        joints = Ros2Subscriber("/joint_states", "sensor_msgs/msg/JointState") @ Rate(hz=100)
        ctrl = Controller() @ Rate(hz=100)                      # step(self, msg) -> {"msg": ...}
        cmd = Ros2Publisher("/cmd_vel", "geometry_msgs/msg/Twist") @ Trigger("msg")
        joints.then(ctrl, sync=Latest())
        ctrl.then(cmd)

**Event time is arrival.** Each ROS message becomes one event of the subscriber's ``msg`` port
at the subscriber's first tick after it arrived (several in one tick are a Burst, in arrival
order), so its tag is a time of this run's clock, like every other event's. The message's own
``header.stamp`` rides in the value (``value["stamp"]``, ns) for a flow that wants it. Not the
tag by default, because a stamp is another clock's reading: a robot's, whose offset from this
run's HLC nobody measured, or simulated time (``use_sim_time``), or zero from a node that never
sets it; a tag from it could lie in the run's past or far in its future, and a tag that jumps
would reorder what every consumer sees. Arrival is what the pipeline could know when it ticked,
which is what replay needs: the subscriber is a source, so ``retriever replay`` takes its events
from the log and re-runs its consumers on exactly those.

The publisher announces itself as rmw_zenoh does (a node token and an ``MP`` token, keys.py), so
``ros2 topic list`` and ``ros2 topic info -v`` see it, and puts each value's CDR on the topic's
key with the attachment rmw_zenoh's subscriptions require (attachment.py). Its step reaches
outside the program, so ``retriever replay`` takes its (empty) outputs from the log rather than
publishing again (``replay="log"``).
"""

from __future__ import annotations

import collections
import threading
import time
import warnings
from collections.abc import Sequence

import numpy as np
import zenoh

from ..errors import RetrieverWarning
from ..flow import Flow
from ..flow.burst import MAX_BURST, Burst
from . import types
from .attachment import Attachment, encode
from .keys import (PUBLISHER, SUBSCRIPTION, QoS, check_domain_id, check_namespace, check_node_name, fully_qualified,
                   topic_key)
from .node import ROS_ROUTER, Ros2Node, domain_id_from_env, gid

#: messages a subscriber holds between two ticks; past it the oldest are dropped (and counted)
MAX_PENDING = 1024
#: bytes of messages a subscriber holds between two ticks (1024 frames of 6 MB would be 6 GB);
#: past it the oldest are dropped (and counted), and a message bigger on its own is dropped too
MAX_PENDING_BYTES = 256 << 20
#: what a list of numbers on a publisher's input holds (numpy's scalars and bools among them)
_NUMBERS = (int, float, np.number, np.bool_)


class _Ros2Endpoint(Flow):
    """What both ends share: the topic (relative names resolve in ``namespace``, ``~/name`` in the
    node's private namespace), its type (a standard one, or one given by its ``.msg`` text as
    ``msgdef``), and the ROS node they are: ``node`` in ``namespace``, in ROS domain
    ``domain_id`` (``ROS_DOMAIN_ID`` by default), whose Zenoh session connects to ``connect``
    (rmw_zenohd on this machine by default) and listens on ``listen``. A topic, node name or
    namespace that breaks a rule of ROS 2's for names (no ``__``, no ``/`` at the end, no token
    starting with a digit, ASCII letters, digits and ``_`` only: keys.NAME_RULES) is a
    ValueError that names the rule."""

    def __init__(self, topic: str, msgtype: str, *, node: str = "retriever", namespace: str = "/",
                 domain_id: int | None = None, connect: Sequence[str] = (ROS_ROUTER,),
                 listen: Sequence[str] = ("tcp/127.0.0.1:0",), msgdef: str | None = None):
        if msgdef is not None:
            types.register_msg(msgtype, msgdef)
        types.check_type(msgtype)
        # names as ROS 2's rules allow them (keys.py; a name that breaks one is refused, naming it)
        self.node_name, self.namespace = check_node_name(node), check_namespace(namespace)
        self.topic, self.msgtype = fully_qualified(topic, self.namespace, self.node_name), msgtype
        self.domain_id = domain_id_from_env() if domain_id is None else check_domain_id(domain_id)
        self.connect, self.listen = list(connect), list(listen)
        self.type_hash = types.type_hash(msgtype)
        self.key = topic_key(self.domain_id, self.topic, msgtype, self.type_hash)
        self._begin()

    def _begin(self) -> None:
        """What an end starts with besides its topic: its counts (reset() starts them again)."""

    def _open_node(self) -> Ros2Node:
        return Ros2Node(self.node_name, namespace=self.namespace, domain_id=self.domain_id,
                        connect=self.connect, listen=self.listen)


class Ros2Subscriber(_Ros2Endpoint):
    """A source flow: the messages of a ROS 2 topic, each an event of port ``msg`` (types.py says
    which value a message becomes). ``received``, ``dropped`` (past ``max_pending`` messages,
    ``MAX_PENDING`` by default, or ``max_pending_bytes`` of them, ``MAX_PENDING_BYTES``, between
    two ticks: the oldest go) and ``undecodable`` (not CDR of
    the type) count what came. They live in the process that steps the flow (a worker's, on the
    real-time backends), so the flow says them where a user looks: a tick that dropped or could
    not decode a message says so in its step record, ``detail["flow"] = {"received": n,
    "dropped": n, "undecodable": n}`` (the counts since the record before that said them), in the
    trace and the log (``retriever log show`` prints it); and the end of the run warns
    (RetrieverWarning) with the totals of a subscriber that dropped or could not decode any."""

    def __init__(self, topic: str, msgtype: str, *, node: str = "retriever", namespace: str = "/",
                 domain_id: int | None = None, connect: Sequence[str] = (ROS_ROUTER,),
                 listen: Sequence[str] = ("tcp/127.0.0.1:0",), msgdef: str | None = None,
                 max_pending: int = MAX_PENDING, max_pending_bytes: int = MAX_PENDING_BYTES):
        for name, bound in (("max_pending", max_pending), ("max_pending_bytes", max_pending_bytes)):
            if isinstance(bound, bool) or not isinstance(bound, int) or bound < 1:
                raise ValueError(f"Ros2Subscriber: {name} must be an int >= 1, got {bound!r}")
        self.max_pending, self.max_pending_bytes = max_pending, max_pending_bytes
        super().__init__(topic, msgtype, node=node, namespace=namespace, domain_id=domain_id, connect=connect,
                         listen=listen, msgdef=msgdef)

    def _begin(self) -> None:
        self.received = self.dropped = self.undecodable = 0
        self._said = (0, 0, 0)  # received, dropped and undecodable as the last step record said

    def setup(self) -> None:
        self._pending: collections.deque = collections.deque()
        self._pending_bytes = 0
        self._lock = threading.Lock()
        self._ros = self._open_node()
        self._ros.declare(SUBSCRIPTION, self.topic, self.msgtype, self.type_hash, QoS())
        # called on Zenoh's own thread (indirect=False), not on a Python thread Zenoh starts for
        # it: an in-process run tears its flows down at the interpreter's exit, which waits for
        # every Python thread first, so such a thread would hold the process forever
        self._subscriber = self._ros.session.declare_subscriber(
            self.key, zenoh.handlers.Callback(self._arrived, indirect=False))

    def _arrived(self, sample) -> None:
        """On Zenoh's thread: keep the payload for the next tick (decoding waits for the step),
        within both bounds: past either, the oldest go (a payload past the byte bound on its own
        is not kept at all)."""
        size = len(sample.payload)
        with self._lock:
            if size > self.max_pending_bytes:
                self.dropped += 1
                return
            pending = self._pending
            while pending and (len(pending) >= self.max_pending or self._pending_bytes + size > self.max_pending_bytes):
                self._pending_bytes -= len(pending.popleft())
                self.dropped += 1
            pending.append(sample.payload.to_bytes())
            self._pending_bytes += size

    @property
    def pending(self) -> int:
        """The messages that arrived and wait for the next tick."""
        lock = getattr(self, "_lock", None)
        if lock is None:  # not set up
            return 0
        with lock:
            return len(self._pending)

    def step(self):
        with self._lock:
            taken = [self._pending.popleft() for _ in range(min(len(self._pending), MAX_BURST))]
            self._pending_bytes -= sum(map(len, taken))
        values = []
        for payload in taken:
            try:
                values.append(types.to_value(types.deserialize(payload, self.msgtype), self.msgtype))
            except Exception:  # a stranger's bytes on the key: counted, never handed on
                self.undecodable += 1
        self.received += len(values)
        with self._lock:
            counts = (self.received, self.dropped, self.undecodable)
        if counts[1:] != self._said[1:]:  # a message was lost since the last record: say it in this one
            self.add_step_detail(**{name: now - before for name, now, before in
                                    zip(("received", "dropped", "undecodable"), counts, self._said)})
            self._said = counts
        return {"msg": Burst(values)} if values else None

    def teardown(self) -> None:
        self._subscriber.undeclare()
        self._ros.close()
        if self.dropped or self.undecodable:
            hint = ("tick the subscriber faster than the topic comes, or raise max_pending(_bytes)" if self.dropped else
                    "another type is published on the topic's key, or another definition of the type")
            warnings.warn(
                f"Ros2Subscriber of {self.topic} ({self.msgtype}) received {self.received} message(s), dropped "
                f"{self.dropped} (past max_pending={self.max_pending} messages or max_pending_bytes="
                f"{self.max_pending_bytes} bytes between two ticks) and could not decode "
                f"{self.undecodable} (not CDR of {self.msgtype})\n    hint: {hint}; the step records' "
                "detail[\"flow\"] say which ticks lost them", RetrieverWarning, stacklevel=2)


class Ros2Publisher(_Ros2Endpoint):
    """A sink flow: the value on its input port ``msg`` published on a ROS 2 topic at each tick
    (types.py says which message a value becomes), as an rmw_zenoh publisher does; behind
    ``Trigger("msg")`` and ``Latest()``, one message per event. ``published`` counts them.

    A ``list`` on ``msg`` is what a ``Queue()`` (or ``Window``) edge delivers: the events since the
    last tick (a subscriber's Burst among them). Each of its elements is published as a message of
    its own, in order; an empty list publishes nothing. The one exception is a list of numbers for
    a type one value of which is a list of numbers (a Vector3, Point or Quaternion ``[x, y, z]``, a
    MultiArray's data: ``types.list_of_numbers_is_one_value``), since no element of it could be a
    message: that list is one message. So a MultiArray of two or more dimensions comes as a numpy
    array, not a nested list. Every element is converted before any is put: a tick whose list holds
    one that does not convert publishes none (and the error says which).

    A message with a ``std_msgs/msg/Header`` (an Image, a JointState, a PoseStamped...) whose value
    says no ``frame_id`` (an image array alone, a dict without the key) gets ``frame_id``: by default
    the ROS node's name (``node``), so that a subscriber can tell whose frame it is rather than
    reading an empty one; give the frame its coordinates are in (``frame_id="camera_optical"``)."""

    def __init__(self, topic: str, msgtype: str, *, node: str = "retriever", namespace: str = "/",
                 domain_id: int | None = None, connect: Sequence[str] = (ROS_ROUTER,),
                 listen: Sequence[str] = ("tcp/127.0.0.1:0",), msgdef: str | None = None,
                 frame_id: str | None = None):
        if frame_id is not None and not isinstance(frame_id, str):
            raise TypeError(f"Ros2Publisher: frame_id must be a str, got {type(frame_id).__name__}")
        super().__init__(topic, msgtype, node=node, namespace=namespace, domain_id=domain_id, connect=connect,
                         listen=listen, msgdef=msgdef)
        self.frame_id = self.node_name if frame_id is None else frame_id

    def _begin(self) -> None:
        self.published = 0
        self.configure(replay="log")

    def setup(self) -> None:
        self._one_value_is_a_list = types.list_of_numbers_is_one_value(self.msgtype)
        self._ros = self._open_node()
        token = self._ros.declare(PUBLISHER, self.topic, self.msgtype, self.type_hash, QoS())
        self._gid = gid(token)
        self._publisher = self._ros.session.declare_publisher(self.key)
        self._sequence = 0

    def _payload(self, value) -> bytes:
        return types.serialize(types.from_value(value, self.msgtype, frame_id=self.frame_id), self.msgtype)

    def step(self, msg):
        if type(msg) is not list:
            payloads = [self._payload(msg)]
        elif msg and self._one_value_is_a_list and all(isinstance(v, _NUMBERS) for v in msg):
            payloads = [self._payload(msg)]
        else:  # a Queue's (or Window's) events: a message each, all converted before any is put
            payloads = []
            for i, value in enumerate(msg):
                try:
                    payloads.append(self._payload(value))
                except (TypeError, ValueError) as error:
                    kind = TypeError if isinstance(error, TypeError) else ValueError
                    raise kind(f"element {i} of the list of {len(msg)} on msg (a Queue's events, each published "
                               f"as a message; none of them was): {error}") from error
        for payload in payloads:
            self._sequence += 1
            attachment = Attachment(self._sequence, time.time_ns(), self._gid)
            self._publisher.put(payload, attachment=encode(attachment))
            self.published += 1

    def teardown(self) -> None:
        self._publisher.undeclare()
        self._ros.close()

