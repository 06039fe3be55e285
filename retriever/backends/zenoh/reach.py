"""Why an endpoint admitted no session: nothing listens there, it refuses new links, or it wants
other credentials.

Zenoh says only that it could not open a session. A session that listens takes a connection
into its handshake, where the connecting side proves a password (or a certificate), and closes
it unproven after its accept timeout; when more connections wait there than it admits, it
closes a new one at once, before a word of the handshake (hub.ACCEPT_TIMEOUT_S: a stranger who
holds idle connections to it). So a plain TCP connection that is not answered tells which:
closed at once, the endpoint refuses new links; held, it waits for credentials, and a session
that still did not open was refused them.
"""

from __future__ import annotations

import selectors
import socket

#: how long an unanswered probe waits to be closed: a session that refuses new links closes it
#: as soon as it accepted it, one that takes it into its handshake holds it for its accept timeout
PROBE_S = 1.0
#: probes sent at once: a place in the handshake freed just then may take one of them
PROBES = 3

NOTHING_LISTENS = "nothing listens there"
NO_ANSWER = "no answer (the address is not reached, or a firewall drops the connection)"
REFUSES_LINKS = ("it closes new connections at once: it refuses new links while too many connections wait in its "
                 "handshake (someone may be holding idle connections to it)")


def why_no_session(endpoint: str, credentials: str = "--secret") -> str:
    """What an endpoint (``tcp/HOST:PORT``, ``tls/...``) that admitted no session does with a
    connection: one of NOTHING_LISTENS, NO_ANSWER, REFUSES_LINKS, or that it wants other
    ``credentials`` than those given (it holds the connection, waiting for them)."""
    address = _address(endpoint)
    if address is None:
        return f"it wants another {credentials}, or nothing listens there"
    sockets, verdict = [], None
    try:
        for _ in range(PROBES):
            try:
                sockets.append(socket.create_connection(address, timeout=PROBE_S))
            except ConnectionRefusedError:
                return NOTHING_LISTENS
            except OSError:
                return NO_ANSWER
        with selectors.DefaultSelector() as selector:
            for s in sockets:
                selector.register(s, selectors.EVENT_READ)
            for key, _ in selector.select(PROBE_S):
                try:
                    closed = key.fileobj.recv(1) == b""
                except OSError:  # reset
                    closed = True
                if closed:
                    verdict = REFUSES_LINKS
    finally:
        for s in sockets:
            s.close()
    return verdict or f"it wants another {credentials}"


def _address(endpoint: str) -> tuple[str, int] | None:
    """``tcp/10.0.0.2:7447`` → ``("10.0.0.2", 7447)``; None for what is no TCP or TLS endpoint."""
    proto, _, rest = endpoint.partition("/")
    host, _, port = rest.split("#")[0].split("?")[0].rpartition(":")
    if proto not in ("tcp", "tls") or not host or not port.isdigit():
        return None
    host = host[1:-1] if host.startswith("[") and host.endswith("]") else host
    return host, int(port)
