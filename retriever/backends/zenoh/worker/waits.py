"""A worker's waits on its coordinator: for a control message (the start, a resume, a
restarted), with the questions that fetch one missed (ask_start); for what the coordinator
says is finished; and, after its last status, until the coordinator took every report.
"""

from __future__ import annotations

import queue
import sys
import time
from collections.abc import Collection

from .. import protocol
from ..node import CONTROL, NodeLoop
from ..wire import WireError
from .links import coordinator_linked

#: A worker that said ``ready`` and has not seen ``start`` after this long says ``ready`` again
#: and asks the coordinator's ``ctl/start`` queryable for the start, and again every as long (a
#: restarted one waiting for ``resume`` or ``restarted`` says ready again). Either put can be
#: missed: one put as a link comes up may precede the subscriptions the other side declares on
#: it, and Zenoh drops what has no known subscriber. A worker that missed it would wait until
#: the run gave up on it (benchmarks/reports/scale.md: many flows starting at once on few cores).
START_ASK_S = 0.5

#: After its last status (done, handed over), a worker keeps its session open until the coordinator
#: has every report it sent. A report over 3 KiB goes through Zenoh's shared memory, and one whose
#: sender had closed its session by the time the receiver read it was dropped (the sender's buffers
#: no longer valid): the coordinator waited for it forever; so does one still in the sender's queue
#: (a report of big frames, across machines). A coordinator writing big frames to its log answers
#: late and takes reports long after they came (it waits for its disk): the worker waits as long as the
#: coordinator answers, and gives up only once it has not answered for REPORTS_TAKEN_S, its
#: link to it is gone, or after REPORTS_TAKEN_MAX_S in all (the coordinator ends a run that waits
#: for a report longer than its own patience anyway, and stops this process).
REPORTS_TAKEN_S = 5.0

REPORTS_TAKEN_MAX_S = 120.0


def ask_start(session, keys, loop: NodeLoop) -> None:
    """Ask the coordinator for the run's start; its answer joins the loop's inbox as control (one
    the coordinator did not seal for this process, as the WireError saying so: garbage)."""
    nonce = protocol.new_nonce()
    for reply in session.get(keys.start(), attachment=nonce, timeout=START_ASK_S):
        if reply.ok is not None:
            try:
                start = loop.opener.reply(protocol.Start, str(reply.ok.key_expr), reply.ok.payload.to_bytes(),
                                          reply.ok.attachment, nonce)
            except WireError as e:
                loop.inbox.put((CONTROL, None, e))
                continue
            loop.inbox.put((CONTROL, None, start))


def await_control(loop: NodeLoop, wanted: type[protocol.Record], node_id: str, ask=None) -> protocol.Record | None:
    """Wait for the run's control to say ``wanted`` (a record of protocol.RUN_CONTROL: to this
    node, if it names one): that record; None on ``stop``. ``ask()``, if given, is called after
    every START_ASK_S without it. What else arrives meanwhile is put back in the loop's inbox."""
    early = []
    try:
        while True:
            try:
                item = loop.inbox.get(timeout=START_ASK_S if ask is not None else None)
            except queue.Empty:
                ask()
                continue
            if item[0] != CONTROL:
                early.append(item)
                continue
            record = item[2]
            kind = type(record)
            if isinstance(record, WireError):
                loop.counts["garbage"] += 1
            elif kind is protocol.Stop:
                return None
            elif kind is wanted and getattr(record, "node", node_id) == node_id:
                return record
            elif kind in (protocol.Lost, protocol.Restarted):  # of a producer: the loop must know, once it runs
                early.append(item)
            elif kind is protocol.Redeclare and node_id in record.nodes:
                loop.redeclare()  # a consumer never got this node's answer (REDECLARE_AFTER_S)
    finally:
        for item in early:
            loop.inbox.put(item)


def drop_queued(loop: NodeLoop, kind: type[protocol.Record], node_id: str) -> None:
    """Forget the control messages of ``kind`` to ``node_id`` queued in the loop's inbox; keep the rest."""
    kept = []
    while True:
        try:
            item = loop.inbox.get_nowait()
        except queue.Empty:
            break
        if item[0] == CONTROL and type(item[2]) is kind and item[2].node == node_id:
            loop.counts["garbage"] += 1
            continue
        kept.append(item)
    for item in kept:
        loop.inbox.put(item)


def coordinator_says(session, keys, opener) -> tuple[set[str], set[str]]:
    """The nodes the coordinator knows are done (they will not answer, nor send, again), and
    those starting afresh after their process died (``opener``: this process's, for the answer)."""
    said = _finished(session, keys, opener)
    return (set(said.nodes), set(said.restarting)) if said is not None else (set(), set())


def _finished(session, keys, opener) -> protocol.Finished | None:
    """The coordinator's ``finished`` answer (protocol.Finished), or None when it did not answer.
    An answer the coordinator did not seal for this process (``opener``: its ControlOpener) is none."""
    nonce = protocol.new_nonce()
    said = None
    for reply in session.get(keys.finished(), attachment=nonce, timeout=0.25):
        if reply.ok is None or said is not None:
            continue  # (the replies are read to the end: the query then ends)
        try:
            said = opener.reply(protocol.Finished, str(reply.ok.key_expr), reply.ok.payload.to_bytes(),
                                reply.ok.attachment, nonce)
        except WireError:
            continue
    return said


def await_reports_taken(session, keys, opener, nodes: str | Collection[str], hub_zid: str | None,
                        handed_over: bool = False, routers: list[str] | None = None) -> None:
    """After its last status, until the coordinator (whose session is ``hub_zid``, reached
    through ``routers`` for a client of them) has every report of ``nodes`` (a node, or a
    group's nodes; its ``finished`` answer, opened by ``opener``, says so: in ``complete``, or,
    for a process that ``handed_over`` to a restarted flow's, in ``handed_over``); see
    REPORTS_TAKEN_S for how long."""
    wanted = {nodes} if isinstance(nodes, str) else set(nodes)
    names = sorted(wanted)
    node_id = ",".join(names) if len(names) <= 3 else f"{names[0]},… ({len(names)} nodes)"
    start = answered = time.monotonic()
    while (now := time.monotonic()) - answered < REPORTS_TAKEN_S and now - start < REPORTS_TAKEN_MAX_S:
        said = _finished(session, keys, opener)
        if said is not None and wanted <= set(said.handed_over if handed_over else said.complete):
            return
        if said is not None:
            answered = time.monotonic()
        elif not (linked := coordinator_linked(session, hub_zid, routers)):
            if linked is not None:  # the coordinator waits for reports that cannot come: say why
                print(f"retriever: worker '{node_id}' has no link to the coordinator at its end: the coordinator may "
                      "lack its last reports and status", file=sys.stderr, flush=True)
            return  # the coordinator is gone (or, without its id, may be): nothing more reaches it
        time.sleep(0.02)
