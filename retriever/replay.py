"""Re-execute a logged run and compare it with the log, byte for byte.

``replay`` (the default) isolates every flow: each logged step of a non-source node runs again
on inputs rebuilt from the *logged* events with the edge's policy, so one divergent node cannot
hide or cause divergence elsewhere. Per step it checks the consumed event ids against the log,
then the status, the produced ids and tags, and every output value's msgpack bytes.

What a real-time run did, the replay does: an event that reached a consumer late (after a tick
at or past its tag ran) goes in its buffer right before the consumer's record that names it,
as it did in the run, never earlier; a LET step whose deadline miss dropped its outputs has them
taken back (their seqs used again); a tick the run stopped before stepping is not stepped; and
``incomplete``, ``late`` and ``overrun`` steps compare as ``ok`` (the replay cannot be late).
A flow whose process died and was started afresh (on_error="restart") starts afresh at its first
record after (``restarted``: flow reset, input buffers emptied, events from where the new process
took each stream on); its consumers are withheld the dead process's events they never got
(``restart_gap``); and its steps whose outputs died with it (the log's fault records) are
re-executed but not compared.

Both first compare the sha256 of each flow module's file, as the run's IR recorded it, with the
file the replay loaded (retriever/code.py): a module edited since the run is warned of before any
value is compared, and named again in the report (``code_changes``), so that a divergence it
causes is not taken for nondeterminism.

``resim`` re-runs the whole graph in virtual time, with the sources emitting their logged events,
and compares the full trace: it proves the log is one consistent run of this graph.

Replay runs the pipeline and the in-process backend, so it sits above them, not in ``log/``.
"""

from __future__ import annotations

import bisect
import dataclasses
import json
import os
import warnings
from dataclasses import dataclass, field
from typing import Any, Callable

import numpy as np

from .backends.inproc import InprocSession
from .code import code_mismatches
from .codec import Encoder, unpackb
from .errors import IRError, LogError, ReplayedError, RetrieverWarning, RunEnded, SetupError, StepError
from .flow._base import settings_of
from .log.reader import LoggedEvent, RunLog
from .pipeline import Pipeline
from .time import format_tag
from .trace import STEPPED, StepRecord, Trace

MAX_DIVERGENCES_KEPT = 20
PROGRESS_EVERY = 2000


@dataclass
class Divergence:
    """One step whose replay differs from the log."""

    node: str
    tag: tuple[int, int]
    what: str  # "value", "inputs", "status", "outputs", "error", "tick" (a record at no tick of its clock)
    port: str | None
    logged: Any
    replayed: Any

    def __str__(self) -> str:
        where = f"{self.node}.{self.port}" if self.port else self.node
        text = (f"{where} at tick {format_tag(self.tag)}: {self.what} differs\n"
                f"      logged:   {_short(self.logged)}\n"
                f"      replayed: {_short(self.replayed)}")
        if self.what == "value":
            text += "".join(f"\n      {line}" for line in explain_difference(self.logged, self.replayed))
        return text


@dataclass
class NodeReplay:
    steps: int = 0  # logged steps of this node
    replayed: int = 0  # of those, re-executed (non-sources)
    identical: int = 0
    divergent: int = 0
    cut: int = 0  # re-executed, not compared: a log cut short lost their outputs (recovered, salvaged)
    lost: int = 0  # re-executed, not compared: their outputs died unpublished with their process (a fault)
    from_log: bool = False  # not re-executed: a source, or a flow configured with replay="log"


@dataclass
class ReplayReport:
    nodes: dict[str, NodeReplay] = field(default_factory=dict)
    divergences: list[Divergence] = field(default_factory=list)  # the first MAX_DIVERGENCES_KEPT
    divergent_steps: int = 0
    code_changes: list[str] = field(default_factory=list)  # flow modules whose file differs from the run's
    #: with ``replay(..., keep_trace=True)``: the run as replayed: every step record as logged (the
    #: replay checks the ids it names), the outputs of each re-executed step as the replay computed
    #: them, the others' from the log
    trace: Trace | None = field(default=None, repr=False)

    @property
    def identical(self) -> bool:
        return self.divergent_steps == 0

    @property
    def steps_replayed(self) -> int:
        return sum(n.replayed for n in self.nodes.values())


