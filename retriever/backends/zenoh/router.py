"""A Zenoh router for deployments whose processes join as clients (``retriever router``).

A session in Zenoh's router mode forwards put/subscribe, queries and liveliness between its
clients (hub.client_config), and between its clients and those of the routers it links to.
Peers do not route for each other, through a router or not: only clients make a run of N
processes N links, with no address of a process reached from outside (a robot behind NAT).

Who may join, as for peers (access.py), from the deployment secret: the router's dictionary
holds, for each namespace it serves, that namespace's run user and watcher with the passwords
every holder of the secret derives (access.run_user, access.watch_user), and the user other
routers link as (access.ROUTER_USER). A session without them gets no link: in client mode its
``zenoh.open`` fails. Every link to a router is one it accepted, so it knows each one's user,
and its access control denies by default:

    retriever-run.NS     everything on retriever/NS/**, both ways
    retriever-watch.NS   on retriever/NS/**, only what access.py lets a watcher do (subscribe,
                         liveliness), and none of the run's control (ctl/**)
    retriever-router     everything on the served namespaces' keys

The far end of a link this router opens (``--connect``) is another router, whose user this
router cannot know (Zenoh authenticates the connecting side only): it is admitted by its Zenoh
id, asked of it at start (linked_router_ids). A linked router that restarts has another id: this
router must restart too.
"""

from __future__ import annotations

import errno
import json
import shutil
import signal
import socket
import sys
from collections.abc import Callable, Iterable
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import zenoh

from ...errors import AccessError, RouterError
from .access import ROUTER_USER, RunAccess, TlsFiles, read_secret, router_password, write_private
from .daemon import DEFAULT_NAMESPACE, LEASE_RANGE, credentials
from .folders import private_folder
from .hub import client_config, raise_open_file_limit
from .reach import why_no_session
from .routing import access_control, router_session_config
from .stopping import Stop
from .wire import check_chunk

#: the kind of private folder (folders.py) of a router's dictionary file
ROUTER_FOLDER = "retriever-router"
#: Zenoh's own port, on every interface, over TCP or TLS (as a worker daemon's)
DEFAULT_LISTEN = "tcp/0.0.0.0:7447"
DEFAULT_TLS_LISTEN = "tls/0.0.0.0:7447"
#: the sessions a router admits at once: each flow process, worker daemon and coordinator of
#: every deployment it serves is one (Zenoh's default, 1000, is five deployments of 200 flows)
MAX_SESSIONS = 10_000
#: how often the main thread wakes while it waits for SIGINT/SIGTERM (a signal is handled only
#: when the main thread runs)
STOP_CHECK_S = 0.5
#: how long a linked router is given to answer who it is
LINK_CHECK_S = 5.0


@dataclass(frozen=True)
class RouterSettings:
    secret: str  # the path of the deployment secret file
    namespaces: tuple[str, ...] = (DEFAULT_NAMESPACE,)
    listen: tuple[str, ...] = (DEFAULT_LISTEN,)
    connect: tuple[str, ...] = ()  # other routers to link to
    tls: TlsFiles | None = None
    lease: float | None = None  # seconds; None: Zenoh's (10 s)
    max_sessions: int = MAX_SESSIONS


def router_config(settings: RouterSettings, secret: bytes, dictionary_file: Path,
                  router_ids: Iterable[str] = ()) -> zenoh.Config:
    """The router's session config: router mode on ``settings.listen``, linked to
    ``settings.connect`` as ROUTER_USER, checking every link against ``dictionary_file``."""
    return router_session_config(
        listen=settings.listen, connect=settings.connect, user=ROUTER_USER, password=router_password(secret),
        dictionary_file=dictionary_file, access=access_control(settings.namespaces, router_ids), tls=settings.tls,
        lease=settings.lease, max_sessions=settings.max_sessions)


def check_settings(settings: RouterSettings) -> None:
    """Every problem with the settings Zenoh would report less clearly, at once."""
    problems = []
    for ns in settings.namespaces:
        try:
            check_chunk("namespace", ns)
        except ValueError as e:
            problems.append(str(e))
    for endpoint in (*settings.listen, *settings.connect):
        if _host_port(endpoint) is None:
            problems.append(f"{endpoint!r} is no endpoint: write tcp/HOST:PORT (or tls/HOST:PORT with TLS)")
    if settings.tls is not None:
        try:
            settings.tls.check_endpoints([*settings.listen, *settings.connect])
        except AccessError as e:
            problems.append(str(e))
    if settings.lease is not None and not LEASE_RANGE[0] <= settings.lease <= LEASE_RANGE[1]:
        problems.append(f"--lease must be seconds from {LEASE_RANGE[0]:g} to {LEASE_RANGE[1]:g}, got {settings.lease:g}")
    if settings.max_sessions < 1:
        problems.append(f"--max-sessions must be at least 1, got {settings.max_sessions}")
    if not settings.listen:
        problems.append("a router needs somewhere to listen: --listen tcp/0.0.0.0:7447")
    if problems:
        raise RouterError("\n".join(problems) if len(problems) == 1 else
                          "the router cannot start:\n" + "\n".join(f"  - {p}" for p in problems))
    for endpoint in settings.listen:
        _check_bindable(endpoint)


