"""What a replay runs before its first step: the pipeline (the one given, or the one rebuilt from
the log's IR), the flows it re-executes set up, and the code it loaded compared with the run's."""

from __future__ import annotations

import json
import os
import warnings
from typing import Callable

from ..backends.inproc import InprocSession
from ..code import code_mismatches
from ..errors import IRError, LogError, RetrieverWarning, SetupError
from ..flow.core import settings_of
from ..log.reader import LogHead, RunLog, ScannedLog, scan_log
from ..pipeline import Pipeline


def pipeline_for(log: LogHead, pipeline: Pipeline | None = None,
                 logged_nodes: Callable[[], set[str]] | None = None) -> Pipeline:
    """The pipeline to replay: the given one (its flows reset to their initial state), or the
    one rebuilt from the log's IR. It must have every node the log has steps of
    (``logged_nodes()``; by default read from ``log.iter_steps()``)."""
    if pipeline is None:
        script = _script_that_ran(log)
        if script is not None:  # the fix first: an IR's advice (`retriever ir`) is no fix for a replay
            raise LogError(f"cannot rebuild the pipeline from the IR in {log.path}: its flows live in the script "
                           f"that ran ({script}), whose __main__ no other process can import",
                           f"retriever replay {log.path} --pipeline {script} "
                           "(FILE:ATTR when the script has more than one pipeline)")
        log.add_import_paths()
        try:
            pipeline = Pipeline.from_ir(log.ir)
        except IRError as e:
            raise LogError(f"cannot rebuild the pipeline from the IR in {log.path}: {e}",
                           "pass the pipeline that wrote the log with --pipeline FILE[:ATTR] (a class that moved or "
                           "was renamed too)") from None
    else:
        pipeline.reset()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RetrieverWarning)  # the original run already showed them
        graph = pipeline.compile()
    nodes = {s.node for s in log.iter_steps()} if logged_nodes is None else logged_nodes()
    unknown = sorted(nodes - set(graph.nodes))
    if unknown:
        raise LogError(f"{log.path} has steps of node(s) {', '.join(unknown)}, which pipeline "
                       f"'{graph.name}' does not have (it has: {', '.join(sorted(graph.nodes))})",
                       "replay with the pipeline that wrote the log")
    return pipeline


def _script_that_ran(log: RunLog) -> str | None:
    """The script whose ``__main__`` holds the log's flows (``python script.py``: no other
    process can import it), as the log's run metadata names it (a hostile log's text, only
    shown); None when no flow lives in ``__main__`` or the metadata names no script."""
    if not any(str(node.get("type", "")).startswith("__main__:") for node in log.ir.nodes):
        return None
    try:
        argv, cwd = json.loads(log.run.get("command_line", "[]")), log.run.get("cwd", "")
        first = argv[0] if type(argv) is list and argv else None
        return os.path.join(cwd, first) if type(first) is str and first.endswith(".py") else None
    except (ValueError, TypeError, AttributeError):
        return None


def set_up_flows(session: InprocSession, logged: frozenset[str]) -> None:
    """Set up the flows the replay steps; a setup() that raises says the replay could not start
    (what the run needed is missing here: a checkpoint moved, a device)."""
    try:
        session.set_up(skip=logged)
    except SetupError as exc:
        raise SetupError(exc.node, exc.__cause__, replay=True) from exc.__cause__


def code_changes(log: RunLog, graph) -> list[str]:
    """How the files of the flow modules replayed differ from those the run's IR recorded, one a
    line; each is also warned of (RetrieverWarning), before anything is compared."""
    recorded = log.ir.doc["metadata"].get("code_sha256", {})
    changes = code_mismatches(recorded, {type(node.flow).__module__ for node in graph.nodes.values()})
    changes += ran_other_code(log)
    for change in changes:
        warnings.warn(f"{change}: what the replay finds different may come from that change", RetrieverWarning,
                      stacklevel=3)
    return changes


#: the most of a worker's word on the code it ran that a replay shows (a hostile log's text)
MAX_SAID = 400


def ran_other_code(log: RunLog) -> list[str]:
    """What the workers of a deployment said of the code they ran anyway (``--code-mismatch
    warn``), as the log's run metadata records it: the run itself ran other code than the IR's.
    A hostile log's text: only shown, shortened, and anything not of the recorded shape ignored."""
    try:
        said = json.loads(log.run.get("deployment", "{}")).get("ran_other_code", {})
    except (ValueError, AttributeError, RecursionError):
        return []
    if type(said) is not dict:
        return []
    return [f"in the run, worker '{worker:.60}' ran {text[:MAX_SAID]}" for worker, texts in sorted(said.items())
            if type(worker) is str and type(texts) is list for text in texts if type(text) is str]


def from_the_log(graph) -> frozenset[str]:
    """The nodes a replay does not re-execute: their outputs come from the log. Sources, and
    flows configured with ``replay="log"`` (their step consults the world outside the program)."""
    return frozenset(nid for nid, node in graph.nodes.items()
                     if not node.inputs or settings_of(node.flow).replay == "log")


def surveyed(path: str | os.PathLike, survey, pipeline: Pipeline | Callable[[], Pipeline] | None,
             progress: Callable[[str, int, int], None] | None
             ) -> tuple[ScannedLog, Pipeline | None, Callable[[int, int], None] | None]:
    """The first reading of a log file that is replayed or re-simulated streamed: ``survey`` (a
    LogSurvey, or a ResimSurvey) takes its messages, a chunk's as arrays where it can, as the file is
    checked, ``progress("reading", bytes, size)`` told; then ``pipeline`` made, if it is a function
    that makes it (after the log read: one that cannot be read is said first). Returns the scanned
    log, the pipeline and what to tell of the steps (``progress("replaying", ...)``)."""
    read = None if progress is None else (lambda done, total: progress("reading", done, total))
    log = scan_log(path, survey.take, progress=read, take_chunk=survey.take_chunk)
    if callable(pipeline):
        pipeline = pipeline()
    steps = None if progress is None else (lambda done, total: progress("replaying", done, total))
    return log, pipeline, steps
