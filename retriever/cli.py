"""The ``retriever`` command: thin — parse, call the public API, format results and errors."""

from __future__ import annotations

import json
import signal
import sys
import traceback
import warnings
from collections import Counter
from importlib.metadata import entry_points
from pathlib import Path
from typing import Annotated, NoReturn, Optional

import typer
from rich.console import Console
from rich.markup import escape
from rich.table import Table
from rich.text import Text

from .backends import canonical, default_backend
from .errors import BackendError, LogWriteError, RetrieverError, RetrieverWarning, StarvedFlowWarning
from .ir import IR
from .starved import describe_starved

app = typer.Typer(no_args_is_help=True, add_completion=False,
                  help="Retriever: closed-loop robot agents with explicit time.")
_state = {"debug": False}


def _visible(text: str) -> str:
    """``text`` with its control characters shown escaped (``\\x1b``), newlines and tabs kept: a
    log's or an IR's strings reach the terminal, where an escape sequence could retitle it,
    recolour it or plant a hyperlink."""
    if text.isprintable():
        return text
    return "".join(c if c.isprintable() or c in "\n\t" else repr(c)[1:-1] for c in text)


#: wider than any table's natural width: what a table is measured against
_UNBOUNDED_COLUMNS = 100_000


class _Uncut:
    """A table at its natural width, past the terminal's edge if it must be: a name cut to fit
    (``contro…``) names nothing. A terminal wraps the long lines; a pipe or a file keeps them."""

    def __init__(self, table: Table):
        self.table = table

    def __rich_console__(self, console, options):
        natural = console.measure(self.table, options=options.update_width(_UNBOUNDED_COLUMNS)).maximum
        yield from console.render(self.table, options.update_width(max(options.max_width, natural)))


class _Console(Console):
    """Rich's console, but a string is never markup unless the call says ``markup=True`` (whose
    text escapes what it interpolates), its control characters are shown escaped, and a table
    is never cut to the terminal's width."""

    def print(self, *objects, **kwargs) -> None:
        if any(isinstance(o, Table) for o in objects):
            kwargs["crop"] = False
        super().print(*(_visible(o) if isinstance(o, str) else _Uncut(o) if isinstance(o, Table) else o
                        for o in objects), **kwargs)


def _cell(value: object) -> Text:
    """A table cell holding a value that may come from a file: plain text, never markup."""
    return Text(_visible(str(value)))


_out = _Console(markup=False)
_err = _Console(stderr=True, soft_wrap=True, markup=False)


def _version(shown: bool) -> None:
    if shown:
        from .log.format import package_versions

        # a checkout that was never installed has no version
        version = package_versions().get("retriever", "unknown (not installed: pip install -e .)")
        _out.print(f"retriever {version}", highlight=False)
        raise typer.Exit()


@app.callback()
def _main(debug: Annotated[bool, typer.Option("--debug", help="Show tracebacks on errors (anywhere on the "
                                                                "command line).")] = False,
          version: Annotated[bool, typer.Option("--version", callback=_version, is_eager=True,
                                                help="Show the version and exit.")] = False) -> None:
    _state["debug"] = debug


def _fail(exc: BaseException) -> None:
    if _state["debug"]:
        traceback.print_exception(exc)
    text = str(exc) if isinstance(exc, RetrieverError) else f"{type(exc).__name__}: {exc}"
    first, *rest = text.split("\n")
    _err.print(f"[bold red]error:[/] {escape(_visible(first))}", highlight=False, markup=True)
    listed = any(line.startswith("  - ") for line in rest)  # hints of listed problems stay under them
    for line in rest:
        if not listed and line.startswith("    hint:"):
            line = line.lstrip()
        _err.print(line, highlight=False, markup=False)
    for note in getattr(exc, "__notes__", ()):  # what became of the run's files (RunLog.end)
        _err.print(note, highlight=False, markup=False)
    if not _state["debug"] and not isinstance(exc, RetrieverError):
        _err.print("(run with --debug for the traceback)", highlight=False)
    raise typer.Exit(code=1)


#: warnings about how the run went, held back to be printed under its table
_after_summary: list[str] = []


def _show_warning(message, category, filename, lineno, file=None, line=None) -> None:
    if issubclass(category, StarvedFlowWarning):
        _after_summary.append(f"warning: {message}")
    elif issubclass(category, RetrieverWarning):
        _err.print(f"warning: {message}", highlight=False, markup=False)
    else:
        _err.print(f"warning: {category.__name__}: {message} ({filename}:{lineno})", highlight=False, markup=False)


warnings.showwarning = _show_warning


def _interrupt(signum, frame) -> None:
    _state["signal"] = signum
    raise KeyboardInterrupt


def _load(target: str):
    from ._loading import load_pipeline

    try:
        return load_pipeline(target)
    except Exception as exc:  # a user file may raise anything while it builds its graph
        _fail(exc)


#: `--foxglove` without a port: the Foxglove app's default for a WebSocket connection
FOXGLOVE_PORT = 8765
_FOXGLOVE = typer.Option(
    "--foxglove", metavar="[PORT]",
    help=f"zenoh: stream the run live to the Foxglove app (its WebSocket server in this process, on "
         f"127.0.0.1:PORT, default {FOXGLOVE_PORT}; needs pip install 'retriever-robotics\\[foxglove]').")

_KEEP = typer.Option(
    metavar="trace|records|counters",
    help="What the run keeps in memory: 'trace' every event's value (the default of run without --log or on "
         "inproc); 'records' the events' ids and tags and the step records, the values only in --log (on zenoh "
         "they then reach this process only to be logged; the default of deploy without --log); 'counters' "
         "nothing but the counters, each record freed once --log has it: memory stays bounded however long "
         "the run (the default of a logged run on zenoh and of a logged deploy).")


@app.command()
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
    keep: Annotated[Optional[str], _KEEP] = None,
    foxglove: Annotated[Optional[int], _FOXGLOVE] = None,
) -> None:
    """Run a pipeline and print per-node ticks, steps, skips and mean step time. Exits 1 when a
    step raised or a flow restarted, even if the run went on (unless --allow-errors)."""
    _check_keep(keep)
    shown = f"{duration:g} s"
    if duration == float("inf"):  # until stopped: a run as long as times may go, in practice
        duration, shown = UNTIL_STOPPED_S, "until stopped"
        if log is None and keep is None:  # no log to read it from: the trace would grow until stopped
            keep = "counters"
            _err.print("--duration inf without --log: the run keeps its counters only (--keep counters; give "
                       "--log to record it, or --keep to choose)", highlight=False)
    options = {k: v for k, v in (("secret", secret), ("namespace", namespace), ("keep", keep),
                                 ("foxglove", foxglove)) if v is not None}
    if foxglove is not None and canonical(backend or default_backend()) not in ("zenoh", "dora"):
        _fail(BackendError("--foxglove streams a real-time run: it needs --backend zenoh or dora\n    hint: for an "
                           "in-process run, write a log and open its export: "
                           "retriever log export run.mcap -o view.mcap"))
    if virtual_time:
        if canonical(backend or default_backend()) != "zenoh":
            _fail(BackendError("--virtual-time is for --backend zenoh (inproc always runs in virtual time)\n"
                               "    hint: retriever run FILE --backend zenoh --virtual-time, or drop --virtual-time"))
        options["virtual_time"] = True
    _execute(_load(target), duration, backend, log, force, allow_errors, options,
             f"{shown}{' of virtual time' if virtual_time else ''} on {backend or default_backend()}")


