"""A worker's links: to its neighbours and the coordinator before it says ready, and watched
while its node runs (a lost link to the coordinator is said on stderr: nothing else tells).

Peers do not route for each other: a worker on another machine joins through its worker daemon
and finds the hub and its neighbours by gossip, so it waits for a direct link to each (a client
of routers waits for a router instead) before it puts anything they must take.
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import zenoh

from ....errors import LinkError
from ....plan import NodePlan
from ..hub import router_linked, wait_for_links, wait_for_router
from ..link.server import MAX_PATH
from ..node import NodeLoop
from ..node.linked import MAX_LINKED_PORTS, LinkPlan
from ..protocol import RunSpec

#: how long a node's first process waits, after the start's barrier, for its same-host links to
#: connect (its producers' sockets are there: each said ready after making its own)
LINK_TIMEOUT_S = 10.0

#: how long a restarted flow's process waits for its producers and consumers to answer before it
#: says ready anyway (one that never answers has finished, or is stuck)
NEIGHBOR_TIMEOUT_S = 10.0


def links_needed(spec: RunSpec, plan: NodePlan, same_process: frozenset[str] = frozenset()) -> set[str]:
    """The Zenoh ids of the sessions the first process of ``plan``'s node must be linked to
    before it says ready: the hub's, and its producers' and consumers' but those in this process
    (an old spec without ids, or a client of routers, which links to nothing else: none)."""
    zids = spec.zids
    if not zids or not spec.hub_zid or spec.router:
        return set()
    neighbors = (producers(plan) | consumers(plan)) - same_process
    return {spec.hub_zid, *(zids[n] for n in neighbors if n in zids)}


def producers(plan: NodePlan) -> set[str]:
    """The other nodes with an edge into ``plan``'s node."""
    return {f.src for f in plan.feeds} - {plan.id}


def consumers(plan: NodePlan) -> set[str]:
    """The other nodes with an edge from ``plan``'s node."""
    return {c.dst for out in plan.consumers.values() for c in out} - {plan.id}


def link_plan(spec: RunSpec, plan: NodePlan, run_dir: Path) -> LinkPlan | None:
    """``plan``'s node's same-host links (node/linked.py), or None when it has none: where the
    spec says ``links`` (every process of the run on this host), each edge between two processes
    but a group's (whose process keeps Zenoh for its edges, as its members' in-process flows
    keep the group's bus). Both ends of an edge read it from the same spec."""
    if not spec.links or plan.id in _grouped(spec):
        return None
    grouped = _grouped(spec)
    outputs = {n["id"]: tuple(sorted(n["outputs"])) for n in spec.ir["nodes"]}
    order = sorted(outputs)
    for node in (plan.id, *producers(plan)):
        if len(outputs[node]) > MAX_LINKED_PORTS:
            raise LinkError(f"node {node!r} has {len(outputs[node])} output ports: a same-host link carries at most "
                            f"{MAX_LINKED_PORTS}\n    hint: pipe.run(..., same_host_links=False)")
    linked_consumers = frozenset(consumers(plan) - grouped)
    linked_producers = {p: (socket_path(run_dir, p, order), outputs[p]) for p in sorted(producers(plan) - grouped)}
    if not linked_consumers and not linked_producers:
        return None
    return LinkPlan(spec.namespace, socket_path(run_dir, plan.id, order) if linked_consumers else None,
                    linked_consumers, linked_producers, outputs[plan.id], on_zenoh=bool(consumers(plan) & grouped))


def all_linked(spec: RunSpec, plan: NodePlan | None, run_dir: Path) -> bool:
    """Whether every edge of ``plan``'s node to another process is a same-host link (None: no
    links in the run)."""
    if plan is None or not (producers(plan) or consumers(plan)):
        return False
    try:
        links = link_plan(spec, plan, run_dir)
    except LinkError:  # (said by build, which makes the same plan: the node's status says it)
        return False
    return links is not None and set(links.producers) == producers(plan) and links.consumers == consumers(plan)


def socket_path(run_dir: Path, node: str, nodes: list[str]) -> Path:
    """``node``'s link socket in the run's folder: ``link-<node>.sock``, or, where that is longer
    than a Unix socket's path may be, ``link-<i>.sock`` (``i``: its index in ``nodes``)."""
    path = run_dir / f"link-{node}.sock"
    return path if len(bytes(path)) <= MAX_PATH else run_dir / f"link-{nodes.index(node)}.sock"


