"""``retriever log info``: what a log holds, line by line and in tables: the run, what befell its
processes, which worker ran each node, its channels and its steps by status."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Annotated

import typer
from rich.table import Table
from rich.text import Text

from ..starved import describe_starved
from . import console
from .console import cell, fail, visible
from .inputs import read
from .summary import counters_in_words


def log_info(path: Annotated[Path, typer.Argument(metavar="LOG.mcap")]) -> None:
    """Nodes, ports, counts, rates, time span, step statuses and run metadata of a log (of a
    deployment's: which worker ran each node, and where a node moved when its worker was lost)."""
    from ..log.reader import run_info

    log = read(path)
    try:
        _print_info(path, log, run_info(log))
    except Exception as exc:  # a damaged or forged log: its records or metadata do not parse
        fail(exc)


def _print_info(path: Path, log, info: dict) -> None:
    for key, value in _info_lines(path, log, info):
        console.out.print(Text.assemble((f"{key:>12}", "bold"), "  ", visible(str(value))), highlight=False)
    table = Table(title="channels", title_justify="left")
    for col in ("topic", "type", "messages", "first (s)", "last (s)", "rate (Hz)"):
        table.add_column(col, justify="left" if col in ("topic", "type") else "right")
    for channel in sorted(log.channels.values(), key=lambda c: c.topic):
        count = info["counts"].get(channel.topic, 0)
        lo, hi = info["span"].get(channel.topic, (0, 0))
        rate = f"{(count - 1) / ((hi - lo) / 1e9):.4g}" if count > 1 and hi > lo else ""
        table.add_row(cell(channel.topic), cell(channel.metadata.get("type", "")), str(count),
                      f"{lo / 1e9:g}" if count else "", f"{hi / 1e9:g}" if count else "", rate)
    console.out.print(table)
    statuses = Table(title="steps by status", title_justify="left")
    names = sorted({s for node in info["statuses"].values() for s in node})
    statuses.add_column("node")
    for name in names:
        statuses.add_column(cell(name), justify="right")
    for node, counts in sorted(info["statuses"].items()):
        statuses.add_row(cell(node), *(str(counts.get(name, 0)) for name in names))
    console.out.print(statuses)


def _info_lines(path: Path, log, info: dict) -> list[tuple[str, str]]:
    """The ``key  value`` lines ``log info`` begins with: the run, what befell its processes
    (faults, moves, starved inputs) and, of a deployment, which worker ran each node."""
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
    deployment = log.deployment
    moves = [("moved", _move_line(move)) for move in deployment.moves] if deployment else []
    lines[5:5] = [*_fault_lines(log), *moves, *(("starved", describe_starved(e)) for e in log.starved)]
    if deployment:
        after_host = next(i for i, (key, _) in enumerate(lines) if key == "host") + 1
        lines[after_host:after_host] = _deployment_lines(deployment)
    return lines


def _fault_lines(log) -> list[tuple[str, str]]:
    """A process that died: what became of its flow."""
    lines = []
    for fault in log.faults:
        what = "restarted afresh" if fault.get("restarted") == "true" else "not restarted"
        lost = f", {len(fault['lost_events'])} unpublished output(s) lost" if fault["lost_events"] else ""
        at = int(fault.get("at_ns", "0")) / 1e9
        lines.append(("fault", f"{fault['node']}: its process (pid {fault.get('pid', '?')}) "
                               f"{fault.get('exit', 'died')} at t={at:g} s; {what}{lost}"))
    return lines


def _move_line(move) -> str:
    """``relay: worker 'gpu-box' was lost at t=2.5 s; the node started afresh on worker 'spare'``."""
    where = "on it once it was back" if move.to == move.left else f"on worker '{move.to}'"
    return f"{move.node}: worker '{move.left}' was lost at t={move.at_ns / 1e9:g} s; the node started afresh {where}"


def _deployment_lines(deployment) -> list[tuple[str, str]]:
    """The deployment's namespace, then each worker: what it said of itself, and the nodes it
    ran (with when, for a node that moved to or from it)."""
    from ..log.deployment import WORKER_FIELDS

    names = sorted({*deployment.workers, *deployment.placed.values()})
    lines = [("deployment", f"namespace '{deployment.namespace}', {len(names)} worker(s)")]
    for name in names:
        said = deployment.workers.get(name, {})
        shown = [f"{key} {', '.join(map(str, value)) if type(value) is list else value}"
                 for key in WORKER_FIELDS if (value := said.get(key)) not in (None, [], "")]
        nodes = ", ".join(map(_span_text, deployment.spans_on(name))) or "no node"
        lines.append(("worker", f"{name}" + (f" ({', '.join(shown)})" if shown else "") + f": ran {nodes}"))
    return lines


def _span_text(span) -> str:
    """``relay``, ``relay (until t=2.5 s)``, ``relay (from t=2.5 s)``: a node a worker ran, and when."""
    when = ([f"from t={span.from_ns / 1e9:g} s"] if span.from_ns is not None else []) + \
        ([f"until t={span.until_ns / 1e9:g} s"] if span.until_ns is not None else [])
    return span.node + (f" ({' '.join(when)})" if when else "")


def _file_state(log) -> str:
    """What ``log info`` says of a file that reads to its end: it is a complete MCAP file (what
    ``log recover`` checks), and whether the run it holds ended."""
    from ..log.format import RECOVERED_METADATA

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
    from ..errors import LogError

    try:
        hashes = log.ir.doc["metadata"].get("code_sha256", {})
    except LogError:  # log info still shows what it can of a log whose IR is damaged
        return "? (the log's IR is invalid)"
    return ", ".join(f"{module} sha256 {digest[:16]}…" for module, digest in sorted(hashes.items())) or "?"


def _metadata_json(path: Path, key: str, text: str, kind: type):
    """A JSON value of the log's metadata, or a LogError naming the file and the key."""
    from ..errors import LogError

    try:
        value = json.loads(text)
    except (TypeError, ValueError):
        value = None
    if not isinstance(value, kind):
        raise LogError(f"{path}: its metadata '{key}' is not a JSON {kind.__name__} ({str(text)[:60]!r})",
                       "the file was changed after it was written")
    return value