# ---------------------------------------------------------------------------------------------
# Commands that other packages add (the `retriever.commands` entry point group)
# ---------------------------------------------------------------------------------------------
#: the entry point group whose entries ("name = module:function") become commands of `retriever`;
#: the project registers `demo` there (agents/command.py): the agents sit above the library,
#: which never imports them
COMMANDS_GROUP = "retriever.commands"


def fail(exc: BaseException) -> NoReturn:
    """Report ``exc`` as every command does (``error:``, its ``hint:``; the traceback with
    --debug) and exit 1."""
    _fail(exc)
    raise AssertionError("unreachable")  # _fail exits


#: where a command prints its results (stdout) and its progress and errors (stderr): strings are
#: never markup and their control characters are shown escaped
out, err = _out, _err


def stop_on_sigterm() -> None:
    """From now on SIGTERM stops the command as Ctrl-C does (a KeyboardInterrupt), and
    :func:`stop_signal` says which signal it was."""
    signal.signal(signal.SIGTERM, _interrupt)


def stop_signal() -> int | None:
    """The signal that stopped the command through :func:`stop_on_sigterm` or a run, if any."""
    return _state.get("signal")


def _add_registered_commands() -> None:
    """Each entry of COMMANDS_GROUP as a command; one that cannot be imported is still listed,
    and says why when it is run, instead of breaking every other command."""
    for entry in entry_points(group=COMMANDS_GROUP):
        if any(c.name == entry.name for c in app.registered_commands):
            continue
        try:
            app.command(name=entry.name)(entry.load())
        except Exception as exc:  # noqa: BLE001 (whatever stops a plugin's import, the command says it)
            app.command(name=entry.name, help=f"(cannot be loaded: {type(exc).__name__})",
                        context_settings={"allow_extra_args": True, "ignore_unknown_options": True},
                        )(_unloadable(entry.name, entry.value, exc))


def _unloadable(name: str, value: str, exc: Exception):
    def command() -> None:
        fail(RetrieverError(f"the command '{name}' ({value}) cannot be loaded: {type(exc).__name__}: {exc}\n"
                            "    hint: install the project itself, which includes it: pip install -e ."))

    return command


_TLS_CA = typer.Option("--tls-ca", metavar="FILE", help="TLS: the CA certificate (PEM) that signs every "
                       "certificate of the deployment; with --tls-cert and --tls-key every link is mutual TLS "
                       "(endpoints tls/HOST:PORT).")
_TLS_CERT = typer.Option("--tls-cert", metavar="FILE", help="TLS: this machine's certificate (PEM), naming the "
                         "addresses it is reached at.")
_TLS_KEY = typer.Option("--tls-key", metavar="FILE", help="TLS: this machine's private key (PEM).")


#: `retriever run --duration inf`: a century, within the int64 nanoseconds of tags, with room
#: for every latency and delay past the end
UNTIL_STOPPED_S = 100 * 365.25 * 86400.0

#: how often the live status table of a deployment is redrawn
LIVE_EVERY_S = 0.5


def _tls(ca, cert, key):
    from .backends.zenoh.access import TlsFiles

    try:
        return TlsFiles.of(ca, cert, key)
    except Exception as exc:
        _fail(exc)


@app.command()
def deploy(
    target: Annotated[str, typer.Argument(metavar="FILE[:ATTR]", help="Python file (and Pipeline name) or IR .json")],
    placement: Annotated[Optional[Path], typer.Option(
        help="A placement file (TOML): in its nodes table, NODE = \"WORKER\" or { labels = [\"gpu\"] }; "
             "others by load.")] = None,
    connect: Annotated[Optional[list[str]], typer.Option(
        help="Zenoh endpoint of a worker (or router) to join, e.g. tcp/10.0.0.2:7447; repeatable.")] = None,
    listen: Annotated[Optional[list[str]], typer.Option(
        help="Zenoh endpoint this coordinator listens on for workers; repeatable.")] = None,
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
    tls_ca: Annotated[Optional[Path], _TLS_CA] = None,
    tls_cert: Annotated[Optional[Path], _TLS_CERT] = None,
    tls_key: Annotated[Optional[Path], _TLS_KEY] = None,
    virtual_time: Annotated[bool, typer.Option(
        "--virtual-time", help="Advance every node in lockstep from the coordinator, in logical time: the trace "
                               "is the in-process backend's, however long the steps take; --duration is then "
                               "virtual seconds.")] = False,
    keep: Annotated[Optional[str], _KEEP] = None,
    foxglove: Annotated[Optional[int], _FOXGLOVE] = None,
    config: Annotated[Optional[Path], typer.Option(
        metavar="deploy.toml", help="Settings from this TOML file (keys as the flags: connect, placement, "
                                    "secret, tls_ca, ...); flags override it.")] = None,
) -> None:
    """Run a pipeline on the worker daemons of a namespace (retriever-worker on each machine):
    place every node (pins and labels from --placement, the rest by load), start all at one T0,
    log the whole deployment, stop every node at the end, Ctrl-C or SIGTERM; the workers stay up."""
    from .backends.zenoh.deploy import load_deploy_config

    _check_keep(keep)
    try:
        given = load_deploy_config(config) if config is not None else {}
    except Exception as exc:
        _fail(exc)
    flags = {"connect": connect, "listen": listen, "namespace": namespace, "placement": placement,
             "duration": duration, "log": log, "secret": secret, "insecure": insecure or None,
             "on_worker_loss": on_worker_loss, "lease": lease, "tls_ca": tls_ca, "tls_cert": tls_cert,
             "tls_key": tls_key, "virtual_time": virtual_time or None, "keep": keep}
    if secret is not None or insecure:  # a flag's choice of security replaces the file's
        given.pop("secret", None), given.pop("insecure", None)
    settings = {"namespace": "default", "duration": 10.0, "on_worker_loss": "replace", **given,
                **{k: v for k, v in flags.items() if v is not None}}
    get = settings.get
    options = {"connect": list(get("connect", [])), "listen": list(get("listen", [])),
               "namespace": get("namespace"), "placement": None if get("placement") is None else str(get("placement")),
               "secret": get("secret"), "insecure": bool(get("insecure")), "on_worker_loss": get("on_worker_loss"),
               "lease": get("lease"), "tls": _tls(get("tls_ca"), get("tls_cert"), get("tls_key")),
               "virtual_time": bool(get("virtual_time")),
               "keep": get("keep") or ("records" if get("log") is None else "counters")}
    if foxglove is not None:
        options["foxglove"] = foxglove
    if get("max_clock_offset") is not None:
        options["max_clock_offset"] = get("max_clock_offset")
    log = None if get("log") is None else Path(get("log"))
    _execute(_load(target), get("duration"), "zenoh", log, force, allow_errors, options,
             f"{get('duration'):g} s{' of virtual time' if get('virtual_time') else ''} on the workers of namespace "
             f"'{get('namespace')}'", live=get("namespace"))


