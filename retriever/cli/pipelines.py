"""The commands that take a pipeline: ``run`` (here, on a backend), ``deploy`` (on the worker
daemons of a namespace) and ``ir`` (its IR, or a picture of it)."""

from __future__ import annotations

import signal
import sys
from pathlib import Path
from typing import Annotated, NoReturn, Optional

import typer

from ..backends import canonical, default_backend
from ..errors import BackendError, LogWriteError, RetrieverError
from ..ir import IR
from . import console
from .console import cleaning_up, fail, print_held_warnings, stop_on_signals, stop_signal
from .deployments import status_table
from .inputs import load, read
from .options import (FOXGLOVE_OPTION, KEEP_OPTION, RERUN_OPTION, TLS_CA_OPTION, TLS_CERT_OPTION, TLS_KEY_OPTION,
                      check_keep, tls_files)
from .summary import print_summary, run_errors

#: `retriever run --duration inf`: a century, within the int64 nanoseconds of tags, with room
#: for every latency and delay past the end
UNTIL_STOPPED_S = 100 * 365.25 * 86400.0

#: how often the live status table of a deployment is redrawn
LIVE_EVERY_S = 0.5


def run(
    target: Annotated[str, typer.Argument(metavar="FILE[:ATTR]", help="Python file (and Pipeline name) or IR .json")],
    backend: Annotated[Optional[str], typer.Option(
        help="Backend: inproc (virtual time, one process), zenoh (real time, a process per flow), or dora "
             "(real time, a dora dataflow: pip install 'retriever-robotics\\[dora]'). "
             "Default: inproc, or what the file chose with retriever.init(backend=...).")] = None,
    duration: Annotated[float, typer.Option(help="Seconds to run: virtual time on inproc, wall time on zenoh; "
                                                  "inf: until Ctrl-C (or SIGTERM).")] = 10.0,
    log: Annotated[Optional[Path], typer.Option(help="Record the run in this MCAP event log.")] = None,
    force: Annotated[bool, typer.Option("--force", help="Overwrite the --log file if it exists.")] = False,
    allow_errors: Annotated[bool, typer.Option(
        "--allow-errors", help="Exit 0 after a run whose steps raised or whose flows restarted "
                               "(on_error='skip_tick' or 'restart' absorbed them).")] = False,
    secret: Annotated[Optional[Path], typer.Option(
        help="zenoh: a deployment secret file (>= 16 bytes, mode 600) the run's passwords derive from, so "
             "that processes holding it can join the run's namespace (--namespace).")] = None,
    namespace: Annotated[Optional[str], typer.Option(help="zenoh: the run's namespace (default: a fresh one).")] = None,
    virtual_time: Annotated[bool, typer.Option(
        "--virtual-time", help="zenoh: one process per flow, advanced in lockstep in logical time: the trace is "
                               "inproc's; --duration is then virtual seconds.")] = False,
    no_links: Annotated[bool, typer.Option(
        "--no-links", help="zenoh: carry every edge on Zenoh, none over same-host links (the default between "
                           "the run's processes on this machine: a Unix socket and shared memory of its own).")] = False,
    keep: Annotated[Optional[str], KEEP_OPTION] = None,
    foxglove: Annotated[Optional[int], FOXGLOVE_OPTION] = None,
    rerun: Annotated[Optional[str], RERUN_OPTION] = None,
) -> None:
    """Run a pipeline and print per-node ticks, steps, skips and mean step time. Exits 1 when a
    step raised or a flow restarted, even if the run went on (unless --allow-errors)."""
    check_keep(keep)
    shown = f"{duration:g} s"
    if duration == float("inf"):  # until stopped: a run as long as times may go, in practice
        duration, shown = UNTIL_STOPPED_S, "until stopped"
        if log is None and keep is None:  # no log to read it from: the trace would grow until stopped
            keep = "counters"
            console.err.print("--duration inf without --log: the run keeps its counters only (--keep counters; give "
                              "--log to record it, or --keep to choose)", highlight=False)
    options = {k: v for k, v in (("secret", secret), ("namespace", namespace), ("keep", keep),
                                 ("foxglove", foxglove), ("rerun", rerun)) if v is not None}
    for flag, value, export in (("--foxglove", foxglove, "-o view.mcap"),
                                ("--rerun", rerun, "--format rerun -o run.rrd")):
        if value is not None and canonical(backend or default_backend()) not in ("zenoh", "dora"):
            fail(BackendError(f"{flag} streams a real-time run: it needs --backend zenoh or dora\n    hint: for an "
                              "in-process run, write a log and open its export: "
                              f"retriever log export run.mcap {export}"))
    _check_rerun_target(rerun)
    if virtual_time:
        if canonical(backend or default_backend()) != "zenoh":
            fail(BackendError("--virtual-time is for --backend zenoh (inproc always runs in virtual time)\n"
                              "    hint: retriever run FILE --backend zenoh --virtual-time, or drop --virtual-time"))
        options["virtual_time"] = True
    if no_links:
        if canonical(backend or default_backend()) != "zenoh":
            fail(BackendError("--no-links is for --backend zenoh (only its runs have same-host links)\n"
                              "    hint: retriever run FILE --backend zenoh --no-links, or drop --no-links"))
        options["same_host_links"] = False
    _execute(load(target), duration, backend, log, force, allow_errors, options,
             f"{shown}{' of virtual time' if virtual_time else ''} on {backend or default_backend()}")


