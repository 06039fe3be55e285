"""A long-lived worker daemon (``retriever-worker``), on each machine flows may run on.

A daemon joins a namespace with a Zenoh peer session (multicast scouting off, its own listen and
connect endpoints), or, with ``--router``, as a client of Zenoh routers, listening nowhere (its
flows too: runs.py), and stays until SIGINT or SIGTERM. Under ``retriever/<namespace>/``::

    workers/<name>   its liveliness token: there while it runs (a killed daemon's goes in ms)
    ctl/<name>       its control queryable

A control query carries a request (protocol.REQUEST: ``[2, op, {fields}]``) and gets one reply,
that op's reply record; an op it does not know, or a payload that is no request, gets
``reply_err`` with an ErrorReply and is counted, never fatal. Its ops (``WorkerDaemon.ops``):

    info    InfoRequest -> InfoReply {protocol, name, labels, host, pid, python, packages, clock_ns, nodes, counts}

and, for ``retriever deploy`` (the coordinator, remote.py), ``prepare``, ``spawn``, ``signal``,
``usage`` and ``end`` (runs.py): a worker imports flow classes only from the modules its allowlist admits
(:func:`module_allowed`; ``--path`` and ``--allow``), and refuses others with :func:`refusal`'s
message, before anything is imported.

Who may talk to it: with ``--secret FILE`` its session admits only peers that hold the secret
(``access.py``: passwords derived from it for the namespace, access control); without one it
refuses to start unless ``--insecure`` says so (a lab on a trusted network).
"""

from __future__ import annotations

import importlib.machinery
import os
import platform
import re
import shutil
import signal
import socket
import sys
import threading
import tomllib
import traceback
from collections import Counter
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from fnmatch import fnmatchcase
from pathlib import Path
from typing import NamedTuple

import zenoh

from ....errors import OtherProtocolError, WorkerError
from ....log.format import package_versions
from ..access import AccessError, RunAccess, TlsFiles, read_secret
from ..folders import DAEMON_FOLDER, private_folder, reap_stale
from ..hub import (await_segments_released, client_config, mapped_segments, peer_config, raise_open_file_limit,
                   remove_orphaned_segments_at_exit, wait_for_peers, weak_callback)
from ..protocol import (PROTOCOL_VERSION, REQUEST, DaemonOp, ErrorReply, InfoReply, InfoRequest, OtherProtocol,
                        Record, decode_reply, error_message)
from ..reach import why_no_session
from ..wire import KeySpace, WireError, check_chunk
from .runs import DaemonRuns

DEFAULT_NAMESPACE = "default"
#: Zenoh's own port, on every interface: where a coordinator on another machine finds the worker
DEFAULT_LISTEN = "tcp/0.0.0.0:7447"
#: where ``retriever workers`` looks when told nowhere: a worker on this machine, at DEFAULT_LISTEN
DEFAULT_CONNECT = "tcp/127.0.0.1:7447"
#: flow classes from these packages (and their modules) are always allowed: Retriever's own flows.
#: Not ``agents`` (Retriever-0): its flows act on the world outside the program (a planner that
#: sends the daemon's API key to a URL its parameters give), so a worker opts in: --allow agents
ALWAYS_ALLOWED = ("retriever",)

#: how long a starting daemon waits for links to its --connect endpoints before it looks for a
#: worker of its name: a link takes milliseconds on a LAN; an endpoint down longer is joined later,
#: in the background (Zenoh retries), unchecked
JOIN_S = 3.0
#: a bound on an answer to a liveliness get or a control query: an answer is one round trip, far
#: shorter on any network a deployment spans, so only a worker that does not answer meets it
QUERY_S = 2.0
#: info queries per worker that measure its clock's offset: the first crosses a new route and is
#: much slower one way than the later ones, so one sample would misjudge the offset
CLOCK_SAMPLES = 5
#: how often the main thread wakes while it waits for SIGINT/SIGTERM: a signal the kernel gives
#: one of Zenoh's threads runs our (main-thread) handler only when the main thread wakes
STOP_CHECK_S = 0.5

CONFIG_KEYS = ("name", "labels", "listen", "connect", "namespace", "path", "allow", "secret", "insecure", "lease",
               "tls_ca", "tls_cert", "tls_key", "code_mismatch", "pass_env", "router")
