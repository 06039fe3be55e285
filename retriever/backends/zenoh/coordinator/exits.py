"""Virtual time: where a step's sys.exit(0) ends the run, and the records held until that is known.

In-process (the reference), a step that calls sys.exit(0) ends the run at its tick: every tick
at an earlier tag ran, and of the ticks at its own tag, those of the nodes before it in the tie
order (plan.tie_order); nothing after. In lockstep (waiting.py) each node runs a window of
virtual time on its own, so when one node's step exits, others may already have run ticks past
it. Their records must not reach the trace or the log: the coordinator holds each step record
and event until no exit can cut it off, then hands it on, or drops it::

    report ──▶ below the final bound? ──▶ take (trace, log, counters)
                  │ no
                  ▼ held ── barrier: final bound = min(every node reached, earliest exit) ──▶ take
                            the run's end: cut at the earliest exit ──▶ take, or drop (its events too)

Below a barrier every node passed (each one not done reached the grant), every exit is known: a
node says ``exit`` before it says ``reached`` or ``done``, on the one key of its statuses.
"""

from __future__ import annotations

from collections.abc import Callable

#: a step's sys.exit(0): its tag and its node
Exit = tuple[tuple[int, int], str]


class ExitCut:
    """The records of a run in virtual time, held until final. ``rank``: per node, its place in
    a tag's ticks (plan.tie_order)."""

    def __init__(self, rank: dict[str, int]):
        self.rank = rank
        # where a final step record and event go (hand_to)
        self.take_step: Callable[[tuple], None] | None = None
        self.take_event: Callable[[tuple], None] | None = None
        self.final_ns = 0  # records and events at tags below this time (ns since T0) are final
        self.settled = False  # the run is over: whatever comes now is taken as it comes
        self.steps: list[tuple] = []  # held: (node, tag, consumed, produced, status, detail, start, wall)
        self.events: list[tuple] = []  # held: (tag, node, port, seq, value, wall)

    def hand_to(self, take_step: Callable[[tuple], None], take_event: Callable[[tuple], None]) -> None:
        """Where a final step record and event go (reports.ReportIngest)."""
        self.take_step, self.take_event = take_step, take_event

    def earliest(self, exits: dict[str, tuple]) -> Exit | None:
        """The exit that ends the run among ``exits`` (per node, its exit's tag first): the
        earliest tag, then the node first in the tie order."""
        if not exits:
            return None
        node = min(exits, key=lambda n: (exits[n][0], self.rank[n]))
        return tuple(exits[node][0]), node

    def step(self, record: tuple) -> None:
        """A step record checked (reports.ReportIngest): taken if final, else held."""
        if self.settled or record[1][0] < self.final_ns:
            self.take_step(record)
        else:
            self.steps.append(record)

    def event(self, event: tuple) -> None:
        """An event checked (reports.ReportIngest): taken if final, else held."""
        if self.settled or event[0][0] < self.final_ns:
            self.take_event(event)
        else:
            self.events.append(event)

    def final_below(self, ns: int) -> None:
        """Every node passed ``ns`` (ns since T0), and no step exited before it: what is held
        below it is final. (An event comes after the step that made it: that step is final too.)"""
        if ns <= self.final_ns:
            return
        self.final_ns = ns
        steps, self.steps = self.steps, []
        for record in steps:
            self.step(record)
        events, self.events = self.events, []
        for event in events:
            self.event(event)

    def settle(self, cut: Exit | None) -> None:
        """The run is over (every node done, or the run failed): take what is held but the steps
        after ``cut`` (the exit that ended the run, if one did) and the events they made."""
        self.settled = True
        dropped = set()
        for record in self.steps:
            if cut is None or self.before(record[0], record[1], cut):
                self.take_step(record)
            else:
                dropped.update(record[3])
        for event in self.events:
            if event[1:4] not in dropped:
                self.take_event(event)
        self.steps, self.events = [], []

    def before(self, node: str, tag: tuple[int, int], cut: Exit) -> bool:
        """Whether the tick of ``node`` at ``tag`` ran in-process before the run ended at
        ``cut``: at an earlier tag, or at its tag before it in the tie order, or it is the exit."""
        at, exiting = cut
        return tag < at or (tag == at and self.rank[node] <= self.rank[exiting])