def _check_keep(keep: str | None) -> None:
    from .trace import KEEP

    if keep is not None and keep not in KEEP:
        _fail(BackendError(f"--keep {keep!r} is none of 'trace', 'records', 'counters'\n    hint: --keep records keeps "
                           "the events' ids and the step records (the values only in --log); --keep trace every "
                           "value; --keep counters nothing but the counters (the records only in --log)"))


def _execute(pipe, duration: float, backend: str | None, log: Path | None, force: bool, allow_errors: bool,
             options: dict, title: str, live: str | None = None) -> None:
    """Run ``pipe``, print its table and counters, and exit as ``retriever run`` documents;
    ``live``: a deployment's namespace, whose status table shows while it runs (on a terminal)."""
    before = _identity(log)
    signal.signal(signal.SIGTERM, _interrupt)  # stop like Ctrl-C: the log is finished, not torn
    watching = _show_live(pipe, live) if live is not None and _err.is_terminal else None
    try:
        trace = pipe.run(duration=duration, backend=backend, log=log, overwrite=force, **options)
    except KeyboardInterrupt:
        if watching is not None:
            watching[0].set()
            watching[1].join(timeout=2.0)
            watching = None
        recorded = _identity(log) not in (None, before)
        if pipe.session is not None:  # what ran until the interrupt, as at the end of a run
            _summary(pipe, pipe.trace, f"{title}, interrupted", log if recorded else None)
            for line in pipe.starved():
                _err.print(f"warning: pipeline '{pipe.name}': {line}", highlight=False, markup=False)
        _err.print("interrupted" + (f"; the run so far is in {log}" if recorded else ""), highlight=False)
        # during a logged run the pipeline's own handler took the signal (it stops between ticks)
        signum = _state.get("signal") or getattr(pipe.session, "stop_signal", None) or signal.SIGINT
        raise typer.Exit(code=128 + signum) from None
    except Exception as exc:
        # only a log this run wrote holds it (a refused run leaves the file as it was; a log that
        # could not be written says so in its own error)
        if _identity(log) not in (None, before) and not isinstance(exc, LogWriteError):
            _err.print(f"the run up to the error is in {log}", highlight=False)
        _fail(exc)
    finally:
        if watching is not None:  # the live table goes before the final one is printed
            watching[0].set()
            watching[1].join(timeout=2.0)
    _summary(pipe, trace, title, log)
    for text in _after_summary:
        _err.print(text, highlight=False, markup=False)
    _after_summary.clear()
    if not allow_errors:
        _fail_on_errors(pipe)


def _summary(pipe, trace, title: str, log: Path | None) -> None:
    """The run's table, what it counted, and where its log is."""
    session = pipe.session
    placed = getattr(getattr(session, "hosting", None), "placed", None)  # a deployment: where each node ran
    starved = _starved_cells(session.starved if session is not None else [])
    table = Table(title=f"{pipe.name}: {title}", title_justify="left")
    for col in ("node", *(("worker",) if placed else ()), "ticks", "steps", "skips", "errors", "mean step",
                *(("starved",) if starved else ())):
        table.add_column(col, justify="left" if col in ("node", "worker", "starved") else "right")
    for node, s in sorted(pipe.stats().items()):
        mean = f"{s.mean_step_s * 1e6:.1f} µs" if s.mean_step_s < 0.01 else f"{s.mean_step_s * 1e3:.1f} ms"
        table.add_row(node, *((_cell(placed[node]),) if placed else ()), str(s.ticks), str(s.steps), str(s.skips),
                      str(s.errors), mean, *((starved.get(node, ""),) if starved else ()))
    _out.print(table)
    for node, s in sorted(pipe.stats().items()):  # what a real-time run counted, node by node
        if any(s.counts.values()):
            _out.print(f"{node} counted: {counters_in_words(s.counts)}", highlight=False)
    unowned = Counter(pipe.counts())
    unowned.subtract(sum((Counter(s.counts) for s in pipe.stats().values()), Counter()))
    if +unowned:
        _out.print(f"the coordinator counted: {counters_in_words(+unowned)}", highlight=False)
    if session is not None and session.keep == "counters":  # reading the log back could take GBs
        steps = sum(s.steps for s in pipe.stats().values())
        kept = "kept only in the log" if log is not None else "not kept"
        _out.print(f"{steps} steps · records {kept} (--keep counters)", highlight=False)
    else:
        digest = f"trace digest {trace.digest()[:16]}" if trace.values_kept else "values not kept (--keep records)"
        _out.print(f"{len(trace.events)} events · {len(trace.steps)} steps · {digest}", highlight=False)
    if log is not None:
        _out.print(f"log: {log} ({log.stat().st_size / 1e6:.2f} MB); check it with: retriever replay {log}",
                   highlight=False, soft_wrap=True)  # a command to copy: never broken across lines


def _starved_cells(episodes: list[dict]) -> dict[str, Text]:
    """Per node, the table's mark of the spans its inputs starved (StarvationWatch):
    ``pixels from 3.9 s`` (to the end), ``pixels 3.9–5.1 s`` (it had events again)."""
    cells: dict[str, list[str]] = {}
    for e in episodes:
        since = f"{e['since_ns'] / 1e9:.3g}"
        span = f"from {since} s" if e["until_ns"] is None else f"{since}–{e['until_ns'] / 1e9:.3g} s"
        cells.setdefault(e["node"], []).append(f"{e['port']} {span}")
    return {node: _cell(", ".join(marks)) for node, marks in cells.items()}


def _show_live(pipe, namespace: str):
    """Show the deployment's status table on stderr, refreshed, until the returned event is set
    (then join the returned thread: the table is cleared)."""
    import threading

    from rich.live import Live

    done = threading.Event()

    def show() -> None:
        with Live(console=_err, refresh_per_second=2, transient=True) as live:
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
    stats = pipe.stats()
    errors = {node: s.errors for node, s in sorted(stats.items()) if s.errors}
    restarts = {node: s.counts.get("restarts", 0) + s.counts.get("moves", 0) for node, s in sorted(stats.items())
                if s.counts.get("restarts") or s.counts.get("moves")}
    crashes = sum(s.counts.get("crash_restarts", 0) + s.counts.get("moves", 0) for s in stats.values())
    if not errors and not restarts:
        return
    parts = [f"{node}: {n} step error(s)" + (f", {restarts[node]} restart(s)" if node in restarts else "")
             for node, n in errors.items()]
    parts += [f"{node}: {n} restart(s)" for node, n in restarts.items() if node not in errors]
    where = ("the error records say what raised (retriever log cat LOG --steps)" if errors else "")
    if crashes:
        where += ("; " if where else "") + (f"{crashes} restart(s) followed a process that died: retriever log "
                                            "info LOG shows each fault")
    _fail(RetrieverError(f"the run went on, but had errors ({'; '.join(parts)})\n"
                         f"    hint: {where}; pass --allow-errors when on_error='skip_tick' or 'restart' is meant "
                         "to absorb them"))