#: what a worker does with a node whose module's file here differs from the coordinator's (the
#: IR's sha256): refuse to run it (the default), or run it and warn
CODE_MISMATCH = ("refuse", "warn")
#: where a worker with TLS listens unless told: DEFAULT_LISTEN, over TLS
DEFAULT_TLS_LISTEN = "tls/0.0.0.0:7447"
#: the bounds of --lease, seconds: how long a link that went silent (a partition) is kept
LEASE_RANGE = (0.1, 3600.0)
#: what a Zenoh endpoint looks like (PROTOCOL/ADDRESS): checked in settings before Zenoh sees it
ENDPOINT = re.compile(r"[a-z0-9]+/\S+")


# ---------------------------------------------------------------------------------------------
# Settings: flags over a worker.toml
# ---------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class WorkerSettings:
    name: str
    labels: tuple[str, ...] = ()
    listen: tuple[str, ...] = (DEFAULT_LISTEN,)
    connect: tuple[str, ...] = ()
    namespace: str = DEFAULT_NAMESPACE
    path: tuple[str, ...] = ()
    allow: tuple[str, ...] = ()
    secret: str | None = None
    insecure: bool = False
    lease: float | None = None  # seconds; None: Zenoh's (10 s)
    tls: TlsFiles | None = None  # mutual TLS on every link (access.TlsFiles)
    code_mismatch: str = "refuse"  # CODE_MISMATCH
    pass_env: tuple[str, ...] = ()  # environment variables flow processes get beyond runs.PASSED_ENV
    #: the Zenoh routers it joins through, as a client listening nowhere (router.py), its flows
    #: too; none: a peer on ``listen`` and ``connect``
    router: tuple[str, ...] = ()


def load_settings(config: str | os.PathLike | None = None, **flags) -> WorkerSettings:
    """A worker's settings: ``flags`` (CONFIG_KEYS; None = not given) over the TOML file
    ``config``, whose relative paths are relative to its folder. Every problem is reported at
    once, one a line."""
    problems: list[str] = []
    values = _read_config(Path(config), problems) if config is not None else {}
    if flags.get("secret") is not None or flags.get("insecure"):
        values.pop("secret", None)  # a flag's choice of security replaces the file's
        values.pop("insecure", None)
    values.update({k: v for k, v in flags.items() if v is not None and v is not False})
    if isinstance(values.get("labels"), str):
        values["labels"] = [label.strip() for label in values["labels"].split(",") if label.strip()]
    settings = _validate(values, problems)
    if problems:
        raise WorkerError("the worker's settings have problems:\n" + "\n".join(f"  - {p}" for p in problems))
    return settings


def _read_config(path: Path, problems: list[str]) -> dict:
    try:
        with path.open("rb") as f:
            values = tomllib.load(f)
    except OSError as e:
        raise WorkerError(f"cannot read the worker config {path}: {e.strerror}") from None
    except UnicodeDecodeError as e:
        raise WorkerError(f"the worker config {path} is not text: TOML is UTF-8, byte {e.start} is "
                          f"{e.object[e.start:e.start + 1]!r}\n"
                          f"    hint: --config takes a worker.toml (name = \"...\", connect = [...])") from None
    except tomllib.TOMLDecodeError as e:
        raise WorkerError(f"the worker config {path} is not valid TOML: {e}") from None
    for key in sorted(set(values) - set(CONFIG_KEYS)):
        problems.append(f"{path}: unknown key '{key}' (a worker config has {', '.join(CONFIG_KEYS)})")
        del values[key]
    for key in ("path", "secret", "tls_ca", "tls_cert", "tls_key"):  # relative to the file, wherever it starts
        if isinstance(values.get(key), list):
            values[key] = [str(path.parent / p) if isinstance(p, str) else p for p in values[key]]
        elif isinstance(values.get(key), str):
            values[key] = str(path.parent / values[key])
    return values


