"""The worker daemon (``retriever worker``, also ``retriever-worker``): a long-lived process on each
machine flows may run on, which a deployment's coordinator asks to run its nodes (docs/deploy.md).

    retriever worker --name NAME [--config worker.toml] (--secret FILE | --insecure)
        │ its settings: the flags over the file, every problem said at once
        │ no secret and no --insecure? refuse to start
        │ join the namespace: a Zenoh peer (--listen, --connect), or a client of routers (--router;
        │ with --local-router each run's flows join a router process of the run's here, linked to those)
        │ a daemon of its name live in the namespace already? refuse
        │ declare ctl/<name>, its control queryable; then workers/<name>, its liveliness token
        ▼ answer until SIGINT or SIGTERM; what it still runs stops with it

    ctl/<name> ─▶ WorkerDaemon.answer ─▶ a protocol.REQUEST ─┬─ info ─▶ InfoReply
      (Zenoh's threads, one lock)                            └─ prepare, spawn, signal, usage, end
                                                                 ─▶ DaemonRuns: a run's spec, its
                                                                    worker processes
    workers/<name>/events ◀─ DaemonRuns: what the run's processes print, and how they exit

A worker process it spawns is the embedded run's (``python -m retriever.backends.zenoh.worker``), a
child of the daemon. It imports flow classes only from the modules its allowlist admits, checked
before anything is imported. Who may talk to it: with ``--secret FILE`` its session admits only
peers that hold the secret (``access.py``: passwords derived from it for the namespace, access
control); without one it refuses to start unless ``--insecure`` says so (a lab on a trusted
network). A run's flows hold passwords of that run alone, derived here for its run id, and link
to the coordinator's hub and to each other, never to the daemon's session.

    settings.py    DaemonSettings: the flags over a worker.toml; the endpoints and namespace unless told
    security.py    who may join: a deployment secret, or --insecure; why an endpoint admitted no one
    allowlist.py   which modules a flow class may come from (--path, --allow)
    core.py        WorkerDaemon: its session, its token, its answers on ctl/<name>; ask, a daemon's answer
    runs.py        what it runs for a coordinator: a run's spec and its worker processes
    run_router.py  with --router and --local-router: a router of each run's here, its flows' (their edges stay here)
    router_process.py  that router's process (python -m), started and stopped with its run, gone with the daemon
    listing.py     retriever workers: the live daemons of a namespace, their info, their clocks' offsets
"""

from ....errors import WorkerError
from .allowlist import ALWAYS_ALLOWED, module_allowed, path_modules, refusal
from .core import JOIN_S, QUERY_S, STOP_CHECK_S, WorkerDaemon, ask, ask_whom, hlc_now_ns, in_session, name_taken, serve
from .listing import CLOCK_SAMPLES, DaemonInfo, Listing, describe, list_workers
from .runs import DaemonRuns
from .security import check_security, credentials, no_router, open_access, reap_stale_folders
from .settings import (CODE_MISMATCH, CONFIG_KEYS, DEFAULT_CONNECT, DEFAULT_LISTEN, DEFAULT_NAMESPACE,
                       DEFAULT_TLS_LISTEN, ENDPOINT, LEASE_RANGE, DaemonSettings, load_settings)

__all__ = [
    "ALWAYS_ALLOWED", "CLOCK_SAMPLES", "CODE_MISMATCH", "CONFIG_KEYS", "DEFAULT_CONNECT", "DEFAULT_LISTEN",
    "DEFAULT_NAMESPACE", "DEFAULT_TLS_LISTEN", "ENDPOINT", "JOIN_S", "LEASE_RANGE", "QUERY_S", "STOP_CHECK_S",
    "DaemonInfo", "DaemonRuns", "DaemonSettings", "Listing", "WorkerDaemon", "WorkerError", "ask", "ask_whom",
    "check_security", "credentials", "describe", "hlc_now_ns", "in_session", "list_workers", "load_settings",
    "module_allowed", "name_taken", "no_router", "open_access", "path_modules", "reap_stale_folders", "refusal",
    "serve",
]