def _identity(path: Path | None) -> tuple[int, int, int, int] | None:
    """What tells one file at ``path`` from another or from its earlier self (None: no file)."""
    try:
        st = path.stat() if path is not None else None
    except OSError:
        return None
    return None if st is None else (st.st_dev, st.st_ino, st.st_mtime_ns, st.st_size)


_COUNTER_LABELS = {"late": "late events", "incomplete": "ticks with an incomplete edge", "overrun": "ticks skipped after overruns",
                   "restart_skipped": "ticks skipped during restarts",
                   "deadline_miss": "LET deadline misses", "unrun_ticks": "ticks never run",
                   "garbage": "garbage messages dropped", "forged": "forged messages or records refused",
                   "report_waits": "waits for the log"}


def counters_in_words(counts: dict[str, int]) -> str:
    """``3 late events, 2 waits for the log (171 ms)``: a run's counters (base.COUNTERS) in words."""
    parts = []
    for name, n in sorted(counts.items()):
        if not n or name == "report_wait_ns":
            continue
        if name == "spin_ns":  # (CPU spent by choice: configure(spin=))
            parts.append(f"{n / 1e9:.3g} s busy-waiting for ticks (spin)")
            continue
        part = f"{n} {_COUNTER_LABELS.get(name, name)}"
        if name == "report_waits" and counts.get("report_wait_ns"):
            part += f" ({counts['report_wait_ns'] / 1e6:.0f} ms)"
        parts.append(part)
    return ", ".join(parts)


@app.command("ir")
def ir_command(
    target: Annotated[str, typer.Argument(metavar="FILE[:ATTR]|IR.json|LOG.mcap",
                                          help="Python file (and Pipeline name), an IR .json, or a log")],
    format: Annotated[str, typer.Option("--format", "-f", help="json, dot or mermaid.")] = "json",
    out: Annotated[Optional[Path], typer.Option("--out", "-o", help="Write here instead of stdout.")] = None,
) -> None:
    """Compile a pipeline to its IR (or a DOT / Mermaid picture of it). An IR file or a log (the
    IR it holds) is read and checked, never imported: nothing of the user's code runs."""
    if format not in ("json", "dot", "mermaid"):
        _fail(RetrieverError(f"unknown format {format!r}\n    hint: use --format json, dot or mermaid"))
    try:
        if target.endswith(".mcap"):
            ir = _read(Path(target)).ir
        elif target.endswith(".json"):
            ir = IR.load(target)
        else:
            ir = _load(target).build_ir()
        text = ir.to_json() if format == "json" else ir.visualize(format)
    except typer.Exit:
        raise
    except Exception as exc:
        _fail(exc)
    if out is None:
        sys.stdout.write(text)
    else:
        out.write_text(text, encoding="utf-8")
        _err.print(f"wrote {out}", highlight=False)


# ---------------------------------------------------------------------------------------------
# Logs
# ---------------------------------------------------------------------------------------------
log_app = typer.Typer(no_args_is_help=True, help="Inspect, print and recover MCAP event logs.")
app.add_typer(log_app, name="log")


def _read(path: Path, salvage: bool = False):
    from .log import read_log

    try:
        return read_log(path, salvage=salvage)
    except Exception as exc:
        _fail(exc)


@app.command()
def replay(
    path: Annotated[Path, typer.Argument(metavar="LOG.mcap", help="A log written by run --log / pipe.run(log=).")],
    pipeline: Annotated[Optional[str], typer.Option(metavar="FILE[:ATTR]",
                                                    help="Replay this pipeline instead of the log's IR.")] = None,
    resim: Annotated[bool, typer.Option("--resim", help="Re-run the whole graph from the logged sources.")] = False,
) -> None:
    """Re-execute a logged run and compare every output byte for byte (exit 0 only if identical)."""
    from rich.progress import Progress

    from .replay import replay as replay_log, resim as resim_log

    log = _read(path)
    pipe = None if pipeline is None else _load(pipeline)
    try:
        if resim:
            result = resim_log(log, pipe)
        else:
            with Progress(console=_err, transient=True, disable=not _err.is_terminal) as bar:
                task = bar.add_task("replaying", total=None)
                result = replay_log(log, pipe, progress=lambda done, total: bar.update(task, completed=done, total=total))
    except Exception as exc:
        _fail(exc)
    source = f"--pipeline {pipeline}" if pipeline else "the IR in the log"
    if resim:
        _out.print(f"re-simulated {path} to t={result.horizon_ns / 1e9:g} s with {source}: "
                   f"{result.steps_compared} steps and {result.events_compared} events compared", highlight=False)
        if result.identical:
            _out.print("[bold green]identical[/]: the log is one run of this graph", markup=True)
            return
        _out.print(f"[bold red]DIVERGED[/]: {escape(_visible(str(result.difference)))}"
                   + "".join(f"\n  {escape(_visible(change))}, which may be why" for change in result.code_changes),
                   highlight=False, markup=True)
        raise typer.Exit(code=1)
    table = Table(title=f"replay of {path} ({source})", title_justify="left")
    for col in ("node", "steps", "replayed", "identical", "divergent"):
        table.add_column(col, justify="left" if col == "node" else "right")
    for node, n in result.nodes.items():
        if n.from_log:
            table.add_row(_cell(node), str(n.steps), "from the log", "", "")
        else:
            table.add_row(_cell(node), str(n.steps), str(n.replayed), str(n.identical),
                          Text(str(n.divergent), style="bold red") if n.divergent else "0")
    _out.print(table)
    if result.identical:
        cut = sum(n.cut for n in result.nodes.values())
        lost = sum(n.lost for n in result.nodes.values())
        notes = ([f"{cut} at the end not compared: the log was cut short and lost events they consumed or produced"]
                 if cut else []) + ([f"{lost} not compared: their outputs died unpublished with their process "
                                     "(retriever log info shows the fault)"] if lost else [])
        _out.print(f"[bold green]identical[/]: {result.steps_replayed} steps replayed, every output byte for byte"
                   + "".join(f" ({note})" for note in notes), markup=True)
        return
    _out.print(f"[bold red]DIVERGED[/]: {result.divergent_steps} of {result.steps_replayed} replayed steps differ"
               f"{escape(_visible(_code_changed(result.code_changes)))}. "
               f"First:\n  {escape(_visible(str(result.divergences[0])))}", highlight=False, markup=True)
    raise typer.Exit(code=1)


