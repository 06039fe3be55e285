"""``retriever workers``: the live worker daemons of a namespace, each with its info and its
clock's offset from ours (DaemonInfo), and the endpoints that admitted no session.
"""

from __future__ import annotations

from typing import NamedTuple

import zenoh

from ....errors import OtherProtocolError, WorkerError
from ..access import TlsFiles
from ..hub import peer_config
from ..protocol import InfoReply, InfoRequest
from ..reach import why_no_session
from ..wire import KeySpace
from .core import QUERY_S, ask_whom, hlc_now_ns, in_session
from .security import check_security, credentials, open_access
from .settings import DEFAULT_NAMESPACE

#: info queries per worker that measure its clock's offset: the first crosses a new route and is
#: much slower one way than the later ones, so one sample would misjudge the offset
CLOCK_SAMPLES = 5


class DaemonInfo(NamedTuple):
    """A worker daemon as :func:`describe` found it: what it said of itself, or why it said nothing."""

    name: str
    info: InfoReply | None  # its info reply, or None
    offset_ns: int | None  # its clock minus ours (NTP-style: theirs minus the midpoint of the query)
    error: str | None  # why there is no info
    zid: str | None = None  # the Zenoh id of the session that answered as it (remote.RemoteHost takes only its answers)
    #: a worker of another protocol version (no info then): that version, and the Retriever it runs
    other_protocol: tuple[int, str | None] | None = None


class Listing(NamedTuple):
    workers: list[DaemonInfo]
    unreachable: dict[str, str]  # endpoints that admitted no session, and why (reach.why_no_session)


def list_workers(connect: list[str], namespace: str = DEFAULT_NAMESPACE, secret: str | None = None,
                 insecure: bool = False, tls: TlsFiles | None = None, router: bool = False) -> Listing:
    """The live workers of ``namespace`` that the peers at ``connect`` know, each with its info.

    A client session per endpoint: the peer it joins routes for it, so it sees every worker
    that peer is linked to, not only itself. ``router``: the endpoints are Zenoh routers the
    workers joined (``retriever worker --router``), which know the namespace's users by name."""
    check_security(secret, insecure, "retriever workers")
    keys = KeySpace(namespace)
    found: dict[str, DaemonInfo] = {}
    unreachable = {}

    def look(session: zenoh.Session) -> None:
        for reply in session.liveliness().get(keys.workers(), timeout=QUERY_S):
            if reply.ok is not None:
                name = str(reply.ok.key_expr).rsplit("/", 1)[-1]
                found.setdefault(name, describe(session, namespace, name))

    with open_access(namespace, secret, tls, client=router) as access:
        for endpoint in connect:
            config = peer_config(connect=[endpoint], access=access)
            config.insert_json5("mode", '"client"')
            try:
                in_session(config, look)
            except zenoh.ZError:  # nothing listens there, it refuses new links, or it wants credentials we lack
                unreachable[endpoint] = why_no_session(endpoint, credentials(tls))
    return Listing(sorted(found.values()), unreachable)


def describe(session: zenoh.Session, namespace: str, name: str) -> DaemonInfo:
    """Worker ``name``'s info, and its clock's offset from ours, measured as NTP does: our HLC
    before and after a query brackets the worker's reading, so offset = theirs - midpoint, off by
    at most half the round trip; of CLOCK_SAMPLES queries, the one of shortest round trip counts."""
    samples = []
    for _ in range(CLOCK_SAMPLES):
        before = hlc_now_ns(session)
        try:
            info, zid = ask_whom(session, namespace, name, InfoRequest())
        except OtherProtocolError as e:
            return DaemonInfo(name, None, None, str(e), other_protocol=(e.protocol, e.retriever))
        except WorkerError as e:
            return DaemonInfo(name, None, None, str(e))
        after = hlc_now_ns(session)
        samples.append((after - before, before, after, info, zid))
    _, before, after, info, zid = min(samples, key=lambda sample: sample[0])
    return DaemonInfo(name, info, info.clock_ns - (before + after) // 2, None, zid)