def deploy(
    target: Annotated[str, typer.Argument(metavar="FILE[:ATTR]", help="Python file (and Pipeline name) or IR .json")],
    placement: Annotated[Optional[Path], typer.Option(
        help="A placement file (TOML): in its nodes table, NODE = \"WORKER\" or { labels = [\"gpu\"] } "
             "(process = \"NAME\": one process with the flows of that name); others by load.")] = None,
    connect: Annotated[Optional[list[str]], typer.Option(
        help="Zenoh endpoint of a worker (or router) to join, e.g. tcp/10.0.0.2:7447; repeatable.")] = None,
    listen: Annotated[Optional[list[str]], typer.Option(
        help="Zenoh endpoint this coordinator listens on for workers; repeatable.")] = None,
    router: Annotated[Optional[list[str]], typer.Option(
        metavar="ENDPOINT", help="Join through the Zenoh router there (retriever router), as the workers did with "
                                 "their --router: every session a client of it, none listening (a machine behind "
                                 "NAT); repeatable. Instead of --connect and --listen.")] = None,
    namespace: Annotated[Optional[str], typer.Option(help="The workers' namespace (default: default).")] = None,
    duration: Annotated[Optional[float], typer.Option(help="Seconds to run (wall time; default 10).")] = None,
    log: Annotated[Optional[Path], typer.Option(help="Record the whole deployment in this MCAP event log.")] = None,
    force: Annotated[bool, typer.Option("--force", help="Overwrite the --log file if it exists.")] = False,
    secret: Annotated[Optional[Path], typer.Option(
        help="The deployment secret (retriever secret new FILE), the same file as the workers'.")] = None,
    insecure: Annotated[bool, typer.Option(
        "--insecure", help="Join without a secret: anyone on the network may join (a trusted lab only).")] = False,
    allow_errors: Annotated[bool, typer.Option(
        "--allow-errors", help="Exit 0 after a run whose steps raised or whose flows restarted.")] = False,
    on_worker_loss: Annotated[Optional[str], typer.Option(
        help="A worker lost mid-run: 'replace' (the default) starts its nodes afresh on other workers their "
             "placement allows; 'wait' on it once it is back; 'stop' stops the run.")] = None,
    lease: Annotated[Optional[float], typer.Option(
        metavar="SECONDS", help="How long a link that went silent (a partition) is kept before its worker counts "
                                "as lost: Zenoh's lease (default 10; under about 3 s, a congested link's close can drop "
                                "healthy links, docs/deploy.md).")] = None,
    tls_ca: Annotated[Optional[Path], TLS_CA_OPTION] = None,
    tls_cert: Annotated[Optional[Path], TLS_CERT_OPTION] = None,
    tls_key: Annotated[Optional[Path], TLS_KEY_OPTION] = None,
    virtual_time: Annotated[bool, typer.Option(
        "--virtual-time", help="Advance every node in lockstep from the coordinator, in logical time: the trace "
                               "is the in-process backend's, however long the steps take; --duration is then "
                               "virtual seconds.")] = False,
    keep: Annotated[Optional[str], KEEP_OPTION] = None,
    foxglove: Annotated[Optional[int], FOXGLOVE_OPTION] = None,
    rerun: Annotated[Optional[str], RERUN_OPTION] = None,
    config: Annotated[Optional[Path], typer.Option(
        metavar="deploy.toml", help="Settings from this TOML file (keys as the flags: connect, placement, "
                                    "secret, tls_ca, ...); flags override it.")] = None,
) -> None:
    """Run a pipeline on the worker daemons of a namespace (retriever-worker on each machine):
    place every node (pins and labels from --placement, the rest by load), start all at one T0,
    log the whole deployment, stop every node at the end, Ctrl-C or SIGTERM; the workers stay up."""
    from ..backends.zenoh.deploy import load_deploy_config

    check_keep(keep)
    _check_rerun_target(rerun)
    try:
        given = load_deploy_config(config) if config is not None else {}
    except Exception as exc:
        fail(exc)
    flags = {"connect": connect, "listen": listen, "router": router, "namespace": namespace, "placement": placement,
             "duration": duration, "log": log, "secret": secret, "insecure": insecure or None,
             "on_worker_loss": on_worker_loss, "lease": lease, "tls_ca": tls_ca, "tls_cert": tls_cert,
             "tls_key": tls_key, "virtual_time": virtual_time or None, "keep": keep}
    if secret is not None or insecure:  # a flag's choice of security replaces the file's
        given.pop("secret", None), given.pop("insecure", None)
    settings = {"namespace": "default", "duration": 10.0, "on_worker_loss": "replace", **given,
                **{k: v for k, v in flags.items() if v is not None}}
    get = settings.get
    options = {"connect": list(get("connect", [])), "listen": list(get("listen", [])),
               "router": list(get("router", [])),
               "namespace": get("namespace"), "placement": None if get("placement") is None else str(get("placement")),
               "secret": get("secret"), "insecure": bool(get("insecure")), "on_worker_loss": get("on_worker_loss"),
               "lease": get("lease"), "tls": tls_files(get("tls_ca"), get("tls_cert"), get("tls_key")),
               "virtual_time": bool(get("virtual_time")),
               "keep": get("keep") or ("records" if get("log") is None else "counters")}
    if foxglove is not None:
        options["foxglove"] = foxglove
    if rerun is not None:
        options["rerun"] = rerun
    if get("max_clock_offset") is not None:
        options["max_clock_offset"] = get("max_clock_offset")
    log = None if get("log") is None else Path(get("log"))
    _execute(load(target), get("duration"), "zenoh", log, force, allow_errors, options,
             f"{get('duration'):g} s{' of virtual time' if get('virtual_time') else ''} on the workers of namespace "
             f"'{get('namespace')}'", live=get("namespace"))