def _code_changed(changes: list[str]) -> str:
    """The flow modules edited since the run, for a DIVERGED line: the likely cause."""
    return "".join(f"; {change}" for change in changes)


@log_app.command("info")
def log_info(path: Annotated[Path, typer.Argument(metavar="LOG.mcap")]) -> None:
    """Nodes, ports, counts, rates, time span, step statuses and run metadata of a log."""
    from .log.reader import run_info

    log = _read(path)
    try:
        _print_info(path, log, run_info(log))
    except Exception as exc:  # a damaged or forged log: its records or metadata do not parse
        _fail(exc)


def _print_info(path: Path, log, info: dict) -> None:
    run, end = log.run, log.end or {}
    state = _file_state(log)
    lines = [("file", f"{path} ({path.stat().st_size / 1e6:.2f} MB, {state})"),
             ("pipeline", run.get("pipeline", "?")), ("backend", run.get("backend", "?")),
             ("status", end.get("status", "?") + (f": {end['error']}" if end.get("error") else "")),
             ("virtual end", f"{int(end['end_ns']) / 1e9:g} s" if "end_ns" in end else "?"),
             ("git", run.get("git_revision") or (f"? ({run['git_error']})" if run.get("git_error") else "?")),
             ("host", run.get("host", "?")), ("code", _code_line(log)),
             ("python", run.get("python", "?")), ("seeds", run.get("seeds", "{}")),
             ("packages", ", ".join(f"{k} {v}" for k, v in sorted(info["packages"].items()))),
             ("command", " ".join(map(str, _metadata_json(path, "command_line", run.get("command_line", "[]"), list))))]
    if end.get("counts"):
        lines.insert(4, ("counted", counters_in_words(_metadata_json(path, "counts", end["counts"], dict))))
    for i, fault in enumerate(log.faults):  # a process that died: what became of its flow
        what = "restarted afresh" if fault.get("restarted") == "true" else "not restarted"
        lost = f", {len(fault['lost_events'])} unpublished output(s) lost" if fault["lost_events"] else ""
        lines.insert(5 + i, ("fault", f"{fault['node']}: its process (pid {fault.get('pid', '?')}) "
                                      f"{fault.get('exit', 'died')} at t={int(fault.get('at_ns', '0')) / 1e9:g} s; "
                                      f"{what}{lost}"))
    faults = len(log.faults)
    for i, episode in enumerate(log.starved):  # an input that had no event while its producers made some
        lines.insert(5 + faults + i, ("starved", describe_starved(episode)))
    for key, value in lines:
        _out.print(Text.assemble((f"{key:>12}", "bold"), "  ", _visible(str(value))), highlight=False)
    table = Table(title="channels", title_justify="left")
    for col in ("topic", "type", "messages", "first (s)", "last (s)", "rate (Hz)"):
        table.add_column(col, justify="left" if col in ("topic", "type") else "right")
    for channel in sorted(log.channels.values(), key=lambda c: c.topic):
        count = info["counts"].get(channel.topic, 0)
        lo, hi = info["span"].get(channel.topic, (0, 0))
        rate = f"{(count - 1) / ((hi - lo) / 1e9):.4g}" if count > 1 and hi > lo else ""
        table.add_row(_cell(channel.topic), _cell(channel.metadata.get("type", "")), str(count),
                      f"{lo / 1e9:g}" if count else "", f"{hi / 1e9:g}" if count else "", rate)
    _out.print(table)
    statuses = Table(title="steps by status", title_justify="left")
    names = sorted({s for node in info["statuses"].values() for s in node})
    statuses.add_column("node")
    for name in names:
        statuses.add_column(_cell(name), justify="right")
    for node, counts in sorted(info["statuses"].items()):
        statuses.add_row(_cell(node), *(str(counts.get(name, 0)) for name in names))
    _out.print(statuses)


def _file_state(log) -> str:
    """What ``log info`` says of a file that reads to its end: it is a complete MCAP file (what
    ``log recover`` checks), and whether the run it holds ended."""
    from .log.format import RECOVERED_METADATA

    if log.damage is not None:  # read whole, but its footer or summary is not what indexed readers need
        return f"damaged: {log.damage}; retriever log recover writes a whole copy"
    if RECOVERED_METADATA in log.metadata:
        return (f"complete, recovered from {log.metadata[RECOVERED_METADATA].get('source')}: the run was cut short "
                "(no end record)")
    if not log.run:
        return "complete, not written by Retriever (no retriever.run record)"
    return "complete" if log.end else "complete, but its run has no end record (was the run cut short?)"


def _code_line(log) -> str:
    """The sha256 of each flow module's file as the run's IR recorded it (its first 16 digits)."""
    from .errors import LogError

    try:
        hashes = log.ir.doc["metadata"].get("code_sha256", {})
    except LogError:  # log info still shows what it can of a log whose IR is damaged
        return "? (the log's IR is invalid)"
    return ", ".join(f"{module} sha256 {digest[:16]}…" for module, digest in sorted(hashes.items())) or "?"


def _metadata_json(path: Path, key: str, text: str, kind: type):
    """A JSON value of the log's metadata, or a LogError naming the file and the key."""
    from .errors import LogError

    try:
        value = json.loads(text)
    except (TypeError, ValueError):
        value = None
    if not isinstance(value, kind):
        raise LogError(f"{path}: its metadata '{key}' is not a JSON {kind.__name__} ({str(text)[:60]!r})",
                       "the file was changed after it was written")
    return value


