"""``EventStream``: sample a recorded stream with a sync policy, outside any pipeline.

Useful in notebooks and tests to see exactly what a policy hands a flow::

    frames = EventStream()
    frames.append(0.000, f0); frames.append(0.033, f1)
    frames.sample(Latest(), now=0.05)          # -> f1
"""

from __future__ import annotations

from typing import Any, Generic, TypeVar

from ..sync import PortBuffer, SyncPolicy
from ..time import Tag, seconds_to_ns
from ..trace import Event

T = TypeVar("T")


class EventStream(Generic[T]):
    """A tag-ordered stream of values from one producer port, sampled like an edge would be.

    Consumption state (Queue cursors, LatestDistinct) is kept per policy object, so repeated
    ``sample`` calls with one policy behave like successive ticks of one consumer.
    """

    def __init__(self, name: str = "stream"):
        self.name = name
        self._events: list[Event] = []
        self._buffers: dict[int, PortBuffer] = {}

    def append(self, t: float | int | Tag, value: T) -> Event:
        """Add a value at time ``t`` (seconds, or a ``(ns, microstep)`` tag); times must not decrease."""
        tag = t if isinstance(t, tuple) else (seconds_to_ns(t), 0)
        if self._events and tag < self._events[-1].tag:
            raise ValueError(f"EventStream {self.name!r}: tag {tag} is earlier than the last one "
                             f"{self._events[-1].tag}; append in time order")
        ev = Event(tag, self.name, "value", len(self._events), value)
        self._events.append(ev)
        for buf in self._buffers.values():
            buf.insert((ev.tag, ev.node, ev.port, ev.seq, ev.value))
        return ev

    def sample(self, policy: SyncPolicy, now: float | int | Tag) -> Any:
        """What a tick at ``now`` would receive through ``policy`` (MISSING if nothing)."""
        tau = now if isinstance(now, tuple) else (seconds_to_ns(now), 0)
        buf = self._buffers.get(id(policy))
        if buf is None:
            buf = self._buffers[id(policy)] = PortBuffer()
            for ev in self._events:
                buf.insert((ev.tag, ev.node, ev.port, ev.seq, ev.value))
        value, _ids, _dropped, commit = policy.select(buf, tau)
        policy.commit_to(buf, commit)
        return value

    def __len__(self) -> int:
        return len(self._events)
