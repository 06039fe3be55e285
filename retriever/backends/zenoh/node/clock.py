"""The run's time as one node sees it: its start ``T0``, its end, and the clocks read from T0."""

from __future__ import annotations

import time


class RunClock:
    """``t0`` (HLC Unix ns) and ``end`` (ns since T0) are known once the run starts (``started``);
    ``promised_end`` is the end producers' frontiers are checked against (an ``end`` control
    message may bring ``end`` sooner, never a producer's promises)."""

    def __init__(self, session):
        self.session = session
        self.t0 = 0
        self.end = 0
        self.promised_end = 0
        # run() began: before, the end is not known, and a frontier past (0, 0) no promise it can
        # keep (with end 0 it said NEVER: "finished", and a consumer ran on without it)
        self.started = False

    def start(self, t0: int, end: int) -> None:
        self.t0, self.end, self.promised_end, self.started = t0, end, end, True

    def now(self) -> int:
        """Wall time since T0, ns."""
        return time.time_ns() - self.t0

    def hlc(self) -> int:
        """HLC time since T0, ns: what ASAP outputs are stamped with."""
        return self.session.new_timestamp().get_time_as_ntp64().as_nanos() - self.t0
