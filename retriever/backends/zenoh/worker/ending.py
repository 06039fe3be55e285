"""How a worker's node ends, the same for a worker of one node and a group's members: a signal
stops its loops (handle_signals); a failure is said with its cause, once every held output is
out (say_failed); a restart hands the state over (hand_over); else ``done`` (say_done); the flow
is released as soon as nothing more steps (release).
"""

from __future__ import annotations

import signal
import sys
import traceback
from collections.abc import Iterable

from ....codec import packb
from ....errors import StopRun
from ....flow.core import tear_down
from .. import protocol
from ..node import CONTROL, Ending, NodeLoop
from .build import Serving
from ..protocol import EXIT_FAILED, EXIT_HANDED_OVER
from .process import PARENT_DIED, Parent
from .starts import LoopStart
from .waits import await_reports_taken


def handle_signals(loops: Iterable[NodeLoop], parent: Parent) -> None:
    """SIGTERM asks every loop of this process to stop; when the parent is dead (a SIGTERM sent
    by someone else then), or on PARENT_DIED, the process ends without a word, as if killed,
    promising its consumers nothing (not "done"): the run goes on without it."""
    loops = list(loops)
    stop_item = (CONTROL, None, protocol.Stop())  # this process's own: no seal to open

    def stop(ending: Ending) -> None:
        for loop in loops:
            loop.stop(ending)
            loop.inbox.put(stop_item)

    signal.signal(signal.SIGTERM,
                  lambda signum, frame: stop(Ending.ABANDONED if parent.gone() else Ending.TOLD_TO_STOP))
    signal.signal(PARENT_DIED, lambda signum, frame: stop(Ending.ABANDONED))


def say_failed(w: Serving, exc: BaseException) -> None:
    """``failed``, with why: a StopRun's error, tag and the step's own traceback (on_error="stop",
    a deadline missed with "error", a causality error), or a crash of the loop itself. First the
    LET outputs the loop still holds go out: their seqs are in its step records already, and a
    consumer would wait forever at the gap they leave (node/outputs.py, release_held)."""
    loop = w.loop
    try:
        if loop.outputs.progress_publisher is not None:  # (a loop that failed before it spoke holds none)
            loop.outputs.release_held()
    except Exception as held_exc:  # a crash of the outputs themselves: the status must still go
        print(f"worker '{w.node}' could not publish its held outputs: {type(held_exc).__name__}: {held_exc}",
              file=sys.stderr, flush=True)
    tell_failed(w, exc)
    loop.undeclare()


def tell_failed(w: Serving, exc: BaseException) -> None:
    """The last reports, then ``failed`` with why (say_failed)."""
    loop = w.loop
    loop.reports.finish()
    if isinstance(exc, StopRun):
        cause = exc.__cause__  # the exception a step raised: where in the flow's code
        w.status(protocol.Failed, error=str(exc), tag=tuple(exc.tag) if exc.tag else None, counts=dict(loop.counts),
                 traceback="".join(traceback.format_exception(cause)) if cause is not None else None,
                 zeno=exc.zeno, raised=exc.raised, **({"out_of_restarts": True} if exc.out_of_restarts else {}))
    else:
        w.status(protocol.Failed, error=f"worker '{w.node}' crashed: {type(exc).__name__}: {exc}",
                 traceback="".join(traceback.format_exception(exc)), counts=dict(loop.counts))


def finish(w: Serving, begin: LoopStart) -> int:
    """After the loop's run: hand the state over to the flow's new process (a restart), or say
    ``done``; release the flow; keep the session until the coordinator has every report."""
    if w.loop.ending is Ending.HANDING_OVER:
        if not hand_over(w):
            return EXIT_FAILED
        await_reports_taken(w.session, w.keys, w.loop.opener, w.node, w.spec.hub_zid, handed_over=True,
                            routers=list(w.spec.router))
        return EXIT_HANDED_OVER
    say_done(w, begin)
    await_reports_taken(w.session, w.keys, w.loop.opener, w.node, w.spec.hub_zid, routers=list(w.spec.router))
    return 0


def hand_over(w: Serving) -> bool:
    """The restarting flow's state, written for its new process (``<run dir>/<node>.handover``);
    then ``handed_over``, and the flow released. False: more to hand over than a new process
    takes over in time (node/handover.py, HANDOVER_EVENTS_MAX): ``failed``, saying so, instead
    (the outputs it holds go with the run, which stops)."""
    loop = w.loop
    loop.undeclare()  # first: no message may arrive after the state is taken
    try:
        state = packb(loop.handover_state())
    except StopRun as exc:
        tell_failed(w, exc)
        return False
    loop.reports.finish()
    handover_file = w.launch.run_dir / f"{w.node}.handover"
    tmp = handover_file.with_suffix(".tmp")
    tmp.write_bytes(state)
    tmp.replace(handover_file)
    w.status(protocol.HandedOver, counts=dict(loop.counts), reports=loop.reporter.sent)
    release(loop, w.node)  # the new process has set up its own: free this one's now
    return True


def say_done(w: Serving, begin: LoopStart) -> None:
    """``done``, with what the coordinator checks the run's end against; the flow released."""
    loop = w.loop
    w.status(protocol.Done, counts=dict(loop.counts), reports=loop.reporter.sent, started_ns=begin.started_ns,
             ticks=loop.reports.recorded, stopped=loop.ending is Ending.TOLD_TO_STOP, sent=dict(loop.sent))
    loop.undeclare()
    release(loop, w.node)


def release(loop: NodeLoop, node_id: str) -> None:
    """The flow's ``teardown()``, once (see Flow.setup): as soon as its process has nothing more
    to step, not after it waited for its reports to be taken. A failure is told, not fatal."""
    try:
        tear_down(loop.flow)
    except Exception as exc:
        print(f"{node_id}.teardown() raised {type(exc).__name__}: {exc}", file=sys.stderr, flush=True)