def _check_rerun_target(target: str | None) -> None:
    """--rerun's TARGET, checked before the pipeline's file is loaded: a folder, a file in a folder
    that does not exist, or what is neither a URL nor an .rrd path, fails here."""
    if target is None:
        return
    from ..log.rerun_live import check_target

    try:
        check_target(target)
    except RetrieverError as exc:
        fail(exc)


def _execute(pipe, duration: float, backend: str | None, log: Path | None, force: bool, allow_errors: bool,
             options: dict, title: str, live: str | None = None) -> None:
    """Run ``pipe``, print its table and counters, and exit as ``retriever run`` documents;
    ``live``: a deployment's namespace, whose status table shows while it runs (on a terminal)."""
    before = _identity(log)
    stop_on_signals()  # stop like Ctrl-C: the log is finished, not torn
    watching = _show_live(pipe, live) if live is not None and console.err.is_terminal else None

    def stop_watching() -> None:  # the live table goes before the final one is printed
        nonlocal watching
        if watching is not None:
            watching[0].set()
            watching[1].join(timeout=2.0)
            watching = None

    try:
        trace = pipe.run(duration=duration, backend=backend, log=log, overwrite=force, **options)
    except KeyboardInterrupt:
        stop_watching()
        _interrupted(pipe, log, before, title)
    except Exception as exc:
        stop_watching()
        if stop_signal() is not None:  # a stop signal came as it failed: e.g. inside a C extension's
            _interrupted(pipe, log, before, title)  # import in a setup(), which says ImportError
        # only a log this run wrote holds it (a refused run leaves the file as it was; a log that
        # could not be written says so in its own error)
        if _identity(log) not in (None, before) and not isinstance(exc, LogWriteError):
            console.err.print(f"the run up to the error is in {log}", highlight=False)
        fail(exc)
    finally:
        stop_watching()
        if "rerun" in options:
            _exit_past_a_stuck_viewer()
    cleaning_up()  # the run is over: a signal from here on no longer cuts its table short
    print_summary(pipe, trace, title, log)
    print_held_warnings()
    if not allow_errors:
        _fail_on_errors(pipe)
    signum = stop_signal()  # one came as the table was printed, or the run went on to its end: its
    if signum is not None:  # exception raised where Python drops it (a __del__, a weakref's callback)
        console.err.print("interrupted", highlight=False)
        raise typer.Exit(code=128 + signum)


