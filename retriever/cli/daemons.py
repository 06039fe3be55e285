"""The long-lived processes a deployment runs on, and its secret: ``worker`` (a worker daemon,
also ``retriever-worker``), ``router`` (a Zenoh router deployments join through) and ``secret
new``."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Optional

import typer

from . import console
from .console import fail
from .options import INSECURE_HELP, SECRET_HELP, TLS_CA_OPTION, TLS_CERT_OPTION, TLS_KEY_OPTION, tls_files


def worker(
    name: Annotated[Optional[str], typer.Option(help="This worker's name, unique in its namespace.")] = None,
    labels: Annotated[Optional[str], typer.Option(metavar="A,B", help="Labels placement may ask for.")] = None,
    listen: Annotated[Optional[list[str]], typer.Option(
        metavar="ENDPOINT", help="Listen here (repeatable). Default: tcp/0.0.0.0:7447.")] = None,
    connect: Annotated[Optional[list[str]], typer.Option(metavar="ENDPOINT", help="Connect here (repeatable).")] = None,
    router: Annotated[Optional[list[str]], typer.Option(
        metavar="ENDPOINT", help="Join through the Zenoh router there (retriever router) as a client listening "
                                 "nowhere, its flows too (repeatable); instead of --listen and --connect.")] = None,
    local_router: Annotated[bool, typer.Option(
        "--local-router", help="With --router: each run's flows join a router of the run's on this machine, linked to "
                               "--router, so that edges between them stay on this machine.")] = False,
    namespace: Annotated[Optional[str], typer.Option(help="The deployment's namespace (default: default).")] = None,
    path: Annotated[Optional[list[Path]], typer.Option(
        metavar="DIR", help="A folder flows are imported from; its modules are allowed (repeatable).")] = None,
    allow: Annotated[Optional[list[str]], typer.Option(
        metavar="MODULE_PATTERN",
        help="Also allow flow classes from modules matching this (fnmatch; repeatable).")] = None,
    secret: Annotated[Optional[Path], typer.Option(metavar="FILE", help=SECRET_HELP)] = None,
    insecure: Annotated[bool, typer.Option("--insecure", help=INSECURE_HELP)] = False,
    config: Annotated[Optional[Path], typer.Option(
        metavar="worker.toml", help="Settings from this TOML file (the same keys); flags override it.")] = None,
    lease: Annotated[Optional[float], typer.Option(
        metavar="SECONDS", help="How long a link that went silent (a partition) is kept: Zenoh's lease "
                                "(default 10; under about 3 s, a congested link's close can drop healthy links, "
                                "docs/deploy.md). A coordinator cut off for this long has its flows stopped.")] = None,
    tls_ca: Annotated[Optional[Path], TLS_CA_OPTION] = None,
    tls_cert: Annotated[Optional[Path], TLS_CERT_OPTION] = None,
    tls_key: Annotated[Optional[Path], TLS_KEY_OPTION] = None,
    code_mismatch: Annotated[Optional[str], typer.Option(
        metavar="refuse|warn", help="A node whose module's file here differs from the coordinator's (the sha256 "
                                    "its IR records): refuse to run it (default), or warn and run it.")] = None,
    pass_env: Annotated[Optional[list[str]], typer.Option(
        "--pass-env", metavar="NAME", help="Give flow processes this environment variable too (repeatable; they get "
                                           "the locale, paths and libraries' settings, no credential, unless told: "
                                           "--pass-env OPENAI_API_KEY).")] = None,
) -> None:
    """Run a long-lived worker daemon that coordinators (retriever deploy) place flows on, until
    SIGINT or SIGTERM. Flow classes come only from retriever, the --path folders' modules and
    --allow patterns (--allow agents for Retriever-0)."""
    from ..backends.zenoh.daemon import load_settings, serve

    try:
        settings = load_settings(config, name=name, labels=labels, listen=listen, connect=connect, router=router,
                                 local_router=local_router,
                                 namespace=namespace, path=[str(p) for p in path] if path else None,
                                 allow=allow, secret=None if secret is None else str(secret), insecure=insecure,
                                 lease=lease, code_mismatch=code_mismatch, pass_env=pass_env,
                                 **{k: None if v is None else str(v) for k, v in
                                    (("tls_ca", tls_ca), ("tls_cert", tls_cert), ("tls_key", tls_key))})
        code = serve(settings)
    except Exception as exc:
        fail(exc)
    raise typer.Exit(code=code)


def router_command(
    secret: Annotated[Optional[Path], typer.Option(metavar="FILE", help=SECRET_HELP)] = None,
    listen: Annotated[Optional[list[str]], typer.Option(
        metavar="ENDPOINT", help="Listen here (repeatable). Default: tcp/0.0.0.0:7447 (tls/0.0.0.0:7447 with TLS).")] = None,
    namespace: Annotated[Optional[list[str]], typer.Option(
        metavar="NS", help="A namespace whose deployments may join (repeatable). Default: default.")] = None,
    connect: Annotated[Optional[list[str]], typer.Option(
        metavar="ENDPOINT", help="Link to the router there (repeatable), proving the same secret; it must be up.")] = None,
    lease: Annotated[Optional[float], typer.Option(
        metavar="SECONDS", help="How long a link that went silent (a partition) is kept: Zenoh's lease (default 10).")
    ] = None,
    max_sessions: Annotated[Optional[int], typer.Option(
        metavar="N", help="The most sessions (flow processes, workers, coordinators) it admits at once "
                          "(default 10000).")] = None,
    tls_ca: Annotated[Optional[Path], TLS_CA_OPTION] = None,
    tls_cert: Annotated[Optional[Path], TLS_CERT_OPTION] = None,
    tls_key: Annotated[Optional[Path], TLS_KEY_OPTION] = None,
) -> None:
    """Run a Zenoh router that deployments of the given namespaces join through, as clients,
    until SIGINT or SIGTERM: only holders of the secret get a link, and each namespace's
    sessions reach only that namespace's keys."""
    from ..backends.zenoh.daemon import DEFAULT_NAMESPACE
    from ..backends.zenoh.router import (DEFAULT_LISTEN, DEFAULT_TLS_LISTEN, MAX_SESSIONS, RouterError,
                                        RouterSettings, serve)

    tls = tls_files(tls_ca, tls_cert, tls_key)
    try:
        if secret is None:
            raise RouterError("retriever router needs --secret FILE: the deployment secret whose holders it admits\n"
                              "    hint: retriever secret new lab.key, and pass the same file to the router, "
                              "the workers and the coordinator")
        settings = RouterSettings(secret=str(secret), namespaces=tuple(namespace or (DEFAULT_NAMESPACE,)),
                                  listen=tuple(listen or ((DEFAULT_TLS_LISTEN if tls else DEFAULT_LISTEN),)),
                                  connect=tuple(connect or ()), tls=tls, lease=lease,
                                  max_sessions=MAX_SESSIONS if max_sessions is None else max_sessions)
        code = serve(settings)
    except Exception as exc:
        fail(exc)
    raise typer.Exit(code=code)


def secret_new(
    path: Annotated[Path, typer.Argument(metavar="FILE", help="Where to write the secret, e.g. lab.key.")],
    force: Annotated[bool, typer.Option("--force", help="Replace FILE if it exists.")] = False,
) -> None:
    """Write a fresh deployment secret (random, mode 0600) for retriever run --secret FILE."""
    from ..backends.zenoh.access import SECRET_NEW_BYTES, new_secret

    try:
        new_secret(path, overwrite=force)
    except Exception as exc:
        fail(exc)
    console.out.print(f"wrote a new deployment secret to {path} ({SECRET_NEW_BYTES} random bytes as hex text, "
                      f"mode 600)\n"
                      f"  use it: retriever run SCRIPT.py --backend zenoh --secret {path} [--namespace NS]  "
                      f"(in Python: pipe.run(backend=\"zenoh\", secret=\"{path}\"))\n"
                      f"  every machine of the deployment needs this same file: copy it privately (scp; never a "
                      f"chat or a repository) and keep it mode 600", highlight=False, soft_wrap=True)
