"""The worker process of a group: several flows in one process (``configure(process=NAME)``).

    python -m retriever.backends.zenoh.worker.group SPEC.json NAME     NAME: a group of the spec's "groups"

The same phases as a worker of one node (the package's docstring), each over every member: one
Zenoh session; the IR read once; each member rebuilt into its own loop, their events between them
on a LocalBus and the run's control heard once for all (node/group.py); every member declared,
linked and ``ready``; then the ``start``, and one GroupLoop stepping them all on this thread; then
each says ``done`` (or ``failed``), releases, and the process waits until the coordinator has
every report of every member.

A member with ``on_error="restart"`` restarts in place: its step raised, and a fresh flow, rebuilt
from the IR and set up here, goes on in its loop, within the budget that loop holds; the other
members step on untouched (node/in_place.py). A member that fails (StopRun, a restart past its
budget, a crash of its loop) ends the group: the run fails anyway, and the others say ``done``.
The process dying takes every member with it, and the run fails (coordinator/processes.py: no
member is started afresh on its own). Signals and ``failed`` are the single worker's (ending.py).

A group on dora (backends/dora/node.py) is served here too: its launch names dora's transport,
which carries what the members exchange with nodes outside the group, as Zenoh does here; and so
is a flow alone there with on_error="restart", a group of one (dora starts its processes once).
"""

from __future__ import annotations

import dataclasses
import sys

from ....ir import IR
from ..command import GROUP_MODULE
from ..hub import needs_shared_memory
from ..node import Ending
from ..node.group import GroupLoop, GroupTransport, LocalBus
from ..node.transport import ZenohTransport
from ..protocol import EXIT_ABANDONED, EXIT_FAILED, RunSpec
from ..wire import KeySpace
from . import main
from .build import Serving, StatusSender, build, open_session, restart_in_place, run_plan, set_up_flow
from .ending import handle_signals, release, say_done, say_failed
from .links import watch_hub_link
from .process import Launch
from .starts import POOL_PADDING, await_start, get_ready
from .waits import await_reports_taken


def serve_group(launch: Launch, spec: RunSpec, pool: set[str]) -> int:
    """Serve every member of the group ``launch.node`` from the session's open to its close."""
    members = list(spec.groups[launch.node])
    keys = KeySpace(spec.namespace)
    ir = IR(spec.ir, source="the run's IR")  # read and planned once, for every member
    plans = run_plan(spec, ir)
    shared_memory = any(needs_shared_memory(spec.ir, n) for n in members)
    with open_session(spec, members[0], launch.mode, shared_memory) as session:
        bus = LocalBus(set(members))
        inner = launch.transport or (lambda session, node: ZenohTransport(session, keys, node))
        served: list[Serving] = []
        control = None
        try:
            for node in members:
                w = Serving(dataclasses.replace(launch, node=node), spec, session, keys,
                            StatusSender(session, keys, node, launch.key),
                            padding=bytes(POOL_PADDING) if shared_memory else None, pool=pool, plan=plans[node],
                            ir=ir, transport=_member_transport(bus, plans[node], inner))
                if not build(w):
                    return EXIT_FAILED
                restart_in_place(w, ir)
                served.append(w)
            group = GroupLoop([w.loop for w in served])
            control = group.hear_control(session, keys, served[0].loop.opener)
            handle_signals((w.loop for w in served), launch.parent)
            if not all(set_up_flow(w) for w in served):
                return EXIT_FAILED
            return _run(served, group, frozenset(members))
        finally:
            if control is not None:
                control.undeclare()
            for w in served:
                release(w.loop, w.node)


def _member_transport(bus: LocalBus, plan, inner):
    """A member's transport maker: its events on ``bus`` to the other members, on ``inner``'s
    transport (Zenoh, or the launch's: dora's) to nodes elsewhere, for the ports a node
    elsewhere consumes only."""
    def make(session, node: str) -> GroupTransport:
        elsewhere = {port for port, edges in plan.consumers.items() if any(c.dst not in bus.members for c in edges)}
        return GroupTransport(bus, inner(session, node), node, elsewhere, bool(elsewhere))

    return make


def _run(served: list[Serving], group, members: frozenset[str]) -> int:
    """Every member ready, the start, the group's run, then each member's end: the exit code."""
    readies = []
    for w in served:
        w.loop.declare()
    for w in served:
        ready = get_ready(w, same_process=members)
        if ready is None:
            return 0  # stopped first (the member said so)
        readies.append(ready)
    begins = [await_start(w, ready) for w, ready in zip(served, readies)]
    if any(b is None for b in begins):
        return 0
    began = {w.node: b for w, b in zip(served, begins)}
    by_id = {w.node: w for w in served}
    done: set[str] = set()

    def ended(loop) -> None:  # said at once, as a process of its own would by exiting
        if loop.ending is not Ending.ABANDONED:  # (its parent died: it says nothing, as if killed)
            say_done(by_id[loop.id], began[loop.id])
        done.add(loop.id)

    hub_link = watch_hub_link(served[0].session, served[0].spec.hub_zid, ",".join(sorted(members)),
                              routers=list(served[0].spec.router))
    try:
        failed = group.run(begins[0].t0, begins[0].end, on_end=ended)
    finally:
        if hub_link is not None:
            hub_link.undeclare()
    if any(w.loop.ending is Ending.ABANDONED for w in served):
        return EXIT_ABANDONED
    code = 0
    for w in served:
        if w.node in done:
            continue
        if failed is not None and failed[0] == w.node:
            say_failed(w, failed[1])
            code = EXIT_FAILED
        else:  # (a member failed: the run ends, and these end with it)
            w.loop.end()
            say_done(w, began[w.node])
    # (a failed member is never `complete`: like a lone flow's process that failed, none waits for it)
    waiting = [w.node for w in served if failed is None or failed[0] != w.node]
    first = served[0]
    if waiting:
        await_reports_taken(first.session, first.keys, first.loop.opener, waiting, first.spec.hub_zid,
                            routers=list(first.spec.router))
    return code


if __name__ == "__main__":
    main(sys.argv[1:], serve_with=serve_group, module=GROUP_MODULE)