@log_app.command("cat")
def log_cat(
    path: Annotated[Path, typer.Argument(metavar="LOG.mcap")],
    node: Annotated[Optional[str], typer.Option(help="Only this node's events.")] = None,
    port: Annotated[Optional[str], typer.Option(help="Only this output port.")] = None,
    steps: Annotated[bool, typer.Option("--steps", help="Print step records instead of events.")] = False,
    limit: Annotated[Optional[int], typer.Option(help="Print at most this many.")] = None,
    brief: Annotated[bool, typer.Option("--brief", help="Arrays as their dtype and shape, not their values.")] = False,
    full: Annotated[bool, typer.Option("--full", help="Arrays whole (by default one of more than 16 elements is "
                                                      "its dtype, shape and range).")] = False,
    as_json: Annotated[bool, typer.Option("--json", help="One JSON object per line (arrays up to 1024 elements "
                                                         "as lists, bigger ones summarised).")] = False,
    start: Annotated[Optional[float], typer.Option("--from", metavar="S", help="Only tags at or after S s.")] = None,
    end: Annotated[Optional[float], typer.Option("--to", metavar="S", help="Only tags before S s.")] = None,
) -> None:
    """Print decoded events (or step records), in tag order."""
    import json

    from .log.foxglove import to_json
    from .log.show import show_value
    from .time import format_tag, seconds_problem

    if brief and full:
        _fail(RetrieverError("--brief and --full ask for arrays both ways\n    hint: pass one of them"))
    arrays = "brief" if brief else "full" if full else "summary"
    for flag, seconds in (("--from", start), ("--to", end)):
        problem = None if seconds is None else seconds_problem(flag, seconds)
        if problem is not None:
            _fail(RetrieverError(f"{problem}\n    hint: seconds from the run's start, e.g. {flag} 1.5"))
    if limit is not None and limit < 0:
        _fail(RetrieverError(f"--limit {limit}: expected a count >= 0"))
    log = _read(path)
    lo = None if start is None else round(start * 1e9)
    hi = None if end is None else round(end * 1e9)

    def in_range(tag) -> bool:
        return (lo is None or tag[0] >= lo) and (hi is None or tag[0] < hi)

    def say(text: str) -> None:
        _out.print(text, highlight=False, markup=False, soft_wrap=True)

    shown = 0
    try:
        if steps:
            records = sorted((s for s in log.iter_steps() if (node is None or s.node == node) and in_range(s.tag)),
                             key=lambda s: (s.tag, s.node))
            for s in records[:limit]:
                if as_json:
                    say(json.dumps({"tag_ns": s.tag[0], "microstep": s.tag[1], "node": s.node, "status": s.status,
                                    "consumed": {p: [list(i) for i in ids] for p, ids in s.consumed.items()},
                                    "produced": [list(i) for i in s.produced], "detail": to_json(s.detail),
                                    "wall_ns": s.wall_ns}))
                else:
                    consumed = {p: [f"{n}.{q}#{i}" for n, q, i in ids] for p, ids in s.consumed.items()}
                    produced = [f"{n}.{q}#{i}" for n, q, i in s.produced]
                    extra = f" {s.detail}" if s.detail else ""
                    say(f"{format_tag(s.tag)}  {s.node}  {s.status}{extra}  consumed={consumed} produced={produced} "
                        f"wall={s.wall_ns / 1e3:.1f}µs")
                shown += 1
        else:
            events = sorted((e for e in log.iter_events() if (node is None or e.node == node)
                             and (port is None or e.port == port) and in_range(e.tag)),
                            key=lambda e: (e.tag, e.node, e.port, e.seq))
            for e in events[:limit]:
                value = log.value(e, keep_unregistered=True)
                if as_json:
                    say(json.dumps({"tag_ns": e.tag[0], "microstep": e.tag[1], "node": e.node, "port": e.port,
                                    "seq": e.seq, "value": show_value(value, arrays) if brief else to_json(value)}))
                else:
                    say(f"{format_tag(e.tag)}  {e.node}.{e.port} #{e.seq}  {show_value(value, arrays)}")
                shown += 1
    except Exception as exc:
        _fail(exc)
    if shown == 0:
        known = sorted({f"{c.metadata.get('node')}.{c.metadata.get('port')}" for c in log.channels.values()
                        if c.metadata.get("node")})
        what = (f"the log's ports are: {', '.join(known)}" if known and not steps
                else "the log has no step records" if steps and not any(True for _ in log.iter_steps())
                else "the log has no Retriever events" if not known else "no step record in that range or of that node")
        _err.print(f"nothing matched; {what}", highlight=False)


@log_app.command("recover")
def log_recover(
    path: Annotated[Path, typer.Argument(metavar="LOG.mcap", help="A log whose writer was killed or that was damaged.")],
    out: Annotated[Optional[Path], typer.Option("--out", "-o", help="Default: LOG.recovered.mcap.")] = None,
    force: Annotated[bool, typer.Option("--force", help="Overwrite the output file if it exists.")] = False,
) -> None:
    """Rebuild a readable log from one whose writer was killed (everything before the damage)."""
    from .log import recover

    try:
        result = recover(path, out, overwrite=force)
    except Exception as exc:
        _fail(exc)
    if result.output is None:
        _out.print(f"{path} is complete and undamaged; nothing to recover", highlight=False)
        return
    _out.print(f"recovered {result.events} events and {result.steps} steps into {result.output}\n"
               f"  {path}: {result.damage}\n  next: retriever replay {result.output}", highlight=False)


@log_app.command("export")
def log_export(
    paths: Annotated[list[Path], typer.Argument(metavar="LOG.mcap...", help="Logs written by run --log / "
                                                "pipe.run(log=); a dataset takes several (one episode each).")],
    format: Annotated[str, typer.Option("--format", help="foxglove: an MCAP with Foxglove's schemas; lerobot: a "
                                        "LeRobot dataset; npz: the same frames as NumPy arrays.")] = "foxglove",
    out: Annotated[Path, typer.Option("--out", "-o", help="The file (foxglove) or folder (lerobot, npz) to "
                                      "write.")] = ...,
    force: Annotated[bool, typer.Option("--force", help="Overwrite the output if it exists.")] = False,
    flow: Annotated[Optional[str], typer.Option("--flow", metavar="NODE", help="lerobot, npz: the Rate flow whose "
                                                "ticks are the frames.")] = None,
    maps: Annotated[Optional[list[str]], typer.Option("--map", metavar="PORT=KEY", help="Name a port's feature "
                                                      "(repeatable): joints=observation.state; a text port =task "
                                                      "gives each frame's task.")] = None,
    task: Annotated[Optional[str], typer.Option("--task", metavar="TEXT", help="The task of every frame "
                                                "(default: the pipeline's name).")] = None,
    exclude: Annotated[Optional[list[str]], typer.Option("--exclude", metavar="PORT", help="Leave a port (or "
                                                         "PORT.FIELD) out of the frames (repeatable).")] = None,
    gaps: Annotated[str, typer.Option("--gaps", help="A gap between two frames (ticks that are no frame): refuse, "
                                      "or split the episode there.")] = "refuse",
    repo_id: Annotated[Optional[str], typer.Option("--repo-id", help="lerobot: the dataset's repo id (default: "
                                                   "retriever/<folder name>).")] = None,
) -> None:
    """Write a log for another tool. --format foxglove: a view that opens in the Foxglove app (images
    as RawImage, numbers as JSON it plots, the step records and the graph; wall-clock times; needs
    pip install 'retriever-robotics\\[foxglove]'). --format lerobot | npz --flow NODE: a training
    set, one frame per tick of a Rate flow: what it consumed and produced there (docs/learning.md;
    lerobot needs pip install 'retriever-robotics\\[lerobot]')."""
    if format in ("lerobot", "npz"):
        _export_dataset(paths, format, out, force, flow, maps or [], task, exclude or [], gaps, repo_id)
        return
    if format != "foxglove":
        _fail(RetrieverError(f"unknown export format {format!r}\n    hint: use --format foxglove, lerobot or npz"))
    if len(paths) != 1:
        _fail(RetrieverError(f"--format foxglove exports one log, got {len(paths)}\n    hint: export each apart"))
    from .log.foxglove import export_foxglove

    log = _read(paths[0])
    try:
        written = export_foxglove(log, out, overwrite=force)
    except Exception as exc:
        _fail(exc)
    _out.print(f"wrote {out}: {sum(written.values())} messages on {len(written)} topics; open it in the Foxglove app",
               highlight=False)