def _grouped(spec: RunSpec) -> set[str]:
    return {n for members in spec.groups.values() for n in members}


def link_to_hub(session, spec: RunSpec, loop: NodeLoop) -> None:
    """Wait (NEIGHBOR_TIMEOUT_S at most) for a direct link to the coordinator's session: a
    process on another machine joins through its worker daemon and finds the hub by gossip,
    and a status it put before that link was up went nowhere (peers do not route). A client of
    routers waits for a router link instead: the router routes to the coordinator."""
    if spec.router:
        wait_for_router(session, NEIGHBOR_TIMEOUT_S, stop=lambda: loop.stopping)
    elif spec.hub_zid:
        wait_for_links(session, {spec.hub_zid}, NEIGHBOR_TIMEOUT_S, stop=lambda: loop.stopping)


def names_of(spec: RunSpec, zids: set[str]) -> list[str]:
    """What the sessions ``zids`` are, by node name ("the coordinator" for the hub)."""
    names = {z: n for n, z in spec.zids.items()}
    names[spec.hub_zid] = "the coordinator"
    return sorted(names.get(z, z) for z in zids)


def coordinator_linked(session, hub_zid: str | None, routers: list[str] | None = None) -> bool | None:
    """Whether this process has its path to the coordinator: a direct link to the hub's session
    (``hub_zid``), or, for a client of ``routers``, a link to a router; None when it cannot
    tell (no hub id)."""
    if routers:
        return router_linked(session)
    return None if not hub_zid else hub_zid in {str(z) for z in session.info.peers_zid()}


def watch_hub_link(session, hub_zid: str | None, node_id: str, routers: list[str] | None = None):
    """Say on stderr when this process's link to the coordinator's session (``hub_zid``) closes
    while the node runs, or, for a client of ``routers``, its last link to a router; the
    listener (undeclare it), or None without a hub id.

    Nothing else would tell: a put with no route is dropped without an error, and Zenoh re-opens
    only the links to a session's configured endpoints. A flow on a worker daemon found the hub by
    gossip, so from then on its reports and its last status go nowhere and the run ends with
    "exited with code 0 before it finished". Zenoh closes a healthy link when its peer's lease
    passes with nothing read from it, and reading stops while Zenoh closes another link whose
    queue a put holds (a consumer's host cut off, congestion control BLOCK): it takes that queue's
    lock, on a thread that also reads links, and waits for each put that holds it, up to its
    wait_before_close, before the link leaves the routes (benchmarks/reports/partition_move.md)."""
    if routers:
        return _watch_router_link(session, routers, node_id)
    if not hub_zid:
        return None

    def closed(event) -> None:  # on a thread of zenoh-python's
        if event.kind == zenoh.SampleKind.DELETE and str(event.transport.zid) == hub_zid:
            print(f"retriever: worker '{node_id}' lost its link to the coordinator at {time.strftime('%H:%M:%S')} "
                  "(Zenoh closed it, and does not open it again): what it reports from now on does not reach the "
                  "coordinator", file=sys.stderr, flush=True)

    return session.info.declare_transport_events_listener(closed)


def _watch_router_link(session, routers: list[str], node_id: str):
    """watch_hub_link for a client of ``routers``: say on stderr when its last router link
    closes, and when one is back (Zenoh joins a router again by itself); what it put between
    the two went nowhere."""
    def changed(event) -> None:  # on a thread of zenoh-python's
        if event.kind == zenoh.SampleKind.DELETE and not list(session.info.routers_zid()):
            print(f"retriever: worker '{node_id}' lost its link to the router ({', '.join(routers)}) at "
                  f"{time.strftime('%H:%M:%S')}: what it reports until the router is back does not reach the "
                  "coordinator", file=sys.stderr, flush=True)
        elif event.kind == zenoh.SampleKind.PUT:
            print(f"retriever: worker '{node_id}' is linked to a router again at {time.strftime('%H:%M:%S')}",
                  file=sys.stderr, flush=True)

    return session.info.declare_transport_events_listener(changed)
