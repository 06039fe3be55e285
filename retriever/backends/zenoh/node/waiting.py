"""Whether a due tick may run: its input edges complete up to it (their producers' frontiers
past it), or past their deadline; whom to ask for a frontier meanwhile; and, in virtual time,
the lockstep with the coordinator's grants.

Virtual time (``retriever deploy --virtual-time``): a tick runs once its inputs are complete,
however long that takes (no deadline). The coordinator advances all nodes in lockstep: a node
runs the ticks below its *grant* (control ``grant`` {until}), then says ``reached`` {until} (a
status) and waits; once every node not done has reached it, the coordinator grants the next
window (coordinator/waiting.py).
"""

from __future__ import annotations

import queue
from collections.abc import Callable
from typing import Protocol

import zenoh

from ..protocol import ControlOpener, Finished, new_nonce
from ..wire import KeySpace, WireError
from .clock import RunClock
from .frontiers import InEdge, Streams
from .inbox import CONTROL, PROGRESS
from .outputs import Outputs
from .reports import Reports
from .schedule import DONE

#: how long a blocked tick waits for a data or progress message before asking the producer
PROBE_AFTER_NS = 500_000
#: after asking a producer for its frontier, how long before asking again
ASK_EVERY_NS = 2_000_000
#: how long a producer has to answer a question for its frontier
ASK_TIMEOUT_S = 1.0
#: Past the run's end plus a trigger edge's deadline, with its producer's frontier short of the
#: end, a node asks the coordinator whether that producer is done (``status/finished``), and
#: waits this long for the answer at most; without one it gives the edge up.
FINISHED_ASK_NS = 1_000_000_000
#: A done producer published its last frontier before it said ``done``: until that reaches the
#: node, events it made before the end are still on their way. On a loaded machine the transport
#: (dora's daemon) or this process can stall past the deadline; the node waits for them (its
#: triggered ticks before the end then run, late), this long past the end plus the deadline at
#: most, well within the coordinator's patience (coordinator/waiting.py, FINISH_SLACK_S); a
#: stream whose last word never came is counted (``unfinished_inputs``).
LAST_WORD_MAX_NS = 5_000_000_000
#: meanwhile, how often it looks again (what it waits for wakes it sooner)
LAST_WORD_POLL_NS = 100_000_000
#: virtual time: how long a loop at its grant, or with no tick known below it, waits before
#: looking again (any message wakes it sooner: the next grant, a frontier)
VIRTUAL_IDLE_NS = 100_000_000


class WaitingOwner(Protocol):
    """What :class:`Waiting` reads and sets of the loop it serves (a NodeLoop), as it changes."""

    #: virtual time: ticks below this (ns since T0) may run; raised here, on a grant
    granted: int
    #: whether the flow is being restarted (its new process says what it reached)
    restarting: bool
    #: virtual time: on_reached(until) says the node reached a grant
    on_reached: Callable[[int], None] | None
    #: where the producers' answers go (read when asking: a group gives its loops inboxes of their own)
    inbox: queue.SimpleQueue
    #: opens the coordinator's answers, with this process's key (set by the worker)
    opener: ControlOpener


