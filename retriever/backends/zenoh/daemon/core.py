"""A worker daemon's core: its session in the namespace, its liveliness token, and its answers on
ctl/<name>. Under ``retriever/<namespace>/``::

    workers/<name>   its liveliness token: there while it runs (a killed daemon's goes in ms)
    ctl/<name>       its control queryable

A daemon joins a namespace with a Zenoh peer session (multicast scouting off, its own listen and
connect endpoints), or, with ``--router``, as a client of Zenoh routers, listening nowhere (its
flows too: runs.py), and stays until SIGINT or SIGTERM.

A control query carries a request (protocol.REQUEST: ``[2, op, {fields}]``) and gets one reply,
that op's reply record; an op it does not know, or a payload that is no request, gets
``reply_err`` with an ErrorReply and is counted, never fatal. Its ops (``WorkerDaemon.ops``):

    info    InfoRequest -> InfoReply {protocol, name, labels, host, pid, python, packages, clock_ns, nodes, counts}

and, for ``retriever deploy`` (the coordinator, remote.py), ``prepare``, ``spawn``, ``signal``,
``usage`` and ``end`` (runs.py), each taken, from a daemon with a secret, only sealed by the
coordinator with a key derived from the secret, and once (protocol/seal.py: a holder of the
namespace's passwords alone, or a replay of a captured request, is refused and counted): a worker imports flow classes only from the modules its allowlist admits
(allowlist.py: ``--path`` and ``--allow``), and refuses others with its refusal's message, before
anything is imported.
"""

from __future__ import annotations

import os
import platform
import signal
import socket
import sys
import threading
import traceback
from collections import Counter
from collections.abc import Callable

import zenoh

from ....errors import OtherProtocolError, WorkerError
from ....log.format import package_versions
from ..access import daemon_control_key, read_secret
from ..hub import (await_segments_released, client_config, mapped_segments, peer_config, raise_open_file_limit,
                   remove_orphaned_segments_at_exit, wait_for_peers, weak_callback)
from ..protocol import (PROTOCOL_VERSION, REQUEST, SEALED_OPS, DaemonOp, ErrorReply, InfoReply, InfoRequest,
                        OtherProtocolReply, Record, RequestOpener, decode_reply, error_message)
from ..stopping import Stop
from ..wire import KeySpace, WireError
from .allowlist import ALWAYS_ALLOWED, module_allowed, path_modules, refusal
from .runs import DaemonRuns
from .security import check_security, no_router, open_access
from .settings import DaemonSettings

#: how long a starting daemon waits for links to its --connect endpoints before it looks for a
#: worker of its name: a link takes milliseconds on a LAN; an endpoint down longer is joined later,
#: in the background (Zenoh retries), unchecked
JOIN_S = 3.0
#: a bound on an answer to a liveliness get or a control query: an answer is one round trip, far
#: shorter on any network a deployment spans, so only a worker that does not answer meets it
QUERY_S = 2.0
#: how often the main thread wakes while it waits for SIGINT/SIGTERM: a signal the kernel gives
#: one of Zenoh's threads runs our (main-thread) handler only when the main thread wakes
STOP_CHECK_S = 0.5


