"""The three ways a worker's loop comes to its start: the node's first process (start), a
restarted flow's new process taking the old one's state (join, --join), and a fresh flow
after its process died (start_afresh, --fresh). Each links, asks its neighbours, makes its
shared-memory pool, says ``ready`` and waits for the coordinator's word: a LoopStart, or None
when stopped first.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass

from .. import protocol
from ..hub import mapped_segments, wait_for_answers, wait_for_links
from ..node import handover
from ..protocol import RESTART_SEQ_GAP
from ..wire import WireError, decode_progress
from .build import Serving
from .links import LINK_TIMEOUT_S, NEIGHBOR_TIMEOUT_S, consumers, link_to_hub, links_needed, names_of, producers
from .waits import ask_start, await_control, coordinator_says, drop_queued

#: Before it says ``ready``, a worker asks each consumer's progress with this much padding, so
#: that Zenoh sends the question through the session's shared-memory pool (messages over 3 KiB
#: between peers on one host go that way; the hub has no shared memory: hub.HUB_SHARED_MEMORY).
#: Zenoh creates the pool on its first such message and writes all of it (128 MiB of page
#: faults): so that happens before T0 (or before a restarted flow joins); left to the first big
#: frame, it held that put and made the source's next ticks late (benchmarks/reports/latency.md).
#: The answer comes once the pool exists: the question is in it. A node with no consumer on its
#: host never sends through a pool, and has none.
POOL_PADDING = 4096

#: A new worker waits, before it says ready, for an answer from each producer (see start), and
#: from each consumer if it makes its pool (POOL_PADDING). With many flows starting at once, a
#: worker linked to its producer may never be told of that producer's queryable, and the run
#: would never start (benchmarks/reports/deploy.md, "Scale"). So after this long without an
#: answer it says ``unanswered``; the coordinator
#: tells those neighbours to ``redeclare`` (on ctl/run, through the hub: the link
#: between the two may be what lost it), and the worker declares its own subscriptions again too.
REDECLARE_AFTER_S = 2.0


@dataclass(frozen=True)
class LoopStart:
    """When the loop runs: from ``t0`` to ``end`` (ns); ``resume``: on a restarted flow's state;
    ``started_ns``: when the start came, ns since T0 (a restarted flow's process: None)."""

    t0: int
    end: int
    resume: bool = False
    started_ns: int | None = None


def start(w: Serving) -> LoopStart | None:
    """The node's first process: declare everything; a direct link to the hub and each
    neighbour before anything is published (peers do not route for each other); each producer
    knowing this node's subscriptions (its answer to a query comes on the link after them: an
    event put before that went to no one, a gap in its stream's seqs that no frontier crosses,
    and this node waited for it forever); its pool; the events' own routes where they are not
    Zenoh's (dora). Then ``ready``, and wait for ``start``. None: stopped first."""
    w.loop.declare()
    ready = get_ready(w)
    return None if ready is None else await_start(w, ready)


def get_ready(w: Serving, same_process: frozenset[str] = frozenset()) -> Callable[[], None] | None:
    """After ``declare``: linked, answered, pooled and routed as :func:`start` says, then say
    ``ready``; the function that says it again, or None when stopped first. ``same_process``:
    the nodes in this process (a group's), which need no link."""
    loop, session, spec, keys, status = w.loop, w.session, w.spec, w.keys, w.status
    timeout = spec.startup_timeout
    unlinked = wait_for_links(session, links_needed(spec, w.plan, same_process), timeout=timeout,
                              stop=w.waiting())

    def nudge(unanswered: set[str]) -> None:  # see REDECLARE_AFTER_S
        status(protocol.Unanswered, nodes=tuple(sorted(key.rsplit("/", 1)[1] for key in unanswered)))
        loop.redeclare()

    wait_for_answers(session, {keys.progress(p) for p in producers(w.plan)}, timeout=timeout,
                     stop=w.waiting(), nudge=nudge, nudge_every=REDECLARE_AFTER_S)
    if w.padding is not None:  # its pool, before T0
        _make_pool(w, lambda: wait_for_answers(session, {keys.progress(c) for c in consumers(w.plan)},
                                               timeout=timeout, stop=w.waiting(), nudge=nudge,
                                               nudge_every=REDECLARE_AFTER_S, payload=w.padding))
    loop.await_routes(timeout=timeout)
    if loop.stopping:
        loop.undeclare()
        return None

    def ready() -> None:
        status(protocol.Ready, linked=not unlinked, unlinked=tuple(names_of(spec, unlinked)),
               peers=len(session.info.routers_zid() if spec.router else session.info.peers_zid()))

    ready()
    return ready


def await_start(w: Serving, ready: Callable[[], None]) -> LoopStart | None:
    """Wait for ``start`` (saying ``ready`` again with each ask); None: stopped first."""
    loop, session, keys = w.loop, w.session, w.keys
    # said again with each ask: a put made as a link came up may reach the hub before
    # its subscriptions did, and be dropped (the coordinator then waited for it forever)
    said = await_control(loop, protocol.Start, w.node, ask=lambda: (ready(), ask_start(session, keys, loop)))
    if said is None:
        stopped_before_start(w)
        return None
    t0, end = said.t0, said.end
    # every producer said ready, its link's socket made: each link connects now, before T0 (a
    # planned link that cannot fails the run, naming it)
    loop.transport.join_links(LINK_TIMEOUT_S, lambda: loop.stopping)
    loop.reports.values = said.values  # whether the coordinator wants the events' values
    if loop.virtual:  # lockstep: the ticks below the first grant may run
        loop.granted = min(0 if said.grant is protocol.ABSENT else said.grant, end)
    # after T0 when the start came late (a loaded machine): after the end, no tick ran
    return LoopStart(t0, end, started_ns=session.new_timestamp().get_time_as_ntp64().as_nanos() - t0)


def join(w: Serving) -> LoopStart | None:
    """A restarted flow's new process: listen now, with links to its producers and consumers,
    each knowing the other's subscribers (once the old process stops, a message that reached
    neither would be a gap); its pool; say ``ready``; take the old process's place, and state,
    when told ``resume``. None: stopped first."""
    loop, session, spec, keys = w.loop, w.session, w.spec, w.keys
    loop.declare_inputs()
    loop.transport.join_links(NEIGHBOR_TIMEOUT_S, w.waiting(), gone=_gone(w))  # its producers' links
    # the other end of each of its edges, and, if it has any, its old process (which answers for
    # the node until the hand-over)
    ends = [f.src for f in w.plan.feeds] + [c.dst for out in w.plan.consumers.values() for c in out]
    neighbors = {w.node, *ends} if ends else set()

    def gone() -> set[str]:
        return {keys.progress(n) for n in coordinator_says(session, keys, loop.opener)[0]}

    wait_for_answers(session, {keys.progress(n) for n in neighbors}, timeout=NEIGHBOR_TIMEOUT_S,
                     stop=w.waiting(), gone=gone)
    if w.padding is not None:  # its pool, before it joins
        _make_pool(w, lambda: wait_for_answers(session, {keys.progress(n) for n in consumers(w.plan)},
                                               timeout=NEIGHBOR_TIMEOUT_S, stop=w.waiting(), payload=w.padding,
                                               gone=gone))
    link_to_hub(session, spec, loop)

    def say_ready() -> None:
        w.status(protocol.Ready)

    say_ready()
    if await_control(loop, protocol.Resume, w.node, ask=say_ready) is None:
        stopped_before_start(w)
        return None
    handover_file = w.launch.run_dir / f"{w.node}.handover"
    handover.take_over(loop, handover.read_state(handover_file, loop))
    handover_file.unlink()
    loop.declare_outputs()
    loop.transport.join_links(NEIGHBOR_TIMEOUT_S, w.waiting(), gone=_gone(w))  # its consumers, at its new socket
    return LoopStart(w.launch.mode.t0, w.launch.mode.end, resume=True)


def start_afresh(w: Serving) -> LoopStart | None:
    """A flow whose process died, in its new process: a fresh flow on fresh inputs, its output
    seqs from the coordinator's ``restarted`` (:func:`_join_afresh`). None: stopped first."""
    seqs = _join_afresh(w)
    if seqs is None:
        stopped_before_start(w)
        return None
    handover.start_fresh(w.loop, seqs, w.launch.mode.t0)
    w.loop.declare_outputs()
    w.loop.transport.join_links(NEIGHBOR_TIMEOUT_S, w.waiting(), gone=_gone(w))  # its consumers, at its new socket
    return LoopStart(w.launch.mode.t0, w.launch.mode.end)


def _gone(w: Serving) -> Callable[[], set[str]]:
    """The nodes a restarted process's links wait for no more: those the coordinator says are
    done or start afresh themselves."""
    return lambda: set().union(*coordinator_says(w.session, w.keys, w.loop.opener))


def stopped_before_start(w: Serving) -> None:
    w.status(protocol.Done, counts=dict(w.loop.counts))
    w.loop.undeclare()


def _make_pool(w: Serving, ask: Callable[[], object]) -> None:
    """``ask()`` the consumers, with POOL_PADDING if the node has a pool to make, which Zenoh
    then makes: its /dev/shm segments are kept (let_go_of)."""
    before = mapped_segments() if w.padding is not None else set()
    ask()
    if w.padding is not None:
        w.pool |= mapped_segments() - before


def _join_afresh(w: Serving) -> dict[str, int] | None:
    """A flow whose process died, in its new process: subscribe to the inputs, take each stream
    on from where its producer stands (its progress answer: the reply comes on the link after
    our subscriptions, so every later event reaches us), link to the consumers (asking them
    with POOL_PADDING), say ``ready`` and wait for the coordinator's ``restarted``: the first
    seq of each output port. None on ``stop``. A neighbour that is itself starting afresh is not
    waited for as a consumer (each would wait for the other), only as a producer (it answers
    once restarted, not waiting for us)."""
    loop, session, spec, keys = w.loop, w.session, w.spec, w.keys
    loop.declare_inputs()
    loop.transport.join_links(NEIGHBOR_TIMEOUT_S, w.waiting(), gone=_gone(w))  # its producers' links
    # its own outputs fed back to it start with the seqs it gets below (start_fresh)
    answers = _producers_progress(w)
    if loop.stopping:
        return None
    handover.sync_inputs(loop.streams, answers)  # a producer that never answered: its events are taken from seq 0
    _make_pool(w, lambda: wait_for_answers(
        session, {keys.progress(n) for n in consumers(w.plan)}, timeout=NEIGHBOR_TIMEOUT_S,
        stop=w.waiting(), payload=w.padding,
        gone=lambda: {keys.progress(n) for n in set().union(*coordinator_says(session, keys, loop.opener))}))
    # the coordinator's comes after `ready`: one before is not its
    drop_queued(loop, protocol.Restarted, w.node)
    link_to_hub(session, spec, loop)

    def ready() -> None:
        w.status(protocol.Ready)

    ready()
    restarted = await_control(loop, protocol.Restarted, w.node, ask=ready)  # said again: see START_ASK_S
    if restarted is None:
        return None
    loop.reports.values = restarted.values
    seqs = restarted.seqs
    if not all(seqs.get(p, -1) >= RESTART_SEQ_GAP for p in loop.ports):
        raise RuntimeError(f"the 'restarted' for {w.node} carries no seq past {RESTART_SEQ_GAP} for each output "
                           f"port: {seqs!r:.200}")
    return dict(seqs)


def _producers_progress(w: Serving) -> dict:
    """Each producer's progress, as it answers (None for one the coordinator says is done), for
    NEIGHBOR_TIMEOUT_S at most; a producer that never answered is left out."""
    wanted = producers(w.plan)
    answers: dict = {}
    give_up = time.monotonic() + NEIGHBOR_TIMEOUT_S
    while not w.loop.stopping and time.monotonic() < give_up:
        for src in sorted(wanted - set(answers)):
            for reply in w.session.get(w.keys.progress(src), timeout=0.25):
                try:
                    answers[src] = decode_progress(reply.ok.payload.to_bytes(), expected=src)
                except (AttributeError, WireError):  # no answer (reply.err), or not a progress message
                    continue
        done, _ = coordinator_says(w.session, w.keys, w.loop.opener)
        answers.update((n, None) for n in (wanted - set(answers)) & done)
        if wanted <= set(answers):
            break
        time.sleep(0.02)
    return answers