class Waiting:
    """The waits of a node: ``ask_after``, per producer, when it may be asked again (over
    ``session``, on ``keys``); ``blocked``, in virtual time, the tick waiting for its inputs and
    since when (wall); ``reached``, the last grant this node said it reached. ``owner`` is the
    loop's state it reads and changes (:class:`WaitingOwner`)."""

    def __init__(self, owner: WaitingOwner, *, virtual: bool, session: zenoh.Session, keys: KeySpace,
                 streams: Streams, clock: RunClock, outputs: Outputs, reports: Reports):
        self.owner, self.virtual, self.session, self.keys = owner, virtual, session, keys
        self.streams, self.clock, self.outputs, self.reports = streams, clock, outputs, reports
        self.ask_after: dict[str, int] = {}
        self.blocked: tuple[tuple[int, int], int] | None = None
        self.reached = -1
        # past the end: when the coordinator was asked which nodes are done, and its answer
        self.finished_asked: int | None = None
        self.finished: frozenset[str] | None = None
        self.unfinished: set[tuple[str, str]] = set()  # streams given up without their last word

    def incomplete(self, tau: tuple[int, int], now: int) -> tuple[list[str], int | None]:
        """Ports whose edge is not complete up to ``tau`` and past deadline; or the wall time to
        look again if some edge may still complete in time."""
        late_ports, wake = [], None
        frontiers, virtual = self.streams.frontiers, self.virtual
        for e in self.streams.edges:
            # (Streams.edge_frontier, inline: this runs on every tick, for every edge)
            f = frontiers[(e.src, e.src_port)]
            if ((f[0] + e.delay_ns, 0) if e.delay_ns else f) > tau:
                continue
            if virtual:  # no deadline: wait for it, asking its producer now and then
                since = self.blocked_since(tau, now)
                again = self.ask(e.src, now, since)
                wake = again if wake is None else min(wake, again)
                continue
            if now >= tau[0] + e.deadline_ns:
                late_ports.append(e.port)
                continue
            wake = min(tau[0] + e.deadline_ns, wake if wake is not None else tau[0] + e.deadline_ns,
                       self.ask(e.src, now, tau[0]))
        return (sorted(set(late_ports)) if late_ports else late_ports), wake

    def ask(self, src: str, now: int, since: int) -> int:
        """Ask a producer for its frontier once a wait has lasted ``PROBE_AFTER_NS`` past
        ``since``, then at most every ``ASK_EVERY_NS``; returns when to look again. (Over the
        run's Zenoh session whatever the transport: it is the producer's queryable that answers.)"""
        if now < since + PROBE_AFTER_NS:
            return since + PROBE_AFTER_NS
        after = self.ask_after.get(src, 0)
        if now < after:
            return after
        self.ask_after[src] = now + ASK_EVERY_NS
        put = self.owner.inbox.put

        def on_reply(reply: zenoh.Reply, src: str = src) -> None:
            if reply.ok is not None:
                put((PROGRESS, src, reply.ok.payload.to_bytes()))
            else:
                put((PROGRESS, src, None))

        self.session.get(self.keys.progress(src), handler=on_reply, timeout=ASK_TIMEOUT_S)
        return now + ASK_EVERY_NS

    def done_waiting(self, now: int) -> int | str:
        """No tick below ``end`` is known: ``DONE`` once no edge can still trigger one, else when
        to look again. An edge whose producer's frontier is short of the end is waited for until
        the end plus its deadline, and past that only while its producer's last messages are on
        their way (:meth:`last_word`)."""
        if self.outputs.held:
            return self.outputs.held[0][0][0]
        wake: int | None = None
        end = self.clock.end
        end_tag = (end, 0)
        frontiers = self.streams.frontiers
        for e in self.streams.triggering:
            f = frontiers[(e.src, e.src_port)]  # (Streams.edge_frontier, inline: this runs after every tick)
            if ((f[0] + e.delay_ns, 0) if e.delay_ns else f) >= end_tag:
                continue
            if self.virtual or now < end + e.deadline_ns:
                again = min(end + e.deadline_ns, self.ask(e.src, now, end))
            else:
                again = self.last_word(e, now)
                if again is None:
                    continue
            wake = again if wake is None else min(wake, again)
        return DONE if wake is None else wake

    def last_word(self, e: InEdge, now: int) -> int | None:
        """Past the end plus ``e``'s deadline, its producer's frontier short of the end: when to
        look again while that producer is done (the coordinator says so) and its last messages
        have not come (see LAST_WORD_MAX_NS), or None to give the edge up: the producer is not
        done (a step outlasting the end is waited for no longer than its deadline), or the
        coordinator did not answer."""
        if self.finished is None:
            if self.finished_asked is None:
                self.ask_finished(now)
            return now + LAST_WORD_POLL_NS if now < self.finished_asked + FINISHED_ASK_NS else None
        if e.src not in self.finished:
            return None
        if now < self.clock.end + e.deadline_ns + LAST_WORD_MAX_NS:
            return now + LAST_WORD_POLL_NS
        stream = (e.src, e.src_port)
        if stream not in self.unfinished:
            self.unfinished.add(stream)
            self.streams.notes.counts["unfinished_inputs"] += 1
        return None

    def ask_finished(self, now: int) -> None:
        """Ask the coordinator which nodes are done; its answer joins the inbox as control
        (one it did not seal for this process, as the WireError saying so: garbage)."""
        self.finished_asked = now
        put, opener, nonce = self.owner.inbox.put, self.owner.opener, new_nonce()

        def on_reply(reply: zenoh.Reply) -> None:
            if reply.ok is None:
                return  # unanswered: given up at FINISHED_ASK_NS
            try:
                put((CONTROL, None, opener.reply(Finished, str(reply.ok.key_expr), reply.ok.payload.to_bytes(),
                                                 reply.ok.attachment, nonce)))
            except WireError as e:
                put((CONTROL, None, e))

        self.session.get(self.keys.finished(), attachment=nonce, handler=on_reply,
                         timeout=FINISHED_ASK_NS / 1e9)

    def said_finished(self, record: Finished) -> None:
        """The coordinator's answer to :meth:`ask_finished`: the nodes done."""
        self.finished = frozenset(record.nodes)

    # -- virtual time -------------------------------------------------------------------------
    def blocked_since(self, tau: tuple[int, int], now: int) -> int:
        """Since when (wall, ns since T0) the tick ``tau`` waits for its inputs."""
        if self.blocked is None or self.blocked[0] != tau:
            self.blocked = (tau, now)
        return self.blocked[1]

    def ask_triggers(self, now: int) -> int:
        """No tick below the grant is known, but a trigger edge may still bring one: ask its
        producer for its frontier now and then; when to look again."""
        granted = self.owner.granted
        wake = now + VIRTUAL_IDLE_NS
        since = self.blocked_since((granted, -1), now)
        for e in self.streams.triggering:
            if self.streams.edge_frontier(e) < (granted, 0):
                wake = min(wake, self.ask(e.src, now, since))
        return wake

    def at_grant(self, now: int) -> int:
        """Every tick below the grant has run; say so once (with this node's frontier to its
        consumers first), then wait for the next grant."""
        owner = self.owner
        if self.reached < owner.granted and not owner.restarting:  # (the new process will say it)
            self.reached = owner.granted
            if self.outputs.consumed:
                self.outputs.publish_progress()
            self.reports.flush()
            if owner.on_reached is not None:
                owner.on_reached(owner.granted)
        return now + VIRTUAL_IDLE_NS

    def granted(self, until) -> None:
        """Control ``grant`` {until}: ticks below ``until`` may run (and our word, if it was
        missed, is said again)."""
        owner = self.owner
        owner.granted = max(owner.granted, min(until, self.clock.end))
        if until <= self.reached and owner.on_reached is not None:
            owner.on_reached(self.reached)


