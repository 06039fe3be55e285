"""The commands that ask a namespace what runs there, from any machine: ``workers`` (its live
worker daemons), ``status`` and ``stop`` (its running deployment)."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Optional

import typer
from rich.table import Table
from rich.text import Text

from ..errors import RetrieverError
from . import console
from .console import cell, fail, visible
from .options import INSECURE_HELP, SECRET_HELP, TLS_CA_OPTION, TLS_CERT_OPTION, TLS_KEY_OPTION, tls_files


# the options every command that joins a namespace takes (workers, status, stop)
_Secret = Annotated[Optional[Path], typer.Option(metavar="FILE", help=SECRET_HELP)]
_Insecure = Annotated[bool, typer.Option("--insecure", help=INSECURE_HELP)]
_TlsCa = Annotated[Optional[Path], TLS_CA_OPTION]
_TlsCert = Annotated[Optional[Path], TLS_CERT_OPTION]
_TlsKey = Annotated[Optional[Path], TLS_KEY_OPTION]
_Namespace = Annotated[str, typer.Option(help="The deployment's namespace.")]
_Through = Annotated[Optional[list[str]], typer.Option(
    metavar="ENDPOINT", help="A worker of the deployment to ask through (repeatable). Default: tcp/127.0.0.1:7447.")]
_Router = Annotated[Optional[list[str]], typer.Option(
    metavar="ENDPOINT", help="Ask through the Zenoh router the deployment joined (retriever deploy --router; "
                             "repeatable), instead of --connect.")]


def workers_command(
    connect: Annotated[Optional[list[str]], typer.Option(
        metavar="ENDPOINT", help="A worker (or a peer linked to workers) to ask (repeatable). "
                                 "Default: tcp/127.0.0.1:7447.")] = None,
    namespace: _Namespace = "default", secret: _Secret = None, insecure: _Insecure = False,
    tls_ca: _TlsCa = None, tls_cert: _TlsCert = None, tls_key: _TlsKey = None, router: _Router = None,
) -> None:
    """List the live workers of a namespace: labels, host, pid, version, clock offset, nodes.
    Exits 1 when it found none (nothing listens, another --secret, or no worker is up)."""
    from ..backends.zenoh.daemon import list_workers

    endpoints = through(connect, router)
    tls = tls_files(tls_ca, tls_cert, tls_key)
    try:
        listing = list_workers(endpoints, namespace, None if secret is None else str(secret), insecure, tls,
                               router=bool(router))
    except Exception as exc:
        fail(exc)
    for endpoint, why in listing.unreachable.items():
        console.err.print(f"warning: no session at {endpoint}: {why}", highlight=False)
    if not listing.workers:
        # with TLS every endpoint is tls/ and each side names its CA, certificate and key
        scheme, files = ("tls", " --tls-ca CA --tls-cert CERT --tls-key KEY") if tls else ("tcp", "")
        joins, asks = ((f"--router {endpoints[0]}", f"--router {endpoints[0]}") if router else
                       (f"--listen {scheme}/0.0.0.0:7447", f"--connect {scheme}/HOST:7447"))
        console.out.print(f"no workers in namespace '{namespace}' at {', '.join(endpoints)}\n"
                          f"  start one: retriever-worker --name NAME --namespace {namespace} "
                          f"{joins}{files} --secret FILE, then: retriever workers "
                          f"{asks}{files} --secret FILE", highlight=False, soft_wrap=True)
        raise typer.Exit(code=1)  # a script waiting for its workers (`until retriever workers ...`) can tell
    console.out.print(_workers_table(listing.workers, namespace))
    if not router:
        console.err.print(f"(the workers linked to {', '.join(endpoints)}: a daemon is linked to those its --connect "
                          "names and those whose --connect names it; list the others with a --connect each)",
                          highlight=False)


def status_command(
    connect: _Through = None, namespace: _Namespace = "default", secret: _Secret = None, insecure: _Insecure = False,
    tls_ca: _TlsCa = None, tls_cert: _TlsCert = None, tls_key: _TlsKey = None, router: _Router = None,
) -> None:
    """Show the running deployment of a namespace, from any machine: per node its worker, state,
    ticks, steps, skips, errors and counters."""
    from ..backends.zenoh.protocol import DeploymentOp

    tls = tls_files(tls_ca, tls_cert, tls_key)
    answer = _ask_deployment(connect, namespace, secret, insecure, DeploymentOp.STATUS, tls, router)
    console.out.print(status_table(answer, namespace))


def status_table(answer: dict, namespace: str) -> Table:
    """A deployment's status (Deployment.status, maybe from the network: every cell plain
    text): per node its worker, state, rate achieved, steps, skips, errors, CPU and counters."""
    t_s = answer.get("t_ns", 0) / 1e9 if type(answer.get("t_ns")) is int else 0.0
    title = (f"{answer.get('pipeline')!s:.60} in namespace '{namespace}': "
             + (f"t = {t_s:.1f} of {answer.get('end_ns', 0) / 1e9:g} s" if answer.get("started") else "starting"))
    table = Table(title=Text(visible(title)), title_justify="left")
    for col in ("node", "worker", "state", "rate (Hz)", "steps", "skips", "errors", "cpu", "counted"):
        table.add_column(col, justify="left" if col in ("node", "worker", "state", "counted") else "right")
    nodes = answer.get("nodes") if type(answer.get("nodes")) is dict else {}
    for node, n in sorted(nodes.items()):
        n = n if type(n) is dict else {}
        counts = n.get("counts") if type(n.get("counts")) is dict else {}
        ticks, cpu = n.get("ticks"), n.get("cpu_s")
        rate = f"{ticks / t_s:.1f}" if type(ticks) is int and t_s > 0 else ""
        load = f"{100 * cpu / t_s:.0f}%" if type(cpu) in (int, float) and t_s > 0 else ""
        table.add_row(*(cell(str(v)) for v in (node, n.get("worker"), n.get("state"), rate, n.get("steps"),
                                                n.get("skips"), n.get("errors"), load)),
                      cell(", ".join(f"{k} {v}" for k, v in sorted(counts.items()))))
    return table


def stop_command(
    connect: _Through = None, namespace: _Namespace = "default", secret: _Secret = None, insecure: _Insecure = False,
    tls_ca: _TlsCa = None, tls_cert: _TlsCert = None, tls_key: _TlsKey = None, router: _Router = None,
) -> None:
    """Stop the running deployment of a namespace, from any machine, as Ctrl-C at its coordinator
    would: every node stops, its log is finished; the workers stay up."""
    from ..backends.zenoh.protocol import DeploymentOp

    tls = tls_files(tls_ca, tls_cert, tls_key)
    answer = _ask_deployment(connect, namespace, secret, insecure, DeploymentOp.STOP, tls, router)
    console.out.print(f"stopping deployment {visible(str(answer.get('pipeline')))!s:.60} in namespace '{namespace}'",
                      highlight=False)


def through(connect: list[str] | None, router: list[str] | None) -> list[str]:
    """The endpoints a command asks at: the routers, or the peers (a worker here by default)."""
    from ..backends.zenoh.daemon import DEFAULT_CONNECT

    if connect and router:
        fail(RetrieverError("--connect and --router both given\n    hint: ask through the deployment's router "
                            "(--router) if it joined through one, else through its workers (--connect)"))
    return router or connect or [DEFAULT_CONNECT]


def _ask_deployment(connect, namespace: str, secret, insecure: bool, op: str, tls=None, router=None) -> dict:
    from ..backends.zenoh.deploy import ask_deployment

    endpoints = through(connect, router)
    try:
        answer = ask_deployment(endpoints, namespace, op, secret, insecure, tls, router=bool(router))
    except Exception as exc:
        fail(exc)
    if answer is None:
        fail(RetrieverError(f"no deployment runs in namespace '{namespace}' at {', '.join(endpoints)}\n"
                            "    hint: retriever workers lists the workers (and the nodes they run); "
                            "is --namespace or --secret another?"))
    return answer


def _workers_table(workers: list, namespace: str) -> Table:
    """One row per worker; its info came from the network: every cell is plain text."""
    table = Table(title=f"workers in namespace '{namespace}'", title_justify="left")
    for col in ("name", "labels", "host", "pid", "version", "clock offset", "nodes"):
        table.add_column(col, justify="right" if col in ("pid", "clock offset") else "left")
    for w in workers:
        if w.info is None:
            table.add_row(cell(w.name), Text(visible(w.error or "no answer"), style="red"), "", "", "", "", "")
            continue
        info = w.info
        offset = "?" if w.offset_ns is None else f"{w.offset_ns / 1e6:+.2f} ms"
        labels = ", ".join(info.labels) or "-"
        nodes = ", ".join(info.nodes) or "-"
        table.add_row(cell(w.name), cell(labels), cell(info.host), cell(info.pid),
                      cell(info.packages.get("retriever", "?")), offset, cell(nodes))
    return table