def pipeline_for(log: RunLog, pipeline: Pipeline | None = None) -> Pipeline:
    """The pipeline to replay: the given one (its flows reset to their initial state), or the
    one rebuilt from the log's IR."""
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
    logged_nodes = {s.node for s in log.iter_steps()}
    unknown = sorted(logged_nodes - set(graph.nodes))
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


def replay(log: RunLog, pipeline: Pipeline | None = None,
           progress: Callable[[int, int], None] | None = None, keep_trace: bool = False) -> ReplayReport:
    """Re-execute every non-source step of ``log``; see the module docstring. The flows are set
    up before the first step and torn down at the end, as in a run. ``keep_trace=True`` keeps
    the replayed run in ``report.trace`` (what an export of the replay reads: docs/learning.md)."""
    pipeline = pipeline_for(log, pipeline)
    graph = pipeline.compile()
    changes = code_changes(log, graph)
    session = InprocSession(graph)
    logged = from_the_log(graph)
    _set_up(session, logged)
    try:
        report = _replay(log, graph, session, logged, progress, keep_trace)
    finally:
        session.close()
    report.code_changes = changes
    return report


def _set_up(session: InprocSession, logged: frozenset[str]) -> None:
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


def _replay(log: RunLog, graph, session: InprocSession, sources: frozenset[str],
            progress: Callable[[int, int], None] | None, keep_trace: bool) -> ReplayReport:
    trace = session.trace
    encode = Encoder().pack
    steps = sorted(log.iter_steps(), key=lambda s: (s.tag, s.node))
    events, logged = _logged_events(log)
    deliveries, late_at = _deliveries(log, events, session.take_routes(), steps)
    # a lost process's outputs that its records claim and no report carried: not comparable (a
    # consumer may still have carried one in: that one is in the log, and compared)
    lost = {event_id for fault in log.faults for event_id in fault["lost_events"]} - logged.keys()
    floors: dict[tuple[str, str, str], int] = {}  # (consumer, producer, port) -> first seq it takes

    # In real time a flow without latency stamps its outputs when it finishes (ASAP): the tag
    # is then checked for causality (after the tick), not recomputed.
    realtime = log.run.get("backend", "inproc") != "inproc"
    stamped = {nid for nid, node in graph.nodes.items() if realtime and not node.settings.latency_ns}
    report = ReplayReport({nid: NodeReplay(from_log=nid in sources) for nid in sorted(graph.nodes)})
    # a log whose writer was killed, recovered or read with salvage=True, may keep a step record
    # (one chunk) and lose the events it consumed or produced (another): such a step cannot be compared
    cut_short = not log.complete or "retriever.recovered" in log.metadata
    kept = Trace() if keep_trace else None
    delivered = 0
    seen_ticks: set[tuple[str, tuple[int, int]]] = set()
    for i, step in enumerate(steps):
        if progress is not None and i % PROGRESS_EVERY == 0:
            progress(i, len(steps))
        stats = report.nodes[step.node]
        stats.steps += 1
        # a source is not re-executed: its records are checked against its clock (a forged
        # record between its ticks, or a second at one, is no step the run made)
        found = _off_clock(step, graph.nodes[step.node].clock, seen_ticks)
        if found is not None:
            _diverged(report, stats, found)
            continue
        restarted = (step.detail or {}).get("restarted")
        if restarted is not None:
            _restart_afresh(session, step.node, restarted, floors)
        for buf, entry in late_at.pop((step.node, step.tag), ()):
            buf.insert(entry)  # it arrived late: in the buffer from this record on, as in the run
        if kept is not None:
            kept.raw_steps.append(tuple(step))
        if step.node in sources or not _stepped(step):
            if kept is not None:  # not re-executed: its outputs as logged
                kept.raw_events.extend((e.tag, e.node, e.port, e.seq, log.value(e), e.publish_ns)
                                       for e in map(logged.get, step.produced) if e is not None)
            continue
        while delivered < len(deliveries) and deliveries[delivered][0] <= step.tag:
            _, consumer, buf, entry = deliveries[delivered]
            if not floors or entry[3] >= floors.get((consumer, entry[1], entry[2]), 0):
                buf.insert(entry)
            delivered += 1
        _execute(session, step)
        if kept is not None:
            kept.raw_events.extend(trace.raw_events)
        stats.replayed += 1
        if lost and not lost.isdisjoint(step.produced):
            stats.lost += 1
        elif cut_short and any(event_id not in logged for event_id in
                               (*step.produced, *(i for ids in step.consumed.values() for i in ids))):
            stats.cut += 1
        else:
            found = _compare(step, trace, logged, encode, step.node in stamped)
            if found is None:
                stats.identical += 1
            else:
                _diverged(report, stats, found)
    if progress is not None:
        progress(len(steps), len(steps))
    report.trace = kept
    return report


