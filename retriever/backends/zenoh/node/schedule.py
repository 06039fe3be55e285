"""When a node ticks: its Rate clock's ticks and the trigger ticks its inputs bring."""

from __future__ import annotations

import heapq
import threading

from ....clocks import Clock

#: what a pass of the node loop returns instead of a wall time to wake at: look again at once,
#: or the loop is done (no tick below the end can come any more)
TICKED, DONE = "ticked", "done"


class Schedule:
    """The next Rate tick (the ``k``-th of the clock), the pending trigger tags (a heap,
    deduplicated by ``pending_set``), the tick in progress and the last tick run. ``lock``
    guards what the progress queryable reads."""

    def __init__(self, clock: Clock, lock: threading.Lock):
        self.clock, self.lock = clock, lock
        self.k = 0
        self.next_rate: tuple[int, int] | None = None
        self.pending: list[tuple[int, int]] = []
        self.pending_set: set[tuple[int, int]] = set()
        self.running: tuple[int, int] | None = None  # the tag of the tick in progress
        self.last_tick: tuple[int, int] = (-1, 0)

    def start(self) -> None:
        """The run begins at the Rate clock's ``k``-th tick (0, or where a fresh process joins)."""
        if self.clock.hz is not None:
            with self.lock:
                self.next_rate = (self.clock.tick_time(self.k), 0)

    def take(self, tau: tuple[int, int]) -> None:
        """The tick ``tau`` runs now: it is in progress, and no longer next."""
        with self.lock:
            self.running = tau
            if tau == self.next_rate:
                self.k += 1
                self.next_rate = (self.clock.tick_time(self.k), 0)
            if self.pending and self.pending[0] == tau:
                heapq.heappop(self.pending)
                self.pending_set.discard(tau)

    def skip_missed(self, now: int, end: int) -> int:
        """Skip the Rate ticks that came due before ``now`` but the newest, which runs next;
        how many were skipped."""
        if self.clock.hz is None:
            return 0
        clock = self.clock
        missed = 0
        with self.lock:
            while clock.tick_time(self.k + 1) <= now and clock.tick_time(self.k) < end:
                self.k += 1
                missed += 1
            self.next_rate = (clock.tick_time(self.k), 0)
        return missed

    def stop(self, end: int) -> int:
        """No tick runs any more: forget them; how many trigger ticks before ``end`` never ran."""
        with self.lock:
            self.next_rate = None
            unrun = sum(1 for tag in self.pending if tag[0] < end)
            self.pending, self.pending_set = [], set()
        return unrun

    def restore(self, k: int, next_rate, pending: list, last_tick) -> None:
        """Go on from another process's schedule (handover.py)."""
        self.k = k
        self.next_rate = tuple(next_rate) if next_rate is not None else None
        self.pending = [tuple(t) for t in pending]
        heapq.heapify(self.pending)
        self.pending_set = set(self.pending)
        self.last_tick = tuple(last_tick)
