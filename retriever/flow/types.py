"""``EventStream``: sample a recorded stream with a sync policy, outside any pipeline.

Useful in notebooks and tests to see exactly what a policy hands a flow::

    frames = EventStream()
    frames.append(0.000, f0); frames.append(0.033, f1)
    frames.sample(Latest(), now=0.05)          # -> f1
"""

from __future__ import annotations

from typing import Any, Generic, TypeVar

from ..sync import MISSING, LatestDistinct, PortBuffer, Queue, SyncPolicy
from ..time import Tag, seconds_to_ns
from ..trace import Event

T = TypeVar("T")


class EventStream(Generic[T]):
    """A tag-ordered stream of values from one producer port, sampled like an edge would be.

    Policies that consume (``Queue``, ``LatestDistinct``) keep their state per policy object, so
    repeated ``sample`` calls with one such object behave like successive ticks of one consumer
    and must move forward in time. Other policies are pure functions of the stream and ``now``.
    """

    def __init__(self, name: str = "stream"):
        self.name = name
        self._events: list[Event] = []
        # id(policy) -> (policy, buffer, last tag sampled); the policy is held so its id stays unique
        self._consumers: dict[int, tuple[SyncPolicy, PortBuffer, Tag]] = {}

    def append(self, t: float | int | Tag, value: T) -> Event:
        """Add a value at time ``t`` (seconds, or a ``(ns, microstep)`` tag); times must not decrease."""
        tag = t if isinstance(t, tuple) else (seconds_to_ns(t), 0)
        if self._events and tag < self._events[-1].tag:
            raise ValueError(f"EventStream {self.name!r}: tag {tag} is earlier than the last one "
                             f"{self._events[-1].tag}; append in time order")
        ev = Event(tag, self.name, "value", len(self._events), value)
        self._events.append(ev)
        for _policy, buf, _last in self._consumers.values():
            buf.insert((ev.tag, ev.node, ev.port, ev.seq, ev.value))
        return ev

    def _fresh_buffer(self) -> PortBuffer:
        buf = PortBuffer()
        buf.entries = [(ev.tag, ev.node, ev.port, ev.seq, ev.value) for ev in self._events]
        return buf

    def sample(self, policy: SyncPolicy, now: float | int | Tag) -> Any:
        """What a tick at ``now`` would receive through ``policy`` (MISSING if nothing)."""
        tau = now if isinstance(now, tuple) else (seconds_to_ns(now), 0)
        if not isinstance(policy, (Queue, LatestDistinct)):
            return policy.select(self._fresh_buffer(), tau)[0]
        entry = self._consumers.get(id(policy))
        if entry is None:
            buf = self._fresh_buffer()
        else:
            _policy, buf, last = entry
            if tau < last:
                raise ValueError(f"EventStream {self.name!r}: {policy!r} consumes events, so its samples must "
                                 f"move forward in time; {tau} is before the previous {last}")
        self._consumers[id(policy)] = (policy, buf, tau)
        value, _ids, _dropped, commit = policy.select(buf, tau)
        if value is not MISSING and commit is not None:
            policy.commit_to(buf, commit)
        return value

    def __len__(self) -> int:
        return len(self._events)