def _validate(values: dict, problems: list[str]) -> WorkerSettings | None:
    def strings(key: str) -> tuple[str, ...]:
        value = values.get(key, ())
        value = [value] if isinstance(value, str) else value
        if not isinstance(value, (list, tuple)) or not all(isinstance(v, str) for v in value):
            problems.append(f"'{key}' must be a list of strings, got {value!r:.60}")
            return ()
        return tuple(value)

    name, namespace = values.get("name"), values.get("namespace", DEFAULT_NAMESPACE)
    if name is None:
        problems.append('a worker needs a name: --name NAME (or name = "..." in --config)')
    elif name in KeySpace.COORDINATOR_CONTROL:
        problems.append(f"a worker may not be named '{name}': ctl/{name} is a run's own key; pick another --name")
    else:
        _check_chunk("worker name", name, problems)
    _check_chunk("namespace", namespace, problems)
    labels = strings("labels")
    for label in labels:
        _check_chunk("label", label, problems)
    try:
        tls = TlsFiles.of(values.get("tls_ca"), values.get("tls_cert"), values.get("tls_key"))
    except AccessError as e:
        problems.append(str(e))
        tls = None
    router = strings("router")
    if router and (values.get("listen") or values.get("connect")):
        problems.append("a worker joined through a router (--router) listens nowhere and connects to the router "
                        "alone: leave out --listen and --connect")
    listen = () if router else strings("listen") or ((DEFAULT_TLS_LISTEN if tls else DEFAULT_LISTEN),)
    connect = () if router else strings("connect")
    if tls is not None:
        try:
            tls.check_endpoints([*listen, *connect, *router])
        except AccessError as e:
            problems.append(str(e))
    for endpoint in (*listen, *connect, *router):
        if not ENDPOINT.fullmatch(endpoint):
            problems.append(f"endpoint {endpoint!r} is no Zenoh endpoint: write PROTOCOL/ADDRESS, "
                            "e.g. tcp/0.0.0.0:7447")
    paths = []
    for given in strings("path"):
        paths.append(str(Path(given).resolve()))
        if not Path(given).is_dir():
            problems.append(f"--path {given}: no such directory")
    secret, insecure = values.get("secret"), values.get("insecure", False)
    if secret is not None and not isinstance(secret, (str, os.PathLike)):
        problems.append(f"'secret' must be the path of a file, got {secret!r:.60}")
    if not isinstance(insecure, bool):
        problems.append(f"'insecure' must be true or false, got {insecure!r:.60}")
    lease = values.get("lease")
    if lease is not None and (type(lease) not in (int, float) or not LEASE_RANGE[0] <= lease <= LEASE_RANGE[1]):
        problems.append(f"'lease' must be seconds from {LEASE_RANGE[0]:g} to {LEASE_RANGE[1]:g}, got {lease!r:.60}")
    code_mismatch = values.get("code_mismatch", "refuse")
    if code_mismatch not in CODE_MISMATCH:
        problems.append(f"'code_mismatch' must be one of {', '.join(CODE_MISMATCH)}, got {code_mismatch!r:.60}")
    pass_env = strings("pass_env")
    for variable in pass_env:
        if not re.fullmatch(r"[A-Za-z_][A-Za-z0-9_]*", variable):
            problems.append(f"'pass_env' names environment variables, got {variable!r:.60}")
    if problems:
        return None
    return WorkerSettings(name, labels, listen, connect, namespace, tuple(paths), strings("allow"),
                          None if secret is None else str(secret), insecure,
                          None if lease is None else float(lease), tls, code_mismatch, pass_env, router)


def _check_chunk(kind: str, value: object, problems: list[str]) -> None:
    try:
        check_chunk(kind, value)
    except ValueError as e:
        problems.append(str(e))


# ---------------------------------------------------------------------------------------------
# Who may join: a deployment secret, or --insecure
# ---------------------------------------------------------------------------------------------
def check_security(secret: object, insecure: bool, command: str) -> None:
    """Refuse to join without a secret unless ``--insecure`` says that is meant."""
    if secret is not None and insecure:
        raise WorkerError(f"{command} takes --secret FILE or --insecure, not both")
    if secret is None and not insecure:
        raise WorkerError(
            f"{command} needs --secret FILE (a deployment secret: only processes holding it may join) "
            "or --insecure (anyone who reaches its endpoints may)\n"
            "    hint: retriever secret new lab.key, copy it privately to every machine, and pass "
            "--secret lab.key to every worker and coordinator")