def _export_dataset(paths: list[Path], format: str, out: Path, force: bool, flow: str | None, maps: list[str],
                    task: str | None, exclude: list[str], gaps: str, repo_id: str | None) -> None:
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn

    from .log.dataset import export_dataset

    if flow is None:
        _fail(RetrieverError(f"--format {format} needs the flow whose ticks are the frames\n"
                             "    hint: --flow NODE (a flow on a Rate clock: retriever log info LOG lists them)"))
    columns = (TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(), TimeRemainingColumn())
    with Progress(*columns, console=_err, transient=True, disable=not _err.is_terminal) as bar:
        ticks = bar.add_task("reading", total=None)

        def progress(log: int, logs: int, done: int, total: int) -> None:
            bar.update(ticks, description=f"log {log + 1}/{logs}: ticks", completed=done, total=total)

        try:
            summary = export_dataset(paths, out, flow=flow, format=format, maps=maps, task=task, exclude=exclude,
                                     gaps=gaps, repo_id=repo_id, overwrite=force, progress=progress)
        except Exception as exc:
            _fail(exc)
    _out.print(str(summary), highlight=False, soft_wrap=True)


# ---------------------------------------------------------------------------------------------
# Workers on many machines (backends/zenoh/daemon.py)
# ---------------------------------------------------------------------------------------------
_SECRET_HELP = "A deployment secret file (>= 16 bytes, mode 600): only holders of it may join."
_INSECURE_HELP = "Join without a secret: anyone who reaches the endpoints may. Only for a lab on a trusted network."