def _host_port(endpoint: str) -> tuple[str, int] | None:
    """``tcp/10.0.0.2:7447`` → ``("10.0.0.2", 7447)``; None for what is no TCP or TLS endpoint."""
    proto, _, rest = endpoint.partition("/")
    host, _, port = rest.split("#")[0].split("?")[0].rpartition(":")
    if proto not in ("tcp", "tls") or not host or not port.isdigit() or int(port) > 65535:
        return None
    return (host[1:-1] if host.startswith("[") else host), int(port)


def _check_bindable(endpoint: str) -> None:
    """Refuse a listen endpoint whose port is taken or whose address is not this machine's, by name."""
    host, port = _host_port(endpoint)
    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    with socket.socket(family, socket.SOCK_STREAM) as s:
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)  # as Zenoh does: TIME_WAIT is no obstacle
        try:
            s.bind((host, port))
        except OSError as e:
            raise RouterError(f"cannot listen on {endpoint}: {e.strerror}\n    hint: "
                              + (f"something else listens on port {port} (another router or worker?): "
                                 f"stop it, or choose another port with --listen"
                                 if e.errno == errno.EADDRINUSE else "listen on an address of this machine, "
                                 "or on all of them: --listen tcp/0.0.0.0:PORT")) from None


def linked_router_ids(settings: RouterSettings, secret: bytes) -> list[str]:
    """The Zenoh id of the router at each of ``settings.connect``, asked as one of its clients
    with the router's own credentials (see the module's docstring)."""
    proof = {"transport/auth/usrpwd": json.dumps({"user": ROUTER_USER, "password": router_password(secret)}),
                 **(settings.tls.session_config() if settings.tls else {})}
    ids = []
    for endpoint in settings.connect:
        try:
            with zenoh.open(client_config(connect=[endpoint], access=proof, shared_memory=False)) as session:
                ids += [str(z) for z in session.info.routers_zid()]
        except zenoh.ZError:
            raise RouterError(f"no router at {endpoint} admitted this one: "
                              f"{why_no_session(endpoint, credentials(settings.tls))}\n    hint: start that router first "
                              f"(with the same --secret), or leave out --connect {endpoint}") from None
    return ids


@contextmanager
def dictionary(settings: RouterSettings, secret: bytes):
    """The user:password file of every namespace served (mode 0600, in a private folder removed
    when this ends)."""
    folder = private_folder(ROUTER_FOLDER)
    try:
        lines = "".join(RunAccess.create(ns, secret).router_users(ns) for ns in settings.namespaces)
        yield write_private(folder / "zenoh-users.txt", lines + f"{ROUTER_USER}:{router_password(secret)}\n")
    finally:
        shutil.rmtree(folder, ignore_errors=True)


def serve(settings: RouterSettings, say: Callable[[str], None] | None = None) -> int:
    """Run the router until SIGINT or SIGTERM; 0 once its session closed."""
    say = say or (lambda line: print(line, file=sys.stderr, flush=True))
    check_settings(settings)
    secret = read_secret(settings.secret)
    stop = Stop(signal.SIGINT, signal.SIGTERM)
    raise_open_file_limit()  # room for every client, and for strangers' idle connections (hub.accept_pending)
    router_ids = linked_router_ids(settings, secret)
    with dictionary(settings, secret) as users:
        try:
            session = zenoh.open(router_config(settings, secret, users, router_ids))
        except zenoh.ZError as e:
            raise RouterError(f"the router cannot open its Zenoh session on {', '.join(settings.listen)}: {e}\n"
                              "    hint: is the port taken? choose another with --listen tcp/0.0.0.0:PORT") from None
        with session:
            say(start_line(settings))
            while not stop.wait(STOP_CHECK_S):
                pass
    say("retriever router stopped")
    return 0


def start_line(settings: RouterSettings) -> str:
    """What a started router says: where it listens, for which namespaces, linked to what."""
    line = (f"retriever router listening on {', '.join(settings.listen)} for namespace(s) "
            f"{', '.join(repr(ns) for ns in settings.namespaces)}")
    if settings.connect:
        line += f"; linked to {', '.join(settings.connect)}"
    return line + ("; mutual TLS" if settings.tls else "")