@contextmanager
def open_access(namespace: str, secret: str | None, tls: TlsFiles | None = None, client: bool = False
                ) -> Iterator[dict[str, str] | None]:
    """The Zenoh config entries that make a session one of the namespace's deployment, derived
    from the secret (access.py), with ``tls`` mutual TLS on its links, or None without either.
    The dictionary file Zenoh checks peers against lives in a private (0700) folder, removed
    when this ends. ``client``: those of a client of a router, which proves the namespace's
    password and checks no one (RunAccess.client_config): no file."""
    links = tls.session_config() if tls is not None else {}
    if secret is None:
        yield links or None
        return
    try:
        access = RunAccess.create(namespace, read_secret(secret))
    except AccessError as e:
        raise WorkerError(str(e)) from None
    if client:
        yield {**access.client_config(namespace), **links}
        return
    folder = private_folder(DAEMON_FOLDER)  # the stale ones of daemons gone reaped first
    try:
        yield {**access.session_config(access.write_dictionary(folder)), **links}
    finally:
        shutil.rmtree(folder, ignore_errors=True)


def reap_stale_folders() -> list[Path]:
    """Remove this user's ``retriever-worker-PID-*`` folders (Zenoh's password file of a daemon,
    and the run folders it prepared: specs with the runs' passwords) whose daemon is gone: a
    SIGKILLed one could not remove its own. Those removed."""
    return reap_stale(DAEMON_FOLDER)


# ---------------------------------------------------------------------------------------------
# The allowlist: which modules a flow class may come from
# ---------------------------------------------------------------------------------------------
def path_modules(paths: list[str]) -> list[str]:
    """The top-level modules and regular packages in the folders ``paths``: the names whose import
    finds them there. Not a folder without ``__init__.py`` (a namespace package: any regular
    package of its name elsewhere, ``venv`` or ``test`` in the standard library, is imported
    first), nor a name the interpreter imports before looking in any folder (built-in or frozen:
    ``sys``, ``os``)."""
    suffixes = sorted(importlib.machinery.all_suffixes(), key=len, reverse=True)
    found = set()
    for folder in paths:
        try:
            entries = list(os.scandir(folder))
        except OSError:
            continue
        for entry in entries:
            if entry.is_dir():
                stem = entry.name if os.path.isfile(os.path.join(entry.path, "__init__.py")) else ""
            else:
                stem = next((entry.name[:-len(s)] for s in suffixes if entry.name.endswith(s)), "")
            if stem.isidentifier() and not stem.startswith("__") and not _imported_first(stem):
                found.add(stem)  # (not __init__, __pycache__)
    return sorted(found)


def _imported_first(name: str) -> bool:
    """Whether ``name`` is a built-in or frozen module, which no folder on the path can provide."""
    return name in sys.builtin_module_names or importlib.machinery.FrozenImporter.find_spec(name) is not None


def module_allowed(module: str, allow: list[str], paths: list[str]) -> bool:
    """Whether a flow class may be imported from ``module``: the module or a package holding it
    is in ALWAYS_ALLOWED, found in a ``paths`` folder, or matches an ``allow`` pattern (fnmatch,
    case-sensitive: ``mylab.*``)."""
    parts = module.split(".") if isinstance(module, str) else [""]
    if not all(part.isidentifier() and not (part.startswith("__") and part.endswith("__")) for part in parts):
        return False  # a dunder part (pkg.__main__) is a package's command line, not a module of flows
    patterns = [*ALWAYS_ALLOWED, *path_modules(paths), *allow]
    prefixes = [".".join(parts[:i]) for i in range(1, len(parts) + 1)]
    return any(fnmatchcase(prefix, pattern) for prefix in prefixes for pattern in patterns)


def refusal(module: str, allow: list[str], paths: list[str], worker: str | None = None) -> str:
    """Why a flow class from ``module`` is refused, and the flag that would allow it."""
    who = f"worker '{worker}'" if worker else "this worker"
    admitted = [f"{', '.join(ALWAYS_ALLOWED)} (always)"]
    if paths:
        admitted.append(f"modules in --path {' '.join(paths)}: {', '.join(path_modules(paths)) or 'none'}")
    if allow:
        admitted.append(f"--allow {' '.join(allow)}")
    top = module.split(".")[0]
    return (f"{who} does not import flow classes from module '{module}': its allowlist admits "
            f"{'; '.join(admitted)}\n"
            f"    hint: start the worker with --allow {module}, or with --path DIR for the folder holding {top}")


