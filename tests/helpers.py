"""What tests across the suite share: a bounded poll for what other processes and threads do in
real time (a worker coming up, a viewer catching up, a run's flows stopping)."""

from __future__ import annotations

import time
from typing import Callable, TypeVar

#: a bound on any wait: a loaded 2-core machine, other test runs beside us
BOUND_S = 60.0
#: how often a poll looks again
POLL_S = 0.02

T = TypeVar("T")


def poll(condition: Callable[[], T], what: str, bound: float = BOUND_S) -> T:
    """``condition()`` until it returns something truthy, returned; past ``bound`` s the test
    fails, saying ``what`` it waited for."""
    give_up = time.monotonic() + bound
    while not (value := condition()):
        assert time.monotonic() < give_up, f"no {what} within {bound:g} s"
        time.sleep(POLL_S)
    return value
