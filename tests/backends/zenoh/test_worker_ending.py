"""worker/ending.py: a single worker and a group's members end alike (issue 37). A failure, a
StopRun or a crash of the loop, is said once every held LET output is out: their seqs are in the
step records, and a consumer would wait forever at the gap; a loop that failed before it spoke
holds none. SIGTERM and PARENT_DIED stop every loop of the process. A hand-over too big to make
is said as a failure."""

from __future__ import annotations

import os
import queue
import signal
from types import SimpleNamespace

import pytest

from retriever.backends.zenoh import protocol
from retriever.backends.zenoh.node import CONTROL, Ending
from retriever.backends.zenoh.worker.ending import finish, handle_signals, say_failed
from retriever.backends.zenoh.protocol import EXIT_FAILED
from retriever.backends.zenoh.worker.process import PARENT_DIED
from retriever.errors import StopRun


class Outputs:
    def __init__(self, declared: bool):
        self.progress_publisher = object() if declared else None
        self.held = [((5, 0), "out", 1, 3)]

    def release_held(self) -> None:
        self.held = []


def serving(declared: bool = True) -> tuple[SimpleNamespace, list]:
    said: list = []
    loop = SimpleNamespace(outputs=Outputs(declared), counts={"ticks": 2}, undeclared=False,
                           reports=SimpleNamespace(finish=lambda: None))
    loop.undeclare = lambda: setattr(loop, "undeclared", True)
    return SimpleNamespace(loop=loop, node="cam", status=lambda kind, **fields: said.append((kind, fields))), said


def crash() -> BaseException:
    try:
        raise ZeroDivisionError("in the loop")
    except ZeroDivisionError as exc:
        return exc


def stop_run() -> BaseException:
    try:
        try:
            raise ValueError("in the step")
        except ValueError as cause:
            raise StopRun("step raised", (5, 0)) from cause
    except StopRun as exc:
        return exc


@pytest.mark.parametrize("exc", [crash(), stop_run()], ids=["crash", "stop_run"])
def test_a_failure_releases_the_held_outputs_then_says_failed_and_undeclares(exc):
    w, said = serving()
    say_failed(w, exc)
    assert w.loop.outputs.held == [], "a held output was left unpublished"
    [(kind, fields)] = said
    assert kind is protocol.Failed and fields["counts"] == {"ticks": 2} and w.loop.undeclared
    if isinstance(exc, StopRun):
        assert fields["error"] == "step raised" and fields["tag"] == (5, 0) and "in the step" in fields["traceback"]
    else:
        assert fields["error"] == "worker 'cam' crashed: ZeroDivisionError: in the loop"
        assert "ZeroDivisionError" in fields["traceback"]


def test_a_hand_over_too_big_to_make_says_failed_and_writes_nothing():
    """node/handover.py refuses a state with more events than a new process takes over in time:
    the old process says so as its failure (the run stops); its held outputs go with the run."""
    w, said = serving()

    def too_big():
        raise StopRun("flow 'cam' cannot restart after its step failed at t=0.000000005s m=0: ...", (5, 0))

    w.loop.handover_state, w.loop.ending = too_big, Ending.HANDING_OVER
    assert finish(w, None) == EXIT_FAILED
    [(kind, fields)] = said
    assert kind is protocol.Failed and fields["error"].startswith("flow 'cam' cannot restart")
    assert fields["tag"] == (5, 0)
    assert w.loop.undeclared and w.loop.outputs.held != []


def test_a_loop_that_failed_before_it_spoke_says_failed_without_publishing():
    w, said = serving(declared=False)
    say_failed(w, crash())
    assert w.loop.outputs.held != [] and [kind for kind, _ in said] == [protocol.Failed]


@pytest.mark.parametrize("signum, parent_gone, ending", [
    (signal.SIGTERM, False, Ending.TOLD_TO_STOP), (signal.SIGTERM, True, Ending.ABANDONED),
    (PARENT_DIED, False, Ending.ABANDONED)])
def test_a_signal_stops_every_loop_of_the_process(signum, parent_gone, ending):
    loops = [SimpleNamespace(endings=[], inbox=queue.Queue()) for _ in range(3)]
    for loop in loops:
        loop.stop = loop.endings.append
    before = signal.getsignal(signal.SIGTERM), signal.getsignal(PARENT_DIED)
    try:
        handle_signals(loops, SimpleNamespace(gone=lambda: parent_gone))
        os.kill(os.getpid(), signum)  # delivered to the main thread before kill returns
    finally:
        signal.signal(signal.SIGTERM, before[0])
        signal.signal(PARENT_DIED, before[1])
    for loop in loops:
        kind, _, record = loop.inbox.get_nowait()
        assert (loop.endings, kind, type(record)) == ([ending], CONTROL, protocol.Stop)
