"""Zenoh sessions the way the embedded runtime opens them: peer mode, loopback, no multicast; and
the client sessions of a run joined through a router (client_config).

The run's *hub* is the session of the process that starts the run. It listens on a free loopback
port (the run says which, and writes it in its watcher file), so that worker processes and any
Zenoh client (a plain ``zenoh`` subscriber watching ``retriever/<ns>/data/**``) can join it. Not
on Zenoh's 7447 unless asked (``hub_port=7447``): that port belongs to the machine's Zenoh router
(rmw_zenoh's ``rmw_zenohd``, which a ROS 2 flow joins there) or its Retriever worker daemon, and a
local run that took it would keep them from starting, or take their clients' links itself.
"""

from __future__ import annotations

import functools
import json
import os
import re
import resource
import secrets
import socket
import time
import weakref
from collections.abc import Callable
from typing import Any

import zenoh

from .wire import KeySpace

LOOPBACK = "127.0.0.1"

#: Zenoh copies a message bigger than 3 KiB between peers on one host into a shared-memory pool
#: of the sender's and sends a reference (its "transport optimization", on by default). A message
#: that does not fit goes over TCP instead, several times slower: with Zenoh's default 16 MiB pool,
#: every 16 MiB frame would (benchmarks/reports/latency.md). So the pool gets up to
#: SHM_POOL_MAX, but at most 1/SHM_POOL_SHARE of what /dev/shm has free (Docker gives 64 MB by
#: default; a write past a full tmpfs is a SIGBUS), and never less than Zenoh's default.
#: Every worker of a run that sends to a consumer on its host has a pool (the hub has none:
#: HUB_SHARED_MEMORY), and writes all of it (worker/starts.py, POOL_PADDING), so the run's workers share
#: that 1/SHM_POOL_SHARE and SHM_POOL_RUN_MAX: 50 flows with 128 MiB each would write 6.4 GB of
#: /dev/shm while they start, and the page faults take so long that some of them miss the run's
#: start (benchmarks/reports/scale.md).
SHM_POOL_MAX = 128 << 20
SHM_POOL_MIN = 16 << 20
SHM_POOL_SHARE = 8
SHM_POOL_RUN_MAX = 1 << 30


#: Zenoh removes a /dev/shm/*.zenoh segment only when it can lock it exclusively: when the last
#: process that maps it lets go, or in a scan of every segment at a process's exit() (and at its
#: first shared-memory use), which skips the segments still mapped, by anyone, the exiting
#: process included. A closed session lets go of its segments on a Zenoh thread some
#: milliseconds later, so a program that exits right after a session closed can leave the
#: session's segment behind. Closing a session with shared
#: memory in a process that goes on (daemon.in_session) waits for that, at most this long.
SEGMENT_RELEASE_S = 0.5


def mapped_segments() -> set[str]:
    """The Zenoh shared-memory segments this process maps (Linux; elsewhere none)."""
    try:
        with open("/proc/self/maps", encoding="utf-8", errors="replace") as maps:
            return {line.rsplit(None, 1)[-1] for line in maps if line.rstrip().endswith(".zenoh")}
    except OSError:
        return set()


def await_segments_released(segments: set[str], bound: float = SEGMENT_RELEASE_S) -> None:
    """After a session's close() and the last reference to it dropped: wait until this process
    maps none of ``segments`` (the session's own), at most ``bound`` s."""
    give_up = time.monotonic() + bound
    while mapped_segments() & segments and time.monotonic() < give_up:
        time.sleep(0.002)


def endpoint(port: int, host: str = LOOPBACK) -> str:
    return f"tcp/{host}:{port}"


def port_is_free(port: int, host: str = LOOPBACK) -> bool:
    """Whether a listener could bind ``port`` now. Like Zenoh's, the probe may reuse the address
    of connections in TIME_WAIT: without that, the port of the last run's hub looked taken for a
    minute after it closed, and the next run moved to a random port."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            s.bind((host, port))
        except OSError:
            return False
    return True


def free_port(host: str = LOOPBACK) -> int:
    """A TCP port nothing listens on now (the OS picks it)."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind((host, 0))
        return s.getsockname()[1]