# ---------------------------------------------------------------------------------------------
# The daemon
# ---------------------------------------------------------------------------------------------
class WorkerDaemon:
    """The worker's answers on ctl/<name>, on Zenoh's threads (hence the lock)."""

    def __init__(self, settings: WorkerSettings, session: zenoh.Session):
        self.settings, self.session = settings, session
        self.keys = KeySpace(settings.namespace)
        #: what it counted: "refused" control messages (garbage, unknown ops), "failed" ops
        self.counts: Counter[str] = Counter()
        self._lock = threading.Lock()
        # read once: info answers at once, reading the clock last (a query measures its offset)
        self._packages = package_versions()
        #: what it runs for a coordinator (runs.py): prepare, spawn, signal, end
        self.runs = DaemonRuns(session, settings.name, settings.namespace, listen=settings.listen,
                               access=RunAccess.create(settings.namespace, read_secret(settings.secret))
                               if settings.secret is not None else None,
                               allowed=self.module_allowed, refusal=self.refusal, paths=settings.path,
                               tls=settings.tls, lease=settings.lease, code_mismatch=settings.code_mismatch,
                               pass_env=settings.pass_env, router=settings.router)
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
        well below it)."""
        try:
            request = REQUEST.decode(query.payload.to_bytes() if query.payload is not None else b"",
                                     who=f"worker '{self.settings.name}'")
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
        except OtherProtocol as e:
            raise OtherProtocolError(name, e, PROTOCOL_VERSION) from None
        except WireError as e:
            raise WorkerError(f"worker '{name}' answered {op} with no control message: {e}") from None
    raise WorkerError(f"worker '{name}' did not answer {op} within {timeout:g} s")


def serve(settings: WorkerSettings, say: Callable[[str], None] | None = None) -> int:
    """Run the daemon until SIGINT or SIGTERM; 0 once its session closed."""
    say = say or (lambda line: print(line, file=sys.stderr, flush=True))
    check_security(settings.secret, settings.insecure, "retriever-worker")
    stop = threading.Event()
    for signum in (signal.SIGINT, signal.SIGTERM):
        signal.signal(signum, lambda *_: stop.set())
    if settings.insecure:
        say(f"warning: retriever-worker '{settings.name}' runs with --insecure: anyone who reaches "
            f"{', '.join(settings.listen or settings.router)} may join namespace '{settings.namespace}' and control it; "
            "only for a lab on a trusted network")
    raise_open_file_limit()  # room for strangers' idle connections beside its flows' pipes (hub.accept_pending)
    with open_access(settings.namespace, settings.secret, settings.tls, client=bool(settings.router)) as access:
        _serve_until(settings, stop, access, say)
    return 0


def _serve_until(settings: WorkerSettings, stop: threading.Event, access: dict[str, str] | None,
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


def _announce_and_answer(settings: WorkerSettings, session: zenoh.Session, stop: threading.Event,
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


def _start_line(settings: WorkerSettings) -> str:
    allowed = [*ALWAYS_ALLOWED, *path_modules(list(settings.path)), *settings.allow]
    parts = [f"retriever-worker '{settings.name}' in namespace '{settings.namespace}'",
             f"joined through router {', '.join(settings.router)}" if settings.router else
             f"listening on {', '.join(settings.listen)}"]
    if settings.connect:
        parts.append(f"connecting to {', '.join(settings.connect)}")
    parts.append(f"labels {', '.join(settings.labels) or '(none)'}")
    parts.append(f"flows from {', '.join(allowed)}")
    if settings.code_mismatch == "warn":
        parts.append("code that differs from the coordinator's: warned of, run")
    return "; ".join(parts)


# ---------------------------------------------------------------------------------------------
# Listing: retriever workers
# ---------------------------------------------------------------------------------------------
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


def no_router(who: str, routers, tls: TlsFiles | None, namespace: str) -> str:
    """Why no router at ``routers`` admitted ``who`` (a client of ``namespace``), and what to do."""
    why = (why_no_session(routers[0], credentials(tls)) if len(routers) == 1 else
           "; ".join(f"{r}: {why_no_session(r, credentials(tls))}" for r in routers))
    return (f"{who} found no router that admits it at {', '.join(routers)}: {why}\n    hint: start one there "
            f"(retriever router --listen {routers[0]} --secret FILE --namespace {namespace}) with the same secret "
            "file, serving this namespace")


def credentials(tls: TlsFiles | None) -> str:
    """What a session that admitted none may want instead of what it was given (reach.why_no_session)."""
    return "--secret or a certificate of another CA" if tls is not None else "--secret"


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
