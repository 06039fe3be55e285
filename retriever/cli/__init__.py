"""The ``retriever`` command: thin — parse, call the public API, format results and errors.

This package holds the typer app and the entry points (``retriever``, ``retriever-worker``); the
commands live by family, each module with one job:

    console.py      where commands print (out, err) and how they fail (fail)
    options.py      options several commands share (--keep, --foxglove, --rerun, TLS, --secret)
    inputs.py       a pipeline or a log read, or the command fails
    pipelines.py    run, deploy, ir
    summary.py      a run's table and counters at its end; the errors that fail it
    logs.py         replay, log cat, log recover, log export
    log_info.py     log info
    deployments.py  workers, status, stop
    daemons.py      worker (retriever-worker), router, secret new
    plugins.py      commands other packages add (the retriever.commands entry points)

Commands are registered here, in the order ``retriever --help`` lists them.
"""

from __future__ import annotations

import os
import sys
from typing import Annotated

import typer

from .console import cleaning_up, err, fail, out, set_debug, stop_on_signals, stop_signal
from .daemons import router_command, secret_new, worker
from .deployments import status_command, status_table, stop_command, workers_command
from .log_info import log_info
from .logs import log_cat, log_export, log_recover, replay
from .options import FOXGLOVE_PORT, RERUN_URL
from .pipelines import LIVE_EVERY_S, UNTIL_STOPPED_S, deploy, ir_command, run
from .plugins import COMMANDS_GROUP, add_registered_commands
from .summary import counters_in_words, run_errors

__all__ = ["COMMANDS_GROUP", "FOXGLOVE_PORT", "LIVE_EVERY_S", "UNTIL_STOPPED_S", "app", "cleaning_up",
           "counters_in_words", "err", "fail", "main", "out", "run_errors", "status_table", "stop_on_signals",
           "stop_signal", "worker_main"]

app = typer.Typer(no_args_is_help=True, add_completion=False,
                  help="Retriever: closed-loop robot agents with explicit time.")


def _version(shown: bool) -> None:
    if shown:
        from ..log.format import package_versions

        # a checkout that was never installed has no version
        version = package_versions().get("retriever", "unknown (not installed: pip install -e .)")
        out.print(f"retriever {version}", highlight=False)
        raise typer.Exit()


@app.callback()
def _main(debug: Annotated[bool, typer.Option("--debug", help="Show tracebacks on errors (anywhere on the "
                                                                "command line).")] = False,
          version: Annotated[bool, typer.Option("--version", callback=_version, is_eager=True,
                                                help="Show the version and exit.")] = False) -> None:
    set_debug(debug)


app.command()(run)
app.command()(deploy)
app.command("ir")(ir_command)
log_app = typer.Typer(no_args_is_help=True, help="Inspect, print and recover MCAP event logs.")
app.add_typer(log_app, name="log")
app.command()(replay)
log_app.command("info")(log_info)
log_app.command("cat")(log_cat)
log_app.command("recover")(log_recover)
log_app.command("export")(log_export)
app.command("worker")(worker)
app.command("workers")(workers_command)
app.command("status")(status_command)
app.command("stop")(stop_command)
app.command("router")(router_command)
secret_app = typer.Typer(no_args_is_help=True, help="Deployment secrets: who may join a zenoh run.")
app.add_typer(secret_app, name="secret")
secret_app.command("new")(secret_new)


def main() -> None:
    add_registered_commands(app)
    _default_foxglove_port(sys.argv)
    _default_rerun_target(sys.argv)
    if _take_debug(sys.argv):
        sys.argv.insert(1, "--debug")  # where the option parser takes it: before the subcommand
    app()


def worker_main() -> None:
    """``retriever-worker``: the same command as ``retriever worker``."""
    set_debug(_take_debug(sys.argv))
    standalone = typer.Typer(add_completion=False)
    standalone.command()(worker)
    standalone()


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


def _default_rerun_target(argv: list[str]) -> None:
    """`--rerun` may come without its target (it takes RERUN_URL then): give it one, as the
    option parser wants a value. What follows is its target when it is a URL or an .rrd path, or a
    folder (no pipeline is one: the run refuses it as a target, saying which targets it takes)."""
    for i, arg in enumerate(argv):
        if arg == "--rerun" and (i + 1 == len(argv) or not _is_rerun_target(argv[i + 1])):
            argv.insert(i + 1, RERUN_URL)
            return


def _is_rerun_target(arg: str) -> bool:
    return (arg.lower().endswith(".rrd") or "://" in arg or arg.endswith(("/", os.sep))
            or os.path.isdir(arg))