def worker(
    name: Annotated[Optional[str], typer.Option(help="This worker's name, unique in its namespace.")] = None,
    labels: Annotated[Optional[str], typer.Option(metavar="A,B", help="Labels placement may ask for.")] = None,
    listen: Annotated[Optional[list[str]], typer.Option(
        metavar="ENDPOINT", help="Listen here (repeatable). Default: tcp/0.0.0.0:7447.")] = None,
    connect: Annotated[Optional[list[str]], typer.Option(metavar="ENDPOINT", help="Connect here (repeatable).")] = None,
    namespace: Annotated[Optional[str], typer.Option(help="The deployment's namespace (default: default).")] = None,
    path: Annotated[Optional[list[Path]], typer.Option(
        metavar="DIR", help="A folder flows are imported from; its modules are allowed (repeatable).")] = None,
    allow: Annotated[Optional[list[str]], typer.Option(
        metavar="MODULE_PATTERN",
        help="Also allow flow classes from modules matching this (fnmatch; repeatable).")] = None,
    secret: Annotated[Optional[Path], typer.Option(metavar="FILE", help=_SECRET_HELP)] = None,
    insecure: Annotated[bool, typer.Option("--insecure", help=_INSECURE_HELP)] = False,
    config: Annotated[Optional[Path], typer.Option(
        metavar="worker.toml", help="Settings from this TOML file (the same keys); flags override it.")] = None,
    lease: Annotated[Optional[float], typer.Option(
        metavar="SECONDS", help="How long a link that went silent (a partition) is kept: Zenoh's lease "
                                "(default 10; under about 3 s, a congested link's close can drop healthy links, "
                                "docs/deploy.md). A coordinator cut off for this long has its flows stopped.")] = None,
    tls_ca: Annotated[Optional[Path], _TLS_CA] = None,
    tls_cert: Annotated[Optional[Path], _TLS_CERT] = None,
    tls_key: Annotated[Optional[Path], _TLS_KEY] = None,
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
    from .backends.zenoh.daemon import load_settings, serve

    try:
        settings = load_settings(config, name=name, labels=labels, listen=listen, connect=connect,
                                 namespace=namespace, path=[str(p) for p in path] if path else None,
                                 allow=allow, secret=None if secret is None else str(secret), insecure=insecure,
                                 lease=lease, code_mismatch=code_mismatch, pass_env=pass_env,
                                 **{k: None if v is None else str(v) for k, v in
                                    (("tls_ca", tls_ca), ("tls_cert", tls_cert), ("tls_key", tls_key))})
        code = serve(settings)
    except Exception as exc:
        _fail(exc)
    raise typer.Exit(code=code)


app.command("worker")(worker)


# the options every command that joins a namespace takes (workers, status, stop)
_Secret = Annotated[Optional[Path], typer.Option(metavar="FILE", help=_SECRET_HELP)]
_Insecure = Annotated[bool, typer.Option("--insecure", help=_INSECURE_HELP)]
_TlsCa = Annotated[Optional[Path], _TLS_CA]
_TlsCert = Annotated[Optional[Path], _TLS_CERT]
_TlsKey = Annotated[Optional[Path], _TLS_KEY]
_Namespace = Annotated[str, typer.Option(help="The deployment's namespace.")]
_Through = Annotated[Optional[list[str]], typer.Option(
    metavar="ENDPOINT", help="A worker of the deployment to ask through (repeatable). Default: tcp/127.0.0.1:7447.")]


@app.command("workers")
def workers_command(
    connect: Annotated[Optional[list[str]], typer.Option(
        metavar="ENDPOINT", help="A worker (or a peer linked to workers) to ask (repeatable). "
                                 "Default: tcp/127.0.0.1:7447.")] = None,
    namespace: _Namespace = "default", secret: _Secret = None, insecure: _Insecure = False,
    tls_ca: _TlsCa = None, tls_cert: _TlsCert = None, tls_key: _TlsKey = None,
) -> None:
    """List the live workers of a namespace: labels, host, pid, version, clock offset, nodes.
    Exits 1 when it found none (nothing listens, another --secret, or no worker is up)."""
    from .backends.zenoh.daemon import DEFAULT_CONNECT, list_workers

    endpoints = connect or [DEFAULT_CONNECT]
    tls = _tls(tls_ca, tls_cert, tls_key)
    try:
        listing = list_workers(endpoints, namespace, None if secret is None else str(secret), insecure, tls)
    except Exception as exc:
        _fail(exc)
    for endpoint, why in listing.unreachable.items():
        _err.print(f"warning: no session at {endpoint}: {why}", highlight=False)
    if not listing.workers:
        # with TLS every endpoint is tls/ and each side names its CA, certificate and key
        scheme, files = ("tls", " --tls-ca CA --tls-cert CERT --tls-key KEY") if tls else ("tcp", "")
        _out.print(f"no workers in namespace '{namespace}' at {', '.join(endpoints)}\n"
                   f"  start one: retriever-worker --name NAME --namespace {namespace} --listen {scheme}/0.0.0.0:7447"
                   f"{files} --secret FILE, then: retriever workers --connect {scheme}/HOST:7447{files} --secret FILE",
                   highlight=False, soft_wrap=True)
        raise typer.Exit(code=1)  # a script waiting for its workers (`until retriever workers ...`) can tell
    _out.print(_workers_table(listing.workers, namespace))
    _err.print(f"(the workers linked to {', '.join(endpoints)}: a daemon is linked to those its --connect names and "
               "those whose --connect names it; list the others with a --connect each)", highlight=False)


@app.command("status")
def status_command(
    connect: _Through = None, namespace: _Namespace = "default", secret: _Secret = None, insecure: _Insecure = False,
    tls_ca: _TlsCa = None, tls_cert: _TlsCert = None, tls_key: _TlsKey = None,
) -> None:
    """Show the running deployment of a namespace, from any machine: per node its worker, state,
    ticks, steps, skips, errors and counters."""
    answer = _ask_deployment(connect, namespace, secret, insecure, "status", _tls(tls_ca, tls_cert, tls_key))
    _out.print(status_table(answer, namespace))


def status_table(answer: dict, namespace: str) -> Table:
    """A deployment's status (Deployment.status, maybe from the network: every cell plain
    text): per node its worker, state, rate achieved, steps, skips, errors, CPU and counters."""
    t_s = answer.get("t_ns", 0) / 1e9 if type(answer.get("t_ns")) is int else 0.0
    title = (f"{answer.get('pipeline')!s:.60} in namespace '{namespace}': "
             + (f"t = {t_s:.1f} of {answer.get('end_ns', 0) / 1e9:g} s" if answer.get("started") else "starting"))
    table = Table(title=Text(_visible(title)), title_justify="left")
    for col in ("node", "worker", "state", "rate (Hz)", "steps", "skips", "errors", "cpu", "counted"):
        table.add_column(col, justify="left" if col in ("node", "worker", "state", "counted") else "right")
    nodes = answer.get("nodes") if type(answer.get("nodes")) is dict else {}
    for node, n in sorted(nodes.items()):
        n = n if type(n) is dict else {}
        counts = n.get("counts") if type(n.get("counts")) is dict else {}
        ticks, cpu = n.get("ticks"), n.get("cpu_s")
        rate = f"{ticks / t_s:.1f}" if type(ticks) is int and t_s > 0 else ""
        load = f"{100 * cpu / t_s:.0f}%" if type(cpu) in (int, float) and t_s > 0 else ""
        table.add_row(*(_cell(str(v)) for v in (node, n.get("worker"), n.get("state"), rate, n.get("steps"),
                                                 n.get("skips"), n.get("errors"), load)),
                      _cell(", ".join(f"{k} {v}" for k, v in sorted(counts.items()))))
    return table


@app.command("stop")
def stop_command(
    connect: _Through = None, namespace: _Namespace = "default", secret: _Secret = None, insecure: _Insecure = False,
    tls_ca: _TlsCa = None, tls_cert: _TlsCert = None, tls_key: _TlsKey = None,
) -> None:
    """Stop the running deployment of a namespace, from any machine, as Ctrl-C at its coordinator
    would: every node stops, its log is finished; the workers stay up."""
    answer = _ask_deployment(connect, namespace, secret, insecure, "stop", _tls(tls_ca, tls_cert, tls_key))
    _out.print(f"stopping deployment {_visible(str(answer.get('pipeline')))!s:.60} in namespace '{namespace}'",
               highlight=False)


def _ask_deployment(connect, namespace: str, secret, insecure: bool, op: str, tls=None) -> dict:
    from .backends.zenoh.daemon import DEFAULT_CONNECT
    from .backends.zenoh.deploy import ask_deployment

    endpoints = connect or [DEFAULT_CONNECT]
    try:
        answer = ask_deployment(endpoints, namespace, op, secret, insecure, tls)
    except Exception as exc:
        _fail(exc)
    if answer is None:
        _fail(RetrieverError(f"no deployment runs in namespace '{namespace}' at {', '.join(endpoints)}\n"
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
            table.add_row(_cell(w.name), Text(_visible(w.error or "no answer"), style="red"), "", "", "", "", "")
            continue
        info = w.info
        offset = "?" if w.offset_ns is None else f"{w.offset_ns / 1e6:+.2f} ms"
        packages = info.get("packages") if isinstance(info.get("packages"), dict) else {}
        labels = ", ".join(map(str, info.get("labels") or [])) or "-"
        nodes = ", ".join(map(str, info.get("nodes") or [])) or "-"
        table.add_row(_cell(w.name), _cell(labels), _cell(info.get("host", "?")), _cell(info.get("pid", "?")),
                      _cell(packages.get("retriever", "?")), offset, _cell(nodes))
    return table


def worker_main() -> None:
    """``retriever-worker``: the same command as ``retriever worker``."""
    _state["debug"] = _take_debug(sys.argv)
    standalone = typer.Typer(add_completion=False)
    standalone.command()(worker)
    standalone()


# ---------------------------------------------------------------------------------------------
# Deployment secrets
# ---------------------------------------------------------------------------------------------
secret_app = typer.Typer(no_args_is_help=True, help="Deployment secrets: who may join a zenoh run.")
app.add_typer(secret_app, name="secret")


@secret_app.command("new")
def secret_new(
    path: Annotated[Path, typer.Argument(metavar="FILE", help="Where to write the secret, e.g. lab.key.")],
    force: Annotated[bool, typer.Option("--force", help="Replace FILE if it exists.")] = False,
) -> None:
    """Write a fresh deployment secret (random, mode 0600) for retriever run --secret FILE."""
    from .backends.zenoh.access import SECRET_NEW_BYTES, new_secret

    try:
        new_secret(path, overwrite=force)
    except Exception as exc:
        _fail(exc)
    _out.print(f"wrote a new deployment secret to {path} ({SECRET_NEW_BYTES} random bytes as hex text, mode 600)\n"
               f"  use it: retriever run SCRIPT.py --backend zenoh --secret {path} [--namespace NS]  "
               f"(in Python: pipe.run(backend=\"zenoh\", secret=\"{path}\"))\n"
               f"  every machine of the deployment needs this same file: copy it privately (scp; never a chat or "
               f"a repository) and keep it mode 600", highlight=False, soft_wrap=True)


def main() -> None:
    _add_registered_commands()
    _default_foxglove_port(sys.argv)
    if _take_debug(sys.argv):
        sys.argv.insert(1, "--debug")  # where the option parser takes it: before the subcommand
    app()


def _take_debug(argv: list[str]) -> bool:
    """Remove every ``--debug`` from ``argv`` (up to a ``--``); whether there was one. Users add
    it where the error showed, at the end (``retriever run F --debug``), where no command has it."""
    end = argv.index("--") if "--" in argv else len(argv)
    found = "--debug" in argv[1:end]
    argv[1:end] = [arg for arg in argv[1:end] if arg != "--debug"]
    return found


def _default_foxglove_port(argv: list[str]) -> None:
    """`--foxglove` may come without its port (it takes FOXGLOVE_PORT then): give it one, as
    the option parser wants a value."""
    for i, arg in enumerate(argv):
        if arg == "--foxglove" and (i + 1 == len(argv) or not argv[i + 1].isdigit()):
            argv.insert(i + 1, str(FOXGLOVE_PORT))
            return


if __name__ == "__main__":
    main()
