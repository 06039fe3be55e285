"""Who may join a worker daemon's namespace: a deployment secret (access.py derives the namespace's
passwords from it, and its access control), or ``--insecure``; and why an endpoint admitted none.
The namespace's passwords are those of the daemons' control; each run's flows get passwords of
their run alone (runs.DaemonRuns.local_spec), with which they never link to a daemon.
"""

from __future__ import annotations

import shutil
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from ....errors import WorkerError
from ..access import AccessError, RunAccess, TlsFiles, read_secret
from ..folders import DAEMON_FOLDER, private_folder, reap_stale
from ..reach import why_no_session


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
