"""The worker daemon (``retriever worker``, also ``retriever-worker``):

    core.py    the daemon: its settings, who may join, its allowlist, its answers, listing daemons
    runs.py    what it runs for a coordinator: a run's spec and its worker processes
"""

from ....errors import WorkerError
from .core import (ALWAYS_ALLOWED, CLOCK_SAMPLES, CODE_MISMATCH, CONFIG_KEYS, DEFAULT_CONNECT, DEFAULT_LISTEN,
                   DEFAULT_NAMESPACE, DEFAULT_TLS_LISTEN, ENDPOINT, JOIN_S, LEASE_RANGE, QUERY_S, STOP_CHECK_S,
                   DaemonInfo, Listing, WorkerDaemon, WorkerSettings, ask, ask_whom, check_security, credentials,
                   describe, hlc_now_ns, in_session, list_workers, load_settings, module_allowed, name_taken,
                   no_router, open_access, path_modules, reap_stale_folders, refusal, serve)
from .runs import DaemonRuns

__all__ = [
    "ALWAYS_ALLOWED", "CLOCK_SAMPLES", "CODE_MISMATCH", "CONFIG_KEYS", "DEFAULT_CONNECT", "DEFAULT_LISTEN",
    "DEFAULT_NAMESPACE", "DEFAULT_TLS_LISTEN", "ENDPOINT", "JOIN_S", "LEASE_RANGE", "QUERY_S", "STOP_CHECK_S",
    "DaemonInfo", "DaemonRuns", "Listing", "WorkerDaemon", "WorkerError", "WorkerSettings", "ask", "ask_whom",
    "check_security", "credentials", "describe", "hlc_now_ns", "in_session", "list_workers", "load_settings",
    "module_allowed", "name_taken", "no_router", "open_access", "path_modules", "reap_stale_folders", "refusal",
    "serve",
]