class WorkerDaemon:
    """The worker's answers on ctl/<name>, on Zenoh's threads (hence the lock)."""

    def __init__(self, settings: DaemonSettings, session: zenoh.Session):
        self.settings, self.session = settings, session
        self.keys = KeySpace(settings.namespace)
        #: what it counted: "refused" control messages (garbage, unknown ops), "failed" ops
        self.counts: Counter[str] = Counter()
        self._lock = threading.Lock()
        # read once: info answers at once, reading the clock last (a query measures its offset)
        self._packages = package_versions()
        #: what it runs for a coordinator (runs.py): prepare, spawn, signal, end
        secret = read_secret(settings.secret) if settings.secret is not None else None
        #: with a secret, every op but info is taken only sealed by a holder of it (seal.RequestOpener)
        self.requests = (RequestOpener(daemon_control_key(secret, settings.namespace))
                         if secret is not None else None)
        self.runs = DaemonRuns(session, settings.name, settings.namespace, listen=settings.listen, secret=secret,
                               allowed=self.module_allowed, refusal=self.refusal, paths=settings.path,
                               tls=settings.tls, lease=settings.lease, code_mismatch=settings.code_mismatch,
                               pass_env=settings.pass_env, router=settings.router,
                               local_router=settings.local_router)
        #: op -> handler(request) -> its reply
        self.ops: dict[DaemonOp, Callable[[Record], Record]] = {DaemonOp.INFO: self.info, **self.runs.ops}

    def info(self, request: InfoRequest) -> InfoReply:
        return InfoReply(protocol=PROTOCOL_VERSION, name=self.settings.name, labels=self.settings.labels,
                         host=socket.gethostname(), pid=os.getpid(), python=platform.python_version(),
                         packages=self._packages, clock_ns=hlc_now_ns(self.session),
                         nodes=tuple(self.runs.nodes()), counts=dict(self.counts))

    def module_allowed(self, module: str) -> bool:
        return module_allowed(module, list(self.settings.allow), list(self.settings.path))

    def refusal(self, module: str) -> str:
        return refusal(module, list(self.settings.allow), list(self.settings.path), self.settings.name)

    def answer(self, query: zenoh.Query) -> None:
        """The queryable's callback: one reply per query, never an exception into Zenoh. A
        request past protocol.MAX_REQUEST_BYTES is refused unread (an IR of hundreds of flows is
        well below it); with a secret, a SEALED_OPS request without the coordinator's seal, or one
        taken before, is refused before its op runs (seal.RequestOpener)."""
        try:
            payload = query.payload.to_bytes() if query.payload is not None else b""
            request = REQUEST.decode(payload, who=f"worker '{self.settings.name}'")
            if self.requests is not None and request.NAME in SEALED_OPS:
                self.requests.open(self.keys.ctl(self.settings.name), payload, query.attachment)
            with self._lock:
                reply = self.ops[request.NAME](request)
        except WireError as e:
            with self._lock:
                self.counts["refused"] += 1
            query.reply_err(ErrorReply(message=str(e)).encode())
            return
        except Exception as e:  # a bug in an op: the daemon stays up and says so
            with self._lock:
                self.counts["failed"] += 1
            traceback.print_exc()
            query.reply_err(ErrorReply(message=f"{type(e).__name__}: {e}").encode())
            return
        query.reply(self.keys.ctl(self.settings.name), reply.encode())


def hlc_now_ns(session: zenoh.Session) -> int:
    """The session's hybrid logical clock, now, in ns since the Unix epoch."""
    return session.new_timestamp().get_time_as_ntp64().as_nanos()


def ask(session: zenoh.Session, namespace: str, name: str, request: Record, timeout: float = QUERY_S) -> Record:
    """Send ``request`` to worker ``name`` and return its reply; WorkerError if it refused or said nothing."""
    return ask_whom(session, namespace, name, request, timeout)[0]


def ask_whom(session: zenoh.Session, namespace: str, name: str, request: Record,
             timeout: float = QUERY_S) -> tuple[Record, str | None]:
    """:func:`ask`, and the Zenoh id of the session that answered."""
    selector, op = KeySpace(namespace).ctl(name), request.NAME
    for reply in session.get(selector, payload=request.encode(), timeout=timeout):
        try:
            if reply.ok is not None:
                return (decode_reply(reply.ok.payload.to_bytes(), op),
                        None if reply.replier_id is None else str(reply.replier_id))
            message = error_message(reply.err.payload.to_bytes())
            if message is None:  # Zenoh's own error reply (the query timed out): no answer
                break
            raise WorkerError(f"worker '{name}' refused {op}: {message}")
        except OtherProtocolReply as e:
            raise OtherProtocolError(name, e, PROTOCOL_VERSION) from None
        except WireError as e:
            raise WorkerError(f"worker '{name}' answered {op} with no control message: {e}") from None
    raise WorkerError(f"worker '{name}' did not answer {op} within {timeout:g} s")


def serve(settings: DaemonSettings, say: Callable[[str], None] | None = None) -> int:
    """Run the daemon until SIGINT or SIGTERM; 0 once its session closed."""
    say = say or (lambda line: print(line, file=sys.stderr, flush=True))
    check_security(settings.secret, settings.insecure, "retriever-worker")
    stop = Stop(signal.SIGINT, signal.SIGTERM)
    if settings.insecure:
        say(f"warning: retriever-worker '{settings.name}' runs with --insecure: anyone who reaches "
            f"{', '.join(settings.listen or settings.router)} may join namespace '{settings.namespace}' and control it; "
            "only for a lab on a trusted network")
    raise_open_file_limit()  # room for strangers' idle connections beside its flows' pipes (hub.accept_pending)
    with open_access(settings.namespace, settings.secret, settings.tls, client=bool(settings.router)) as access:
        _serve_until(settings, stop, access, say)
    return 0


