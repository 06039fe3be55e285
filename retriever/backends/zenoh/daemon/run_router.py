"""A worker daemon's router for one run (``retriever worker --router ENDPOINT --local-router``).

Through a remote router alone, two flows on one machine talk through it: every edge between them
goes out to the router and back, and stops while the machine is cut off from it. So a daemon with
``--local-router`` opens, for each run it prepares, a Zenoh session in router mode of its own,
listening on a free loopback port and linked to the upstream routers; the run's flows join it as
clients (runs.DaemonRuns.local_spec) in place of the remote router. Zenoh routes between routers:
an edge between two flows of this machine stays on it, an edge to another machine goes through
the upstream routers as before.

    flow ──┐                             ┌── flow (other machine)
    flow ──┴─ run router (127.0.0.1) ── upstream router ── coordinator, daemons
         this machine

Who may join, as strict as at the upstream router (router.py): its dictionary holds the run's own
password alone (access.RunAccess.create with the run id, derived here from the secret, as for
peers), under the namespace's run user, so a session without that run's password gets no link:
not another run's flows, not a holder of the namespace's passwords. Its access control denies by
default (routing.access_control): the run user everything on the namespace's keys; the upstream
routers, whose user it cannot learn (Zenoh authenticates the connecting side only), by their
Zenoh ids, which the daemon's own session is linked to. Upstream it proves what the daemon
proves: the namespace's run user and password; with TLS, its certificate on ``tls/`` links. Its
own listener is plain TCP on loopback: no other machine reaches it, and a process of this one
still needs the run's password.

One session per run, because Zenoh reads a router's dictionary once, when the session opens. It
closes with its run (runs.DaemonRuns._end), and when the daemon stops.
"""

from __future__ import annotations

import time
from pathlib import Path

import zenoh

from ..access import RunAccess, SessionDictionary, TlsFiles, run_user
from ..hub import LOOPBACK, endpoint, free_port
from ..routing import access_control, router_session_config
from ..wire import WireError

#: how long a new run router is given to link to an upstream router: a link takes one round trip
#: and the daemon's own session is linked already, so only a router that went away meets it
UPSTREAM_LINK_S = 5.0
#: the links a run router admits: its run's flow processes on this machine
MAX_RUN_SESSIONS = 1000
#: how often a new run router's links are looked at while it waits for its upstream one
LINK_POLL_S = 0.01


class RunRouter:
    """One run's router session (close it), and the endpoint its flows join it at."""

    def __init__(self, session: zenoh.Session, at: str):
        self.session, self.endpoint = session, at

    def close(self) -> None:
        self.session.close()


def open_run_router(namespace: str, secret: bytes, run_id: str, upstream: tuple[str, ...], upstream_ids: list[str],
                    folder: Path, tls: TlsFiles | None = None) -> RunRouter:
    """Run ``run_id``'s router: on a free loopback port, linked to the routers at ``upstream``
    (admitted by their Zenoh ids, ``upstream_ids``), admitting the run's password alone (see the
    module's docstring); ``folder``: the run's private folder, where the dictionary is written
    where the system has no memory file for it (access.SessionDictionary).

    Its upstream link keeps Zenoh's lease, as the flows' own links to a remote router do
    (runs.DaemonRuns.local_spec: the daemon's short one closes links that are merely slow)."""
    if not upstream_ids:  # its access control would admit no router: nothing would route
        raise WireError(f"run {run_id}: the worker has no link to its router ({', '.join(upstream)}) now, "
                        "so its router for the run would have none")
    run_password = RunAccess.create(namespace, secret, run=run_id).run_password
    own = RunAccess.create(namespace, secret)  # the daemon's: what the upstream routers admit
    dictionary = SessionDictionary(f"{run_user(namespace)}:{run_password}\n", folder / "zenoh-run-router-users.txt")
    at = endpoint(free_port(LOOPBACK))
    try:
        session = zenoh.open(router_session_config(
            listen=[at], connect=upstream, user=run_user(namespace), password=own.run_password,
            dictionary_file=dictionary.path, access=access_control([namespace], upstream_ids), tls=tls, lease=None,
            max_sessions=MAX_RUN_SESSIONS))
    except zenoh.ZError as e:
        raise WireError(f"run {run_id}: the worker's router for it cannot open on {at}: {e}") from None
    finally:
        dictionary.close()
    give_up = time.monotonic() + UPSTREAM_LINK_S
    while not set(upstream_ids) & {str(z) for z in session.info.routers_zid()}:
        if time.monotonic() > give_up:
            session.close()
            raise WireError(f"run {run_id}: the worker's router for it got no link to the upstream router "
                            f"({', '.join(upstream)}) within {UPSTREAM_LINK_S:g} s")
        time.sleep(LINK_POLL_S)
    return RunRouter(session, at)