def _logged_events(log: RunLog) -> tuple[list[LoggedEvent], dict]:
    """The log's events in the order it holds them, and by id; an id logged twice is refused."""
    events = list(log.iter_events())
    logged = {e.id: e for e in events}
    if len(logged) < len(events):
        twice = next(e for i, e in enumerate(events) if any(e.id == f.id for f in events[:i]))
        raise LogError(f"{log.path}: event {twice.node}.{twice.port} #{twice.seq} is logged twice",
                       "the file is damaged or was edited: retriever replay reads logs as a run wrote them")
    return events, logged


def _deliveries(log: RunLog, events: list[LoggedEvent], routes: dict, steps: list) -> tuple[list, dict]:
    """Where each logged event goes: ``(arrival, consumer node, buffer, entry)`` in arrival order
    at each consumer (an edge's delay shifts it), but for the late ones: in real time they reached
    a consumer after a tick at or past their tag had run without them, so they go in its buffer
    right before the record that names them (the second result, by (consumer node, record tag)).
    An event a consumer never had (a restart's gap, an incomplete view) goes nowhere."""
    late = _late_events(steps)
    missed = _incomplete_views(steps)
    gaps = _restart_gaps(steps)
    late_at: dict[tuple[str, tuple[int, int]], list] = {}  # (consumer node, record tag) -> (buf, entry)
    deliveries = []
    for e in events:
        consumers = routes.get((e.node, e.port))
        if not consumers:
            continue
        value = log.value(e)
        for consumer, buf, delay_ns in consumers:
            if _in_gap(gaps.get(consumer), e):
                continue
            arrival = (e.tag[0] + delay_ns, 0) if delay_ns else e.tag
            entry = (arrival, e.node, e.port, e.seq, value)
            seen_at = late.get((consumer, e.id))
            if seen_at is not None:
                late_at.setdefault((consumer[0], seen_at), []).append((buf, entry))
            elif not _never_had(missed.get((consumer, e.node, e.port)), arrival, e.seq):
                deliveries.append((arrival, consumer[0], buf, entry))
    deliveries.sort(key=lambda d: d[0])
    return deliveries, late_at


def _execute(session: InprocSession, step) -> None:
    """Run the recorded tick again, its trace (only) in ``session.trace``."""
    trace = session.trace
    del trace.raw_events[:], trace.raw_steps[:]
    try:
        session.tick(step.node, step.tag)
    except (StepError, RunEnded):
        pass  # on_error="stop", or sys.exit(0): the step is recorded; compare it like any other
    if step.status == "late" and step.detail.get("on_deadline_miss") in ("drop", "error"):
        session.retract(step.node)  # the run dropped what this step returned


def _diverged(report: ReplayReport, stats: NodeReplay, found: Divergence) -> None:
    stats.divergent += 1
    report.divergent_steps += 1
    if len(report.divergences) < MAX_DIVERGENCES_KEPT:
        report.divergences.append(found)


def _off_clock(step, clock, seen: set[tuple[str, tuple[int, int]]]) -> Divergence | None:
    """The record at a tag where its node's clock has no tick, or at one it already recorded."""
    key = (step.node, step.tag)
    if not clock.may_tick_at(step.tag):
        return Divergence(step.node, step.tag, "tick", None, f"a record at {format_tag(step.tag)}",
                          f"no tick of {clock!r} there")
    if key in seen:
        return Divergence(step.node, step.tag, "tick", None, "a second record of this tick", "one record a tick")
    seen.add(key)
    return None


