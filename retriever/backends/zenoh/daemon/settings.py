"""A worker daemon's settings: its flags over a worker.toml (``retriever worker --config``), every
problem reported at once, one a line; the endpoints and namespace it uses unless told.
"""

from __future__ import annotations

import os
import re
import tomllib
from dataclasses import dataclass
from pathlib import Path

from ....errors import WorkerError
from ..access import AccessError, TlsFiles
from ..wire import KeySpace, check_chunk

DEFAULT_NAMESPACE = "default"
#: Zenoh's own port, on every interface: where a coordinator on another machine finds the worker
DEFAULT_LISTEN = "tcp/0.0.0.0:7447"
#: where ``retriever workers`` looks when told nowhere: a worker on this machine, at DEFAULT_LISTEN
DEFAULT_CONNECT = "tcp/127.0.0.1:7447"

CONFIG_KEYS = ("name", "labels", "listen", "connect", "namespace", "path", "allow", "secret", "insecure", "lease",
               "tls_ca", "tls_cert", "tls_key", "code_mismatch", "pass_env", "router", "local_router")
#: what a worker does with a node whose module's file here differs from the coordinator's (the
#: IR's sha256): refuse to run it (the default), or run it and warn
CODE_MISMATCH = ("refuse", "warn")
#: where a worker with TLS listens unless told: DEFAULT_LISTEN, over TLS
DEFAULT_TLS_LISTEN = "tls/0.0.0.0:7447"
#: the bounds of --lease, seconds: how long a link that went silent (a partition) is kept
LEASE_RANGE = (0.1, 3600.0)
#: what a Zenoh endpoint looks like (PROTOCOL/ADDRESS): checked in settings before Zenoh sees it
ENDPOINT = re.compile(r"[a-z0-9]+/\S+")


@dataclass(frozen=True)
class DaemonSettings:
    """A worker daemon's settings, as :func:`load_settings` read and checked them."""

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
    #: with ``router``: each run's flows join a router of the run's on this machine
    #: (run_router.py), linked to ``router``, so that their edges between each other stay here
    local_router: bool = False


def load_settings(config: str | os.PathLike | None = None, **flags) -> DaemonSettings:
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


def _validate(values: dict, problems: list[str]) -> DaemonSettings | None:
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
    local_router = values.get("local_router", False)
    if not isinstance(local_router, bool):
        problems.append(f"'local_router' must be true or false, got {local_router!r:.60}")
    elif local_router and not router:
        problems.append("--local-router links each run's router to the routers of --router: give --router ENDPOINT")
    elif local_router and secret is None:
        problems.append("--local-router admits each run's flows by the run's password, derived from the deployment "
                        "secret: give --secret FILE (not --insecure)")
    if problems:
        return None
    return DaemonSettings(name, labels, listen, connect, namespace, tuple(paths), strings("allow"),
                          None if secret is None else str(secret), insecure,
                          None if lease is None else float(lease), tls, code_mismatch, pass_env, router, local_router)


def _check_chunk(kind: str, value: object, problems: list[str]) -> None:
    try:
        check_chunk(kind, value)
    except ValueError as e:
        problems.append(str(e))
