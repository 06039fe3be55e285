"""What the coordinator has seen of a run, in memory that does not grow with the run's length.

A run of hours sends millions of events and step records; the coordinator checks each against
what came before (an event twice, a second record of one tick) and frees the record once logged.
These two sets answer those questions as a set would, in bounded memory:

- :class:`EventIds`: every event id ``(node, port, seq)`` seen, as runs of consecutive seqs per
  stream: a stream's events come in seq order, so it holds one run per stream, plus one per gap
  (a restarted producer's skipped seqs, an event still on its way).
- :class:`RecentTicks`: the ``(node, tag)`` of each node's last ``window`` step records; a record
  older than all of them counts as seen (a worker reports its ticks in order: only a forged or
  replayed record comes from that far back).
"""

from __future__ import annotations

from bisect import bisect_right
from collections import deque

EventId = tuple[str, str, int]


class EventIds:
    """A set of event ids, held per stream as sorted, disjoint runs ``[first, last]`` of seqs."""

    def __init__(self) -> None:
        self._runs: dict[tuple[str, str], list[list[int]]] = {}

    def __contains__(self, event_id: EventId) -> bool:
        runs = self._runs.get(event_id[:2])
        if not runs:
            return False
        seq = event_id[2]
        last = runs[-1]
        if last[0] <= seq <= last[1]:  # the common case: the newest run
            return True
        i = bisect_right(runs, [seq, float("inf")]) - 1
        return i >= 0 and runs[i][0] <= seq <= runs[i][1]

    def add(self, event_id: EventId) -> None:
        seq = event_id[2]
        runs = self._runs.setdefault(event_id[:2], [])
        if runs and runs[-1][1] + 1 == seq:  # the common case: the next seq of the stream
            runs[-1][1] = seq
            return
        i = bisect_right(runs, [seq, float("inf")])  # runs[:i] start at or before seq
        before = runs[i - 1] if i > 0 else None
        after = runs[i] if i < len(runs) else None
        if before is not None and before[0] <= seq <= before[1]:
            return
        if before is not None and before[1] + 1 == seq:
            before[1] = seq
            if after is not None and after[0] == seq + 1:  # the gap closed: one run
                before[1] = after[1]
                del runs[i]
        elif after is not None and after[0] == seq + 1:
            after[0] = seq
        else:
            runs.insert(i, [seq, seq])

    def runs(self) -> int:
        """How many runs it holds (its memory): one per stream and per gap."""
        return sum(len(r) for r in self._runs.values())

    def copy(self) -> "EventIds":
        other = EventIds()
        other._runs = {stream: [list(r) for r in runs] for stream, runs in self._runs.items()}
        return other


class RecentTicks:
    """The ``(node, tag)`` of each node's last ``window`` step records, and, per node, the tag
    below which everything counts as seen (the newest tag that left the window)."""

    def __init__(self, window: int = 8192) -> None:
        self.window = window
        self._recent: dict[str, set] = {}
        self._order: dict[str, deque] = {}
        self._floor: dict[str, tuple[int, int]] = {}

    def __contains__(self, tick: tuple[str, tuple[int, int]]) -> bool:
        node, tag = tick
        floor = self._floor.get(node)
        return (floor is not None and tag <= floor) or tag in self._recent.get(node, ())

    def add(self, tick: tuple[str, tuple[int, int]]) -> None:
        node, tag = tick
        recent = self._recent.setdefault(node, set())
        if tag in recent:
            return
        recent.add(tag)
        order = self._order.setdefault(node, deque())
        order.append(tag)
        if len(order) > self.window:
            old = order.popleft()
            recent.discard(old)
            floor = self._floor.get(node)
            self._floor[node] = old if floor is None or old > floor else floor

    def remembered(self) -> int:
        """How many ticks it holds one by one (its memory): at most ``window`` per node."""
        return sum(len(tags) for tags in self._recent.values())

    def copy(self) -> "RecentTicks":
        other = RecentTicks(self.window)
        other._recent = {n: set(s) for n, s in self._recent.items()}
        other._order = {n: deque(d) for n, d in self._order.items()}
        other._floor = dict(self._floor)
        return other