def _late_events(steps) -> dict[tuple[tuple[str, str], tuple[str, str, int]], tuple[int, int]]:
    """``((consumer node, port), event id)`` of every event that reached a real-time consumer
    late, to the tag of the consumer's record that names it (its ``late`` detail, ``{port:
    [event id, ...]}``): the first tick whose buffer had it."""
    return {((s.node, port), (node, out, seq)): s.tag
            for s in steps if s.detail and "late" in s.detail
            for port, ids in s.detail["late"].items() for node, out, seq in ids}


def _incomplete_views(steps) -> dict[tuple[tuple[str, str], str, str], tuple[list, list]]:
    """Per ``((consumer node, port), producer, producer port)``, the tags of the consumer's ticks
    that ran incomplete on it and, at each, the seq that stream's next event would have had
    (their ``had_below`` detail): the two lists in tag order."""
    views: dict[tuple[tuple[str, str], str, str], list] = {}
    for s in steps:
        for port, streams in ((s.detail or {}).get("had_below") or {}).items():
            for node, out, seq in streams:
                views.setdefault(((s.node, port), node, out), []).append((s.tag, seq))
    return {key: tuple(map(list, zip(*sorted(v)))) for key, v in views.items()}


def _never_had(view: tuple[list, list] | None, arrival: tuple[int, int], seq: int) -> bool:
    """Whether a consumer never had an event that no record of it names late: the first of its
    ticks at or past the event's tag ran incomplete without it. Had it come afterwards, a later
    record would name it; it came after the consumer's last record, or never (a real-time run)."""
    if view is None:
        return False
    tags, seqs = view
    i = bisect.bisect_left(tags, arrival)
    return i < len(tags) and seq >= seqs[i]


def _restart_gaps(steps) -> dict[tuple[str, str], list[tuple[str, str, int, int]]]:
    """Per ``(consumer node, port)``, the seq ranges ``[lo, hi)`` of a restarted producer's
    streams it gave up (the dead process's events it never got), from its records' ``restart_gap``."""
    gaps: dict[tuple[str, str], list[tuple[str, str, int, int]]] = {}
    for s in steps:
        for port, ranges in ((s.detail or {}).get("restart_gap") or {}).items():
            gaps.setdefault((s.node, port), []).extend(tuple(r) for r in ranges)
    return gaps


def _in_gap(ranges: list[tuple[str, str, int, int]] | None, event: LoggedEvent) -> bool:
    """Whether ``event`` falls in one of a consumer port's restart gaps."""
    return ranges is not None and any(src == event.node and port == event.port and lo <= event.seq < hi
                                      for src, port, lo, hi in ranges)


def _restart_afresh(session: InprocSession, node: str, restarted: dict, floors: dict) -> None:
    """Start ``node`` afresh at its first record after its process died: its buffers keep only
    the events from where the new process took each stream on, and later ones below are not given."""
    for port, ids in restarted["inputs"].items():
        for src, src_port, first in ids:
            floors[(node, src, src_port)] = first
    for buf, entries in session.restart_afresh(node, restarted["seqs"]):
        for entry in entries:
            if entry[3] >= floors.get((node, entry[1], entry[2]), 0):
                buf.insert(entry)


def _compare(step, trace: Trace, logged: dict[tuple, LoggedEvent], encode, stamped: bool) -> Divergence | None:
    (_, tag, consumed, produced, status, detail, *_), = trace.raw_steps

    def differs(what: str, logged_value: Any, replayed: Any, port: str | None = None) -> Divergence:
        return Divergence(step.node, step.tag, what, port, logged_value, replayed)

    if consumed != step.consumed:
        port = next((p for p in sorted(set(consumed) | set(step.consumed)) if consumed.get(p) != step.consumed.get(p)))
        return differs("inputs (consumed event ids)", step.consumed.get(port), consumed.get(port), port)
    if status != ("ok" if step.status in STEPPED else step.status):
        return differs("status", _status(step.status, step.detail), _status(status, detail))
    if status == "error" and (detail or {}).get("error") != (step.detail or {}).get("error"):
        return differs("error", step.detail.get("error"), detail.get("error"))
    if produced != step.produced:
        return differs("outputs (produced event ids)", list(step.produced), list(produced))
    for ev in trace.raw_events:
        tag, node, port, seq, value = ev[:5]
        original = logged.get((node, port, seq))
        if original is None:
            return differs("value", "<not in the log: the log ends here>", value, port)
        if stamped:
            if original.tag <= step.tag:
                return differs("output tag (not after its tick: causality)", format_tag(original.tag),
                               f"after {format_tag(step.tag)}", port)
        elif tag != original.tag:
            return differs("output tag", format_tag(original.tag), format_tag(tag), port)
        if encode(value) != original.raw_value:
            return differs("value", _logged_value(original), value, port)
    return None