def _serve_until(settings: DaemonSettings, stop: Stop, access: dict[str, str] | None,
                 say: Callable[[str], None]) -> None:
    """Join, check the name is free, answer until ``stop``, close."""
    # a process that outlives the runs it serves keeps whatever pool it is sent through (hub.HUB_SHARED_MEMORY)
    if settings.router:
        config = client_config(connect=list(settings.router), access=access, lease=settings.lease,
                               shared_memory=False)
    else:
        config = peer_config(listen=settings.listen, connect=settings.connect, access=access, lease=settings.lease,
                             shared_memory=False)
    remove_orphaned_segments_at_exit()  # what its runs' workers leave
    try:
        taken, counts = in_session(config, lambda session: _announce_and_answer(settings, session, stop, say))
    except zenoh.ZError as e:
        if settings.router:
            raise WorkerError(no_router(f"retriever-worker '{settings.name}'", settings.router, settings.tls,
                                        settings.namespace)) from None
        raise WorkerError(f"retriever-worker '{settings.name}' cannot open its Zenoh session on "
                          f"{', '.join(settings.listen)}: {e}\n    hint: is the port taken? "
                          "choose another with --listen tcp/0.0.0.0:PORT") from None
    if taken is not None:
        raise WorkerError(taken)
    refused = counts.get("refused", 0)
    say(f"retriever-worker '{settings.name}' stopped"
        + (f"; it refused {refused} control message(s)" if refused else ""))


def in_session(config: zenoh.Config, use: Callable[[zenoh.Session], object]):
    """``use(session)`` in a session of its own, closed after, its shared-memory segments let go
    of: exit() removes only segments no one maps (hub.SEGMENT_RELEASE_S). ``use`` returns what
    went wrong rather than raise it: a traceback would hold the session."""
    before = mapped_segments()
    session = zenoh.open(config)
    segments = mapped_segments() - before  # the session's own
    try:
        with session:
            return use(session)
    finally:
        del session  # the last reference
        await_segments_released(segments)


def _announce_and_answer(settings: DaemonSettings, session: zenoh.Session, stop: Stop,
                         say: Callable[[str], None]) -> tuple[str | None, dict[str, int]]:
    """Unless a worker of its name runs (its refusal then), answer on ctl/<name> and hold the
    token until ``stop``; what it counted."""
    keys = KeySpace(settings.namespace)
    wait_for_peers(session, len(settings.connect), JOIN_S, stop=stop.is_set)
    taken = name_taken(session, settings.namespace, settings.name)
    if taken is not None:
        return taken, {}
    daemon = WorkerDaemon(settings, session)
    # the queryable before the token: whoever sees the worker can ask it at once
    queryable = session.declare_queryable(keys.ctl(settings.name), weak_callback(daemon.answer))
    token = session.liveliness().declare_token(keys.workers(settings.name))
    say(_start_line(settings))
    while not stop.wait(STOP_CHECK_S):
        pass
    token.undeclare()
    queryable.undeclare()
    daemon.runs.close()  # what it still runs stops with it
    return None, dict(daemon.counts)


def name_taken(session: zenoh.Session, namespace: str, name: str) -> str | None:
    """Why this worker may not start, if a worker of its name is live in the namespace (among
    the peers linked now); else None."""
    keys = KeySpace(namespace)
    if not any(r.ok is not None for r in session.liveliness().get(keys.workers(name), timeout=QUERY_S)):
        return None
    try:
        info = ask(session, namespace, name, InfoRequest())
        other = f"on host {info.host}, pid {info.pid}"
    except WorkerError as e:
        other = f"({e})"
    return (f"a worker named '{name}' already runs in namespace '{namespace}' {other}\n"
            f"    hint: pick another --name, or stop that worker first")


def _start_line(settings: DaemonSettings) -> str:
    allowed = [*ALWAYS_ALLOWED, *path_modules(list(settings.path)), *settings.allow]
    parts = [f"retriever-worker '{settings.name}' in namespace '{settings.namespace}'",
             f"joined through router {', '.join(settings.router)}"
             + ("; each run's flows through a router of the run's here" if settings.local_router else "")
             if settings.router else
             f"listening on {', '.join(settings.listen)}"]
    if settings.connect:
        parts.append(f"connecting to {', '.join(settings.connect)}")
    parts.append(f"labels {', '.join(settings.labels) or '(none)'}")
    parts.append(f"flows from {', '.join(allowed)}")
    if settings.code_mismatch == "warn":
        parts.append("code that differs from the coordinator's: warned of, run")
    return "; ".join(parts)
