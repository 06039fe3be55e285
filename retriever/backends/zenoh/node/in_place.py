"""Restarting a flow where it runs: ``on_error="restart"`` for a member of a group
(worker/group.py), whose process steps its neighbours too and must not end with its flow.

A step raised. Its error record is made as for any restart (``on_error: restart``); then, within
the flow's budget (``tick.decide`` with the budget held here: nothing else restarts a grouped
flow, since its process dying takes the whole group down), the old flow is torn down and a fresh
one, rebuilt from the IR and set up as a new process would, steps from the next tick on. The
rest of the loop is as it was: its input buffers, schedule, held LET outputs and seqs, as a
hand-over to a new process gives them but with no gap (no tick is skipped, none runs late on
its account). The neighbours go on untouched. A log replays as any restart's: the replay resets
the flow at the error record. Past the budget the run stops with the RestartLimitError a lone
flow's coordinator raises (StopRun ``out_of_restarts``: the ``failed`` status says it).
"""

from __future__ import annotations

import sys
from collections.abc import Callable

from ....flow.core import Flow, tear_down
from ....tick import RestartBudget


class InPlaceRestart:
    """The restarts of a flow in its own loop: its ``budget`` and ``fresh``, which makes its
    fresh flow (rebuilt, set up; a StopRun when its setup() raised)."""

    def __init__(self, budget: RestartBudget, fresh: Callable[[], Flow]):
        self.budget, self.fresh = budget, fresh

    def renew(self, old: Flow, node_id: str) -> Flow:
        """``old`` torn down (a failure is told, not fatal, as at a run's end), then its fresh flow."""
        try:
            tear_down(old)
        except Exception as exc:
            print(f"{node_id}.teardown() raised {type(exc).__name__}: {exc}", file=sys.stderr, flush=True)
        return self.fresh()