def _logged_value(event: LoggedEvent) -> Any:
    """A logged value to show beside the replayed one: itself, or what it is when it does not decode."""
    try:
        return unpackb(event.raw_value, keep_unregistered=True)
    except Exception as e:  # a damaged value differs from any replayed one: say what it is
        return f"<{len(event.raw_value)} bytes that do not decode: {type(e).__name__}>"


def _stepped(step) -> bool:
    """Whether the run called step() at this tick or its policy skipped it: every tick but one
    that a real-time run stopped before stepping (realtime="hard", an incomplete edge)."""
    return step.status != "skipped" or "missing" in (step.detail or {})


def _status(status: str, detail: dict | None) -> str:
    return f"{status} {detail}" if detail else status


def _short(value: Any, limit: int = 300) -> str:
    # every float as the shortest text that reads back to it: two values that differ never look alike
    with np.printoptions(floatmode="unique"):
        text = repr(value)
    return text if len(text) <= limit else text[:limit] + f"... ({len(text)} chars)"


def explain_difference(logged: Any, replayed: Any) -> list[str]:
    """Where two differing values differ, in words: the path to the first differing part (a
    dataclass field, dict key or list item), and for arrays their shapes and dtypes, how many
    elements differ and the largest difference (absolute and relative), values in full."""
    found = _first_difference(logged, replayed, "")
    if found is None:  # equal as values, different as bytes: e.g. 1 vs 1.0, or a list vs a tuple
        return [f"as values they are equal; their encodings differ ({type(logged).__name__} vs "
                f"{type(replayed).__name__})"]
    path, a, b = found
    at = f"at {path}: " if path else ""
    if isinstance(a, np.ndarray) and isinstance(b, np.ndarray):
        first, *rest = _array_difference(a, b)
        return [at + first, *rest]
    if type(a) is not type(b):
        return [f"{at}logged a {type(a).__name__}, replayed a {type(b).__name__}"]
    lines = [f"{at}logged {_short(a)}, replayed {_short(b)}"] if path else []
    if isinstance(a, (float, np.floating)) and np.isfinite(a) and np.isfinite(b):
        lines.append(f"difference: absolute {abs(float(b) - float(a))!r}{_relative(float(a), float(b))}")
    return lines


def _first_difference(a: Any, b: Any, path: str) -> tuple[str, Any, Any] | None:
    if type(a) is not type(b):
        return (path, a, b)
    if isinstance(a, np.ndarray):
        same = a.shape == b.shape and a.dtype == b.dtype and np.array_equal(a, b, equal_nan=a.dtype.kind in "fc")
        return None if same else (path, a, b)
    if dataclasses.is_dataclass(a):
        fields = [f.name for f in dataclasses.fields(a)]
        return next((d for name in fields
                     if (d := _first_difference(getattr(a, name), getattr(b, name), f"{path}.{name}"))), None)
    if isinstance(a, dict):
        for key in list(a) + [k for k in b if k not in a]:
            if key not in a or key not in b:
                return (f"{path}[{key!r}]", a.get(key, "<absent>"), b.get(key, "<absent>"))
            if (d := _first_difference(a[key], b[key], f"{path}[{key!r}]")) is not None:
                return d
        return None
    if isinstance(a, (list, tuple)):
        if len(a) != len(b):
            return (path, a, b)
        return next((d for i, (x, y) in enumerate(zip(a, b)) if (d := _first_difference(x, y, f"{path}[{i}]"))), None)
    if isinstance(a, float) and a != a and b != b:  # NaN: the same value to the log
        return None
    return None if a == b else (path, a, b)