def _exit_past_a_stuck_viewer() -> None:
    """The command owns its process: when its Rerun live view's close gave up on a viewer that
    takes nothing (suspended), Rerun's at-exit shutdown, which would wait on it for ever, is
    dropped (the view said it did not take the end; the log, if any, is already finished)."""
    from ..log.rerun_live import skip_rerun_shutdown_if_stuck

    skip_rerun_shutdown_if_stuck()


def _interrupted(pipe, log: Path | None, before, title: str) -> NoReturn:
    """Print what ran until the stop signal (as at the end of a run) and exit 128 + the signal."""
    cleaning_up(ignored_one=getattr(pipe.session, "signal_ignored", False))
    recorded = _identity(log) not in (None, before)
    if pipe.session is not None:
        print_summary(pipe, pipe.trace, f"{title}, interrupted", log if recorded else None)
        for line in pipe.starved():
            console.err.print(f"warning: pipeline '{pipe.name}': {line}", highlight=False, markup=False)
    console.err.print("interrupted" + (f"; the run so far is in {log}" if recorded else ""), highlight=False)
    # during a logged run the pipeline's own handler took the signal (it stops between ticks)
    signum = stop_signal() or getattr(pipe.session, "stop_signal", None) or signal.SIGINT
    raise typer.Exit(code=128 + signum) from None


def _show_live(pipe, namespace: str):
    """Show the deployment's status table on stderr, refreshed, until the returned event is set
    (then join the returned thread: the table is cleared)."""
    import threading

    from rich.live import Live

    done = threading.Event()

    def show() -> None:
        with Live(console=console.err, refresh_per_second=2, transient=True) as live:
            while not done.wait(LIVE_EVERY_S):
                hosting = getattr(pipe.session, "hosting", None)  # a deployment's says what runs where
                if hasattr(hosting, "status"):
                    try:
                        live.update(status_table(hosting.status(), namespace))
                    except RuntimeError:  # read while the run updates it: next time
                        continue

    thread = threading.Thread(target=show, name="retriever-live", daemon=True)
    thread.start()
    return done, thread


def _fail_on_errors(pipe) -> None:
    """A run whose steps raised, or whose flows restarted, fails (exit 1) though it went on."""
    error = run_errors(pipe.stats())
    if error is not None:
        fail(error)


def _identity(path: Path | None) -> tuple[int, int, int, int] | None:
    """What tells one file at ``path`` from another or from its earlier self (None: no file)."""
    try:
        st = path.stat() if path is not None else None
    except OSError:
        return None
    return None if st is None else (st.st_dev, st.st_ino, st.st_mtime_ns, st.st_size)


def ir_command(
    target: Annotated[str, typer.Argument(metavar="FILE[:ATTR]|IR.json|LOG.mcap",
                                          help="Python file (and Pipeline name), an IR .json, or a log")],
    format: Annotated[str, typer.Option("--format", "-f", help="json, dot or mermaid.")] = "json",
    out: Annotated[Optional[Path], typer.Option("--out", "-o", help="Write here instead of stdout.")] = None,
) -> None:
    """Compile a pipeline to its IR (or a DOT / Mermaid picture of it). An IR file or a log (the
    IR it holds) is read and checked, never imported: nothing of the user's code runs."""
    if format not in ("json", "dot", "mermaid"):
        fail(RetrieverError(f"unknown format {format!r}\n    hint: use --format json, dot or mermaid"))
    try:
        if target.endswith(".mcap"):
            ir = read(Path(target)).ir
        elif target.endswith(".json"):
            ir = IR.load(target)
        else:
            ir = load(target).build_ir()
        text = ir.to_json() if format == "json" else ir.visualize(format)
    except typer.Exit:
        raise
    except Exception as exc:
        fail(exc)
    if out is None:
        sys.stdout.write(text)
    else:
        out.write_text(text, encoding="utf-8")
        console.err.print(f"wrote {out}", highlight=False)