def shm_pool_bytes(free_bytes: int | None = None, sessions: int = 1) -> int:
    """The shared-memory pool for one of a run's ``sessions`` (SHM_POOL_MAX): ``free_bytes`` is
    what /dev/shm has free (read now if not given; 0 if there is no /dev/shm)."""
    if free_bytes is None:
        try:
            st = os.statvfs("/dev/shm")
            free_bytes = st.f_bavail * st.f_frsize
        except OSError:
            free_bytes = 0
    run_share = min(SHM_POOL_RUN_MAX, free_bytes // SHM_POOL_SHARE)
    return max(SHM_POOL_MIN, min(SHM_POOL_MAX, run_share // max(1, sessions)))


#: Gossip makes two workers that learn of each other (from the hub) link up directly; by default
#: both open a link at once, and Zenoh keeps one. With authentication, whose handshake is longer,
#: that race can lose both links, leaving a worker pair with no link (a consumer that never gets
#: an event). So only the peer of greater Zenoh id opens it (tests/backends/zenoh/test_access.py's
#: runs depend on every pair linking).
GOSSIP_ONE_WAY = '{peer: {to_peer: "greater-zid", to_router: "always"}}'


#: A link a session accepts waits in Zenoh's handshake (its peer proves the run's password) for
#: at most ACCEPT_TIMEOUT_S, and at most accept_pending() links wait at once; a connection
#: beyond that is closed at once. A stranger with no credentials who holds idle TCP connections
#: to an endpoint takes those places: at Zenoh's defaults (100 links, 10 s) 250 connections held
#: open kept every deploy, `retriever workers` and flow restart off a daemon. A handshake is two
#: round trips; ACCEPT_TIMEOUT_S leaves a loaded machine and a long route room for them while a
#: stranger's connection holds its place 3 s instead of 10 s. A place costs a file descriptor
#: and a small task, so a session takes ACCEPT_PENDING_MAX places, but at most half of the
#: process's open-file limit (raise_open_file_limit), never fewer than Zenoh's 100. Whoever
#: holds more connections still keeps new links out: docs/security.md says what to do about it.
ACCEPT_TIMEOUT_S = 3.0
ACCEPT_PENDING_MAX = 2000
ACCEPT_PENDING_MIN = 100


def accept_pending(open_files: int | None = None) -> int:
    """How many links a session lets wait in Zenoh's handshake at once (see ACCEPT_TIMEOUT_S),
    of a process that may open ``open_files`` files (its limit now, if not given)."""
    if open_files is None:
        open_files = resource.getrlimit(resource.RLIMIT_NOFILE)[0]
    if open_files == resource.RLIM_INFINITY:
        return ACCEPT_PENDING_MAX
    return max(ACCEPT_PENDING_MIN, min(ACCEPT_PENDING_MAX, open_files // 2))


def raise_open_file_limit() -> int:
    """Raise this process's soft limit of open files to its hard limit (what systemd and most
    shells leave at 1024 is the soft one), so that the links waiting in a handshake
    (accept_pending) cannot take every descriptor a daemon needs to start its flows. Its
    processes inherit it. The limit now."""
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    if soft != hard:
        try:
            resource.setrlimit(resource.RLIMIT_NOFILE, (hard, hard))
        except (ValueError, OSError):  # a platform that caps it lower (macOS: OPEN_MAX)
            return soft
    return hard


def peer_config(*, listen: list[str] = (), connect: list[str] = (), sessions: int = 1,
                access: dict[str, str] | None = None, lease: float | None = None,
                zid: str | None = None, shared_memory: bool = True, blocked_put: float | None = None) -> zenoh.Config:
    """Peer mode, multicast scouting off, explicit endpoints, quick reconnects.

    Zenoh's shared memory stays on (its default) unless ``shared_memory`` is false (see
    :func:`needs_shared_memory`), though Retriever never allocates in it: with it off, big
    messages between peers on one host are much slower (benchmarks/reports/latency.md compares
    Retriever's latency with raw Zenoh's), and its pool is sized by
    :func:`shm_pool_bytes` for one of the run's ``sessions``. Its costs: each session has a
    segment in /dev/shm, which a SIGKILLed process leaves behind; and a process with a link that
    uses it wakes 20 times a second for as long as it lives (:func:`needs_shared_memory`).

    ``blocked_put``: how long (s) a put may wait for room on one link before Zenoh closes that
    link (its default: 5 s); the put then goes on to the other links.

    ``access``: the config entries that make the session one of a run's (``access.py``:
    authentication and access control); without it, the session admits anyone. ``zid``: the
    session's Zenoh id (:func:`new_zid`), for one the others must know before it exists."""
    config = _session_config("peer", connect, sessions=sessions, lease=lease, zid=zid, shared_memory=shared_memory,
                             blocked_put=blocked_put)
    config.insert_json5("listen/endpoints", json.dumps(list(listen)))
    config.insert_json5("connect/retry", "{period_init_ms: 100, period_max_ms: 200, period_increase_factor: 1.5}")
    # strangers' idle connections must not keep the run's own links out (see ACCEPT_TIMEOUT_S)
    config.insert_json5("transport/unicast/accept_timeout", str(round(ACCEPT_TIMEOUT_S * 1000)))
    config.insert_json5("transport/unicast/accept_pending", str(accept_pending()))
    # of two peers that learn of each other, only one opens the link (see GOSSIP_ONE_WAY)
    config.insert_json5("scouting/gossip/autoconnect_strategy", GOSSIP_ONE_WAY)
    for key, value in (access or {}).items():
        config.insert_json5(key, value)
    return config


def client_config(*, connect: list[str], sessions: int = 1, access: dict[str, str] | None = None,
                  lease: float | None = None, zid: str | None = None, shared_memory: bool = True,
                  blocked_put: float | None = None) -> zenoh.Config:
    """Client mode: a session that joins a run through the Zenoh routers at ``connect``
    (``retriever router``, router.py, or any Zenoh router), listens nowhere and scouts for
    nothing. A router forwards between its clients, where peers would need a direct link
    between every pair: the run's processes need no address the others reach, only a way out
    to a router (a robot behind NAT), and a run of N sessions has N links, not N²/2.

    ``zenoh.open`` raises ZError at once when no router at ``connect`` admits the session (none
    listens, or it refused the credentials); one that admitted it and was lost is joined again
    by Zenoh, in the background. ``access``: the entries with which it proves its namespace's
    password to the router (``RunAccess.client_config``); the router checks it and enforces
    what each namespace may do, so a client has no dictionary or access control of its own.
    The other arguments are :func:`peer_config`'s."""
    config = _session_config("client", connect, sessions=sessions, lease=lease, zid=zid, shared_memory=shared_memory,
                             blocked_put=blocked_put)
    config.insert_json5("listen/endpoints", "[]")
    for key, value in (access or {}).items():
        config.insert_json5(key, value)
    return config


def _session_config(mode: str, connect: list[str], *, sessions: int, lease: float | None, zid: str | None,
                    shared_memory: bool, blocked_put: float | None) -> zenoh.Config:
    """What a peer's and a client's configs share: ``mode``, where it connects, no multicast
    scouting, and the settings of its links and shared memory (peer_config's arguments)."""
    config = zenoh.Config()
    if zid is not None:
        config.insert_json5("id", json.dumps(zid))
    config.insert_json5("mode", json.dumps(mode))
    config.insert_json5("scouting/multicast/enabled", "false")
    config.insert_json5("transport/shared_memory/transport_optimization/pool_size", str(shm_pool_bytes(sessions=sessions)))
    config.insert_json5("connect/endpoints", json.dumps(list(connect)))
    if lease is not None:  # how long a silent link lives (a partition): Zenoh's default is 10 s
        config.insert_json5("transport/link/tx/lease", str(round(lease * 1000)))
    if blocked_put is not None:  # a put held this long by one link (BLOCK: its far end took nothing) closes it
        config.insert_json5("transport/link/tx/queue/congestion_control/block/wait_before_close",
                            str(round(blocked_put * 1e6)))
    if not shared_memory:
        config.insert_json5("transport/shared_memory/enabled", "false")
    return config


#: the words of a port type (as the IR writes it, flow/core.type_name) whose values are a few
#: bytes whatever they hold: Zenoh's shared memory carries messages over 3 KiB only
_SMALL_TYPE_WORDS = frozenset({"int", "float", "bool", "complex", "None", "NoneType"})
#: ``Optional[...]`` and ``Union[...]`` hold what their brackets say (bare, they hold anything)
_UNION_OPENING = re.compile(r"\b(?:Optional|Union)\[")


def needs_shared_memory(ir: dict, node_id: str) -> bool:
    """Whether ``node_id``'s session may carry a value big enough for Zenoh's shared memory:
    unless every port of the node that an edge connects has a type made of scalars only
    (``float``, ``int | None``, …). A node with no edge (an idle flow) or only such ports
    opens its session without it. A process with a link that uses shared memory runs Zenoh's
    watchdog "confirmator" every 50 ms (fixed in Zenoh): 20 wake-ups a second, a small share of
    what an idle flow costs in all (benchmarks/reports/idle_cpu.md). A value bigger than its port's type said still arrives, over TCP.
    Anything this cannot read in the IR keeps shared memory on (Zenoh's default)."""
    try:
        node = next(n for n in ir["nodes"] if n["id"] == node_id)
        for edge in ir["edges"]:
            for end, ports in (("source", "outputs"), ("destination", "inputs")):
                if edge[end]["node"] == node_id:
                    spelled = _UNION_OPENING.sub("[", node[ports][edge[end]["port"]])
                    words = set(re.split(r"[\s|,\[\]]+", spelled)) - {""}
                    if not words or not words <= _SMALL_TYPE_WORDS:
                        return True
    except (KeyError, TypeError, StopIteration):
        return True
    return False


def forward_dropping(keys: KeySpace) -> dict[str, str]:
    """The config entries (key → JSON5 value) with which the hub forwards what the run's
    processes publish with congestion control DROP instead of their BLOCK.

    The hub forwards those messages to its Zenoh clients only, the watchers: peers do not route
    for each other, so the run's own events go worker to worker (open_peer). A BLOCK message
    waits for room in its link's queue up to Zenoh's `wait_before_close` (5 s), then the link is
    closed; and the hub forwards on the thread that read the message from the producer's link.
    So to a watcher that stopped reading (SIGSTOP: its socket full), the hub's thread reading
    the cam's link waited 5 s, then closed the watcher's link; meanwhile the cam's own put of a
    frame waited on its full link to the hub, and after 5 s the cam closed that link ("Unable
    to push non droppable network message ... Closing transport!"), reports and statuses queued
    on it lost: the run failed 1 in 5 times, more under load (a worker that "did not finish in
    time" or "exited before it finished", a sink short of events; test_access.py). With DROP,
    a message to a congested link is dropped at once: a watcher that cannot keep up misses
    messages, the run never waits for it. Only the hub's forwarding changes: the workers' puts
    keep BLOCK on their links, and the coordinator's control (ctl/run, not in these keys) too;
    watchers never get that (access.py, WATCHER_UNSEEN)."""
    rule = {"id": "forward_to_watchers_dropping", "messages": ["put", "delete"], "flows": ["egress"],
            "key_exprs": [keys.all_data(), keys.progress("**"), keys.status("**"), keys.warm("**")],
            "overwrite": {"congestion_control": "drop"}}
    return {"qos/network": json.dumps([rule])}


#: A process that receives a message through another's shared-memory pool maps that pool, and
#: the pool's metadata segment (1.25 MiB), until it exits: Zenoh keeps every segment it ever
#: attached in storage global to the process, closed sessions and exited senders alike, and
#: zenoh-python has nothing that lets go of one (eclipse-zenoh/zenoh#1700, #2787). With shared
#: memory, a run's hub would attach each worker's pool (its ``ready`` status, then its reports),
#: so a program would keep RAM mapped for every run it had run (/dev/shm, counted in RssShmem),
#: growing with each. So the hub has no shared memory, nor a pool of its own; the workers use
#: theirs between each other.
HUB_SHARED_MEMORY = False


@functools.cache
def remove_orphaned_segments_at_exit() -> None:
    """Have Zenoh remove the /dev/shm segments that no process maps, now and at this process's
    exit(): it does so in a process in which it has set up shared memory, as making a provider
    (dropped at once, mapping nothing after) does. A run's last worker to exit still maps the
    metadata segment of the producer it received from, which so outlives both; a process whose
    sessions have no shared memory (a hub's, a worker daemon's: HUB_SHARED_MEMORY) would leave it
    there."""
    try:
        zenoh.shm.ShmProvider.default_backend(4096)
    except (AttributeError, zenoh.ZError):  # a Zenoh without shared memory leaves no segment
        pass


def open_hub(preferred_port: int = 0, attempts: int = 5, access: dict[str, str] | None = None,
             keys: KeySpace | None = None) -> tuple[zenoh.Session, str]:
    """Open the run's hub session; returns it and the endpoint it listens on. Close it (``with``).
    ``preferred_port``: where to listen if that port is free (0, the default: a free port).
    ``keys``: the run's key space, whose messages it forwards to watchers dropping
    (forward_dropping).

    Without shared memory (HUB_SHARED_MEMORY), so what the workers send it comes over TCP."""
    # 0: any free port (Zenoh would listen on one but tell no one which)
    port = preferred_port if preferred_port and port_is_free(preferred_port) else free_port()
    remove_orphaned_segments_at_exit()
    if keys is not None:
        access = {**(access or {}), **forward_dropping(keys)}
    last: Exception | None = None
    for _ in range(attempts):
        try:
            return (zenoh.open(peer_config(listen=[endpoint(port)], access=access, shared_memory=HUB_SHARED_MEMORY)),
                    endpoint(port))
        except zenoh.ZError as e:  # taken between the check and the bind: try another
            last = e
            port = free_port()
    raise OSError(f"could not open a Zenoh hub on 127.0.0.1 after {attempts} attempts: {last}")


def open_peer(hub_endpoint: str, sessions: int = 1, access: dict[str, str] | None = None,
              listen: list[str] | None = None, lease: float | None = None, zid: str | None = None,
              shared_memory: bool = True, blocked_put: float | None = None) -> zenoh.Session:
    """A worker's or client's session, joined to the hub, one of the run's ``sessions``. Close it
    (``with``).

    It listens too, on a free loopback port unless ``listen`` says where (a worker on another
    machine: an address the others reach it at, port 0): peers do not route for each other, so
    two workers exchange messages over the direct link that gossip (learning of each other from
    the hub) opens between them, which is also the fastest path."""
    return zenoh.open(peer_config(listen=listen or [endpoint(0)], connect=[hub_endpoint], sessions=sessions,
                                  access=access, lease=lease, zid=zid, shared_memory=shared_memory,
                                  blocked_put=blocked_put))


def wait_for_answers(session: zenoh.Session, keys: set[str], timeout: float, stop=lambda: False, gone=lambda: set(),
                     nudge=None, nudge_every: float = 2.0, payload: bytes | None = None) -> set[str]:
    """Query each of ``keys`` until a reply has come from each that is not ``gone()``, at most
    ``timeout`` s; the keys that never answered. A reply travels on the link between the two
    sessions, after the declarations each had sent on it: once a peer answers, each knows the
    other's subscribers (peers do not route for each other: there is no other path).

    Each key is asked by name, all at once: a query on a wildcard (``progress/**``) would go to
    every node of the run, so N starting nodes would ask N² questions, and at scale the answers
    fall so far behind that some node never has its producer's (benchmarks/reports/deploy.md).
    ``nudge(missing)``, if given, is called every ``nudge_every`` s that some key has not answered.
    ``payload``: what each question carries (the answerers ignore it: worker/starts.py, POOL_PADDING)."""
    missing = set(keys)
    give_up = time.monotonic() + timeout
    next_nudge = time.monotonic() + nudge_every
    while missing and time.monotonic() < give_up and not stop():
        asked = [session.get(key, payload=payload, timeout=0.25) for key in sorted(missing)]
        for replies in asked:
            for reply in replies:
                if reply.ok is not None:
                    missing.discard(str(reply.ok.key_expr))
        missing -= gone()
        if missing and nudge is not None and time.monotonic() >= next_nudge:
            nudge(missing)
            next_nudge = time.monotonic() + nudge_every
        if missing:
            time.sleep(0.02)
    return missing


def new_zid() -> str:
    """A random Zenoh session id, as ``str(session.zid())`` spells it (lowercase hex, 32 digits,
    no leading zero): given to a session in its config, the others know it before it opens."""
    return secrets.choice("123456789abcdef") + secrets.token_hex(16)[1:]


def wait_for_peers(session: zenoh.Session, count: int, timeout: float, stop=lambda: False) -> bool:
    """Wait until ``session`` has direct links to ``count`` peers; False on timeout or ``stop()``."""
    give_up = time.monotonic() + timeout
    while len(session.info.peers_zid()) < count:
        if time.monotonic() > give_up or stop():
            return False
        time.sleep(0.005)
    return True


def wait_for_links(session: zenoh.Session, zids: set[str], timeout: float, stop=lambda: False) -> set[str]:
    """Wait until ``session`` has a direct link to each of the sessions ``zids``: those it has
    none to at the timeout or ``stop()`` (none: all linked). Counting links is not enough where
    sessions of others (a worker daemon) are peers too."""
    give_up = time.monotonic() + timeout
    while missing := zids - {str(z) for z in session.info.peers_zid()}:
        if time.monotonic() > give_up or stop():
            return missing
        time.sleep(0.005)
    return set()


def wait_for_router(session: zenoh.Session, timeout: float, stop=lambda: False) -> bool:
    """Wait until ``session`` (a client: client_config) has a link to a router; False on
    timeout or ``stop()``. A client's only links are to routers, which route for it: what a
    peer's direct links to its neighbours (wait_for_links) prove, one router link does."""
    give_up = time.monotonic() + timeout
    while not router_linked(session):
        if time.monotonic() > give_up or stop():
            return False
        time.sleep(0.005)
    return True


def router_linked(session: zenoh.Session) -> bool:
    """Whether ``session`` has a link to a router now (a client loses it with the router, and
    Zenoh opens it again by itself once the router is back)."""
    return bool(list(session.info.routers_zid()))


def weak_callback(method: Callable[..., None], *leading: Any) -> Callable[[Any], None]:
    """A callback for Zenoh that calls ``method(*leading, sample)`` while the method's object
    lives, without holding it: every bound method handed to Zenoh goes through here.

    Zenoh sometimes keeps an undeclared subscriber's or queryable's callback for as long as its
    session lives (under load, 2-3 of 200 node loops declared, undeclared and closed by hand).
    A callback holding its object (a node loop, a worker daemon or its runs, a coordinator) then
    held the object's session in a cycle through Zenoh that no garbage collection sees, and with
    it the session's shared-memory segment, which outlived the process in /dev/shm (Zenoh's
    exit() skips a segment still mapped)."""
    ref = weakref.WeakMethod(method)

    def call(arg: Any) -> None:
        bound = ref()
        if bound is not None:
            bound(*leading, arg)

    return call