def _array_difference(a: np.ndarray, b: np.ndarray) -> list[str]:
    if a.shape != b.shape or a.dtype != b.dtype:
        return [f"logged {a.dtype} {a.shape}, replayed {b.dtype} {b.shape}"]
    differs = a != b
    if a.dtype.kind in "fc":
        differs &= ~(np.isnan(a) & np.isnan(b))
    count = int(np.count_nonzero(differs))
    head = f"{a.dtype} {a.shape}: {count} of {a.size} element{'s' if a.size != 1 else ''} differ"
    if a.dtype.kind not in "iufc":
        first = tuple(int(i) for i in np.argwhere(differs)[0])
        return [f"{head}; the first at {list(first)}: logged {a[first]!r}, replayed {b[first]!r}"]
    with np.errstate(invalid="ignore", over="ignore"):
        gap = np.where(differs, np.abs(b.astype(np.complex128 if a.dtype.kind == "c" else np.float64)
                                       - a.astype(np.complex128 if a.dtype.kind == "c" else np.float64)), 0)
    gap = np.where(np.isnan(gap), np.inf, gap)  # a NaN on one side only is the largest difference
    where = tuple(int(i) for i in np.unravel_index(int(np.argmax(gap)), a.shape))
    x, y = a[where].item(), b[where].item()
    return [head, f"largest difference at {list(where)}: logged {x!r}, replayed {y!r} "
                  f"(absolute {abs(y - x)!r}{_relative(x, y)})"]


def _relative(logged: Any, replayed: Any) -> str:
    return f", relative {abs(replayed - logged) / abs(logged)!r}" if logged else ""


# -------------------------------------------------------------------------------------------
# Re-simulation
# -------------------------------------------------------------------------------------------
@dataclass
class ResimReport:
    horizon_ns: int
    steps_compared: int
    events_compared: int
    difference: str | None
    code_changes: list[str] = field(default_factory=list)  # flow modules whose file differs from the run's

    @property
    def identical(self) -> bool:
        return self.difference is None


def _logged_outputs(step: StepRecord, values: dict) -> list | ReplayedError:
    """What a replayed source's tick gives the re-simulation: its logged events, or its logged
    error (raised again, so that the tick is an error record, handled by ``on_error``, as in
    the run)."""
    if step.status == "error":
        error = (step.detail or {}).get("error")
        return ReplayedError(error if type(error) is str else "an error (the log does not say which)")
    return [(i[1], values[i]) for i in step.produced]


def resim(log: RunLog, pipeline: Pipeline | None = None) -> ResimReport:
    """Re-run the graph in virtual time from the logged source events; compare the trace."""
    if log.faults:  # the run lost state with a process: no re-run from the start can match it
        nodes = ", ".join(sorted({fault["node"] for fault in log.faults}))
        raise LogError(f"{log.path}: a process of the run died (of {nodes}), so its flow lost its state there: "
                       "--resim re-runs every flow from its start, which this run did not",
                       "retriever replay LOG (without --resim) follows the run through its restarts")
    pipeline = pipeline_for(log, pipeline)
    graph = pipeline.compile()
    changes = code_changes(log, graph)
    original = log.trace()
    end = log.end
    if end is not None and end.get("status") == "finished":
        horizon = int(end["end_ns"])
    else:  # a recovered or failed run: its last instant may be cut short, compare before it
        horizon = max((s.tag[0] for s in original.steps), default=0)

    session = InprocSession(graph)
    values = {e.id: e.value for e in original.events}
    logged = from_the_log(graph)
    for nid in logged:
        ticks = sorted((s for s in original.steps if s.node == nid and s.status != "skipped"), key=lambda s: s.tag)
        session.replace_step(nid, iter([_logged_outputs(s, values) for s in ticks]))
    try:
        _set_up(session, logged)
        session.advance(horizon)
    except StepError as e:
        if not isinstance(e.__cause__, ReplayedError):  # (a logged source's error stopped the run too)
            return ResimReport(horizon, 0, 0, f"the re-simulation stopped: {e}", changes)
    finally:
        session.close()
    kept_steps = [s for s in original.steps if s.tag[0] < horizon]
    kept_ids = {i for s in kept_steps for i in s.produced}
    expected = Trace([e for e in original.events if e.id in kept_ids], kept_steps)
    again = session.trace
    return ResimReport(horizon, len(kept_steps), len(expected.raw_events), expected.first_difference(again), changes)
