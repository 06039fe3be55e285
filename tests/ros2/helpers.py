"""What the tests of retriever.ros2 share besides their router (conftest.py): waiting, with a bound,
for what Zenoh links and delivers on its own threads, in real time."""

from __future__ import annotations

import time
from typing import Callable

#: how long a test waits for Zenoh to link the sessions and deliver, at most
BOUND_S = 20.0


def until(condition: Callable[[], object], what: str, act: Callable[[], object] | None = None,
          timeout: float = BOUND_S) -> None:
    """``act()`` (else a pause of a ms) until ``condition()`` holds; past ``timeout`` s the test
    fails, saying ``what`` it waited for."""
    give_up = time.monotonic() + timeout
    while not condition():
        assert time.monotonic() < give_up, f"{what}: not within {timeout:g} s"
        if act is None:
            time.sleep(0.001)
        else:
            act()
