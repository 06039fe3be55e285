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

**Memory: a log larger than RAM replays.** ``replay_file(path)`` (what ``retriever replay``
runs) reads the file twice and keeps neither:

1. ``log.reader.scan_log`` checks it whole, as ``read_log`` does (the same errors for a log torn
   or damaged, before anything runs), handing each message to a :class:`LogSurvey`: what the
   replay must know of the whole log before its first step, in memory that grows with what was
   unusual in the run, not with its length (the nodes, the step count, the event ids as ranges
   of seqs per port, the ``late`` / ``had_below`` / ``restart_gap`` details), and where the chunks
   are. A step record without detail (nearly all) is only read for its node there: the second
   pass checks it, and a log with one that is not one is refused there, with the same error and
   no report;
2. ``ScannedLog.time_ordered`` reads the messages again in log-time order (ties in file
   order: what sorting the file's messages by log time gives), chunk by chunk, holding only the
   chunks whose times overlap. The replay takes them an instant (a log time) at a time: the
   instant's events go to their consumers' deliveries (decoded once, on a heap by arrival), then
   its step records run in ``(tag, node)`` order, as when every record was sorted up front. An
   event waits until the record that produced it has run (the same instant, for a log a run
   wrote); a step's outputs are compared once they are read (a LET step's come later in the
   log than its tick), the comparisons reported in step order. An id that the survey says the
   log lacks is known to be missing at once (the log is cut short, or it is a divergence).

``replay(log)`` of a log read whole (``read_log``) takes the same two steps over its message
list. Only a changed log can tell them apart: a record that names as late an event from its own
future puts it in at once rather than at that record, and a second record naming an event the
first already took compares as if the log lacked it. ``keep_trace`` holds the whole replayed run,
so only ``replay`` has it.

``resim`` re-runs the whole graph in virtual time, with the sources emitting their logged events,
and compares the full trace: it proves the log is one consistent run of this graph. It reads the
log whole.

Replay runs the pipeline and the in-process backend, so it sits above them, not in ``log/``.
"""

from __future__ import annotations

import bisect
import dataclasses
import heapq
import json
import os
import warnings
from collections import deque
from dataclasses import dataclass, field
from itertools import chain as _chain
from pathlib import Path
from typing import Any, Callable, Iterator

import msgpack
import numpy as np

from .backends.inproc import InprocSession
from .code import code_mismatches
from .codec import Encoder, unpackb
from .errors import IRError, LogError, ReplayedError, RetrieverWarning, RunEnded, SetupError, StepError
from .flow._base import settings_of
from .log import format as fmt
from .log.reader import LogHead, LoggedEvent, RunLog, read_log, scan_log
from .pipeline import Pipeline
from .time import format_tag
from .trace import STEPPED, StepRecord, StepStatus, Trace

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


def replay(log: RunLog, pipeline: Pipeline | None = None,
           progress: Callable[[int, int], None] | None = None, keep_trace: bool = False) -> ReplayReport:
    """Re-execute every non-source step of ``log``; see the module docstring. The flows are set
    up before the first step and torn down at the end, as in a run. ``keep_trace=True`` keeps
    the replayed run in ``report.trace`` (what an export of the replay reads: docs/learning.md)."""
    survey = LogSurvey(log.path)
    channels = log.channels
    for m in log.messages:
        survey.take(channels[m.channel_id], m)
    return _replay_surveyed(log, survey, lambda: iter(sorted(log.messages, key=_log_time)), pipeline, progress,
                            keep_trace)


def replay_file(path: str | os.PathLike, pipeline: Pipeline | Callable[[], Pipeline] | None = None,
                progress: Callable[[str, int, int], None] | None = None) -> ReplayReport:
    """:func:`replay` of the log at ``path`` that holds no more than a few of its chunks in memory
    at a time, however long the log (the module docstring says how). ``pipeline``: as for
    :func:`replay`, or a function that makes it, called once the log has been read (so a log
    that cannot be read is said first). ``progress(what, done, total)``: ``"reading"`` with bytes
    as the file is checked, then ``"replaying"`` with steps. A log with messages outside its chunks
    (MCAP allows them; Retriever's writer makes none) is replayed by :func:`replay`, read whole."""
    survey = LogSurvey(Path(path))
    read = None if progress is None else (lambda done, total: progress("reading", done, total))
    log = scan_log(path, survey.take, progress=read)
    if callable(pipeline):
        pipeline = pipeline()
    steps = None if progress is None else (lambda done, total: progress("replaying", done, total))
    if log.loose:
        return replay(read_log(path), pipeline, steps)
    return _replay_surveyed(log, survey, log.time_ordered, pipeline, steps, False)


def _log_time(message) -> int:
    return message.log_time


def _replay_surveyed(log: LogHead, survey: LogSurvey, messages: Callable[[], Iterator], pipeline: Pipeline | None,
                     progress: Callable[[int, int], None] | None, keep_trace: bool) -> ReplayReport:
    pipeline = pipeline_for(log, pipeline, survey.logged_nodes)
    graph = pipeline.compile()
    changes = code_changes(log, graph)
    session = InprocSession(graph)
    logged = from_the_log(graph)
    _set_up(session, logged)
    try:
        report = _Replay(log, survey, graph, session, logged, keep_trace).play(messages, progress)
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


class LogSurvey:
    """What a replay must know of the whole log before its first step, gathered from its
    messages in one pass in file order (as the file is checked, or from a read log's list), in
    memory that grows with what was unusual in the run, not with its length: the nodes that
    have steps and how many steps; which event ids the log holds (per port, ranges of seqs: one
    range for a port whose events all are there), so an event logged twice is found; the events
    that reached a consumer late, the incomplete ticks' views and the restart gaps (the step
    records' ``late``, ``had_below`` and ``restart_gap``). A record with detail that is not one
    is kept as the error the replay raises before its first step; one without detail (nearly
    all: only its node is read here) the replay refuses where it reads it, with the same error."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self.nodes: set[str] = set()
        self.steps = 0
        self.seqs: dict[tuple[str, str], _Seqs] = {}
        #: ((consumer, port), event id) -> the tag of the consumer's record that names it late
        self.late: dict[tuple[tuple[str, str], tuple[str, str, int]], tuple[int, int]] = {}
        self._views: dict[tuple[tuple[str, str], str, str], list] = {}
        self.gaps: dict[tuple[str, str], list[tuple[str, str, int, int]]] = {}
        self.step_error: LogError | None = None
        self.event_error: LogError | None = None
        self.twice: LogError | None = None
        self._kinds: dict[int, Any] = {}  # channel id -> _STEPS, (node, port, seqs), or None

    def take(self, channel, m) -> None:
        kind = self._kinds.get(m.channel_id, _UNSEEN)
        if kind is _UNSEEN:
            kind = self._kinds[m.channel_id] = self._kind(channel)
        if kind is _STEPS:
            self._step(m)
        elif kind is not None:
            node, port, seqs = kind
            if self.event_error is None:
                try:
                    fmt.split_event(m.data)
                except ValueError as e:
                    self.event_error = LogError(f"{self.path}: event {node}.{port} #{m.sequence} is malformed ({e})")
            if not seqs.add(m.sequence) and self.twice is None:
                self.twice = LogError(f"{self.path}: event {node}.{port} #{m.sequence} is logged twice",
                                      "the file is damaged or was edited: retriever replay reads logs as a run "
                                      "wrote them")

    def _kind(self, channel) -> Any:
        if channel.topic == fmt.STEPS_TOPIC:
            return _STEPS
        port = fmt.parse_data_topic(channel.topic)
        return None if port is None else (*port, self.seqs.setdefault(port, _Seqs()))

    def _step(self, m) -> None:
        if self.step_error is not None:
            return
        # a record without detail tells the survey only its node: read, not checked (the replay's
        # own reading of it checks it, and refuses the log with the same error there)
        try:
            record = msgpack.unpackb(m.data, use_list=False)
        except Exception:
            record = None
        if type(record) is tuple and len(record) == 7 and record[5] is None and type(record[0]) is str:
            self.steps += 1
            self.nodes.add(record[0])
            return
        try:
            node, microstep, _, _, _, detail, _ = fmt.decode_step(m.data)
        except Exception as e:
            self.step_error = LogError(f"{self.path}: step record #{m.sequence} is malformed ({e})")
            return
        self.steps += 1
        self.nodes.add(node)
        if not detail:
            return
        tag = (m.log_time, microstep)
        for port, ids in (detail.get("late") or {}).items():
            for event_id in ids:
                key = ((node, port), tuple(event_id))
                if self.late.get(key, tag) <= tag:  # named late twice: the record that sorts last
                    self.late[key] = tag
        for port, streams in (detail.get("had_below") or {}).items():
            for src, out, seq in streams:
                self._views.setdefault(((node, port), src, out), []).append((tag, seq))
        for port, ranges in (detail.get("restart_gap") or {}).items():
            self.gaps.setdefault((node, port), []).extend(tuple(r) for r in ranges)

    def logged_nodes(self) -> set[str]:
        """The nodes the log has steps of (or the error of its first step record that is not one)."""
        if self.step_error is not None:
            raise self.step_error
        return self.nodes

    def check_events(self) -> None:
        """Raise what is wrong with the log's events: one that is not one, one logged twice."""
        if self.event_error is not None:
            raise self.event_error
        if self.twice is not None:
            raise self.twice

    def views(self) -> dict[tuple[tuple[str, str], str, str], tuple[list, list]]:
        """Per ``((consumer node, port), producer, producer port)``, the tags of the consumer's ticks
        that ran incomplete on it and, at each, the seq that stream's next event would have had
        (their ``had_below`` detail): the two lists in tag order."""
        return {key: tuple(map(list, zip(*sorted(v)))) for key, v in self._views.items()}

    def in_log(self, event_id: tuple[str, str, int]) -> bool:
        seqs = self.seqs.get(event_id[:2])
        return seqs is not None and event_id[2] in seqs


_STEPS = "steps"
_UNSEEN = object()


class _Seqs:
    """A set of seqs held as sorted ranges ``[lo, hi)``: as small as the gaps between them."""

    __slots__ = ("lo", "hi")

    def __init__(self) -> None:
        self.lo: list[int] = []
        self.hi: list[int] = []

    def add(self, seq: int) -> bool:
        """Put ``seq`` in; False if it was there."""
        lo, hi = self.lo, self.hi
        if hi and hi[-1] == seq:  # the next one: the common case
            hi[-1] = seq + 1
            return True
        i = bisect.bisect_right(lo, seq)
        if i and seq < hi[i - 1]:
            return False
        after, before = i and hi[i - 1] == seq, i < len(lo) and lo[i] == seq + 1
        if after and before:
            hi[i - 1] = hi[i]
            del lo[i], hi[i]
        elif after:
            hi[i - 1] = seq + 1
        elif before:
            lo[i] = seq
        else:
            lo.insert(i, seq)
            hi.insert(i, seq + 1)
        return True

    def __contains__(self, seq: int) -> bool:
        i = bisect.bisect_right(self.lo, seq)
        return bool(i) and seq < self.hi[i - 1]


class _Check:
    """One logged step's comparison, in step order: decided when every logged output it needs
    has been read (a LET step's outputs come later in the log than its tick)."""

    __slots__ = ("step", "stats", "replayed", "events", "stamped", "originals", "waiting", "found", "done")

    def __init__(self, step, stats: NodeReplay, found: Divergence | None = None, done: bool = True) -> None:
        self.step, self.stats, self.found, self.done = step, stats, found, done
        self.originals: dict[tuple, LoggedEvent] = {}
        self.waiting = 0


class _Replay:
    """One replay of a log's steps (:meth:`play`): the log's messages read once in log-time
    order (``messages()``), an instant at a time::

        an instant's messages ─┬─ events ─→ read: decoded once, to the consumers' deliveries (a
                               │            heap by arrival) and to the check waiting for them
                               └─ records → run, in (tag, node) order: checked against the clock,
                                            the deliveries due put in, the tick re-executed,
                                            compared (its outputs once read: decide), the
                                            comparisons reported in step order (flush)
        the log's end ─────────→ finish: the checks no output came for; the kept trace

    What is held is what the instants still to come need (deliveries not due, comparisons waiting
    for a LET output, the survey's exceptions)."""

    __slots__ = ("log", "session", "sources", "keep_trace", "encode", "routes", "late", "gaps", "missed", "in_log",
                 "lost", "floors", "stamped", "cut_short", "report", "total", "done", "on_clock", "seen_ticks",
                 "deliveries", "delivered", "late_at", "unclaimed", "waiting", "checks", "now",
                 "kept_steps", "kept_parts", "kept_events")

    def __init__(self, log: LogHead, survey: LogSurvey, graph, session: InprocSession, sources: frozenset[str],
                 keep_trace: bool) -> None:
        survey.check_events()
        self.log, self.session, self.sources, self.keep_trace = log, session, sources, keep_trace
        self.encode = Encoder().pack
        self.routes = session.take_routes()
        self.late, self.gaps, self.missed = survey.late, survey.gaps, survey.views()
        self.in_log = survey.in_log
        # a lost process's outputs that its records claim and no report carried: not comparable (a
        # consumer may still have carried one in: that one is in the log, and compared)
        self.lost = {event_id for fault in log.faults for event_id in fault["lost_events"] if not self.in_log(event_id)}
        self.floors: dict[tuple[str, str, str], int] = {}  # (consumer, producer, port) -> first seq it takes
        # In real time a flow without latency stamps its outputs when it finishes (ASAP): the tag
        # is then checked for causality (after the tick), not recomputed.
        realtime = log.run.get("backend", "inproc") != "inproc"
        self.stamped = {nid for nid, node in graph.nodes.items() if realtime and not node.settings.latency_ns}
        # a log whose writer was killed, recovered or read with salvage=True, may keep a step record
        # (one chunk) and lose the events it consumed or produced (another): such a step cannot be compared
        self.cut_short = not log.complete or "retriever.recovered" in log.metadata
        self.report = ReplayReport({nid: NodeReplay(from_log=nid in sources) for nid in sorted(graph.nodes)})
        self.total, self.done = survey.steps, 0
        self.on_clock = TickCheck(graph)
        self.seen_ticks: set[tuple[str, tuple[int, int]]] = set()  # this instant's (node, tag)s
        self.deliveries: list = []  # heap of (arrival, n, consumer node, buffer, entry)
        self.delivered = 0  # events put on the heap: its tie-break, the order the log was read in
        self.late_at: dict[tuple[str, tuple[int, int]], list] = {}  # (consumer node, record tag) -> [(buf, entry)]
        self.unclaimed: dict[tuple, LoggedEvent] = {}  # events read whose step record has not been replayed yet
        self.waiting: dict[tuple, _Check | None] = {}  # outputs a replayed record named, not read yet -> its check
        self.checks: deque[_Check] = deque()  # in step order, from the first not decided
        self.now = (-1, 0)  # the tag of the instant whose steps run
        # keep_trace: every step record, and in step order the outputs of each
        self.kept_steps, self.kept_parts, self.kept_events = [], [], {}

    def play(self, messages: Callable[[], Iterator], progress: Callable[[int, int], None] | None) -> ReplayReport:
        """Replay the log: each instant's messages read, then its step records run."""
        log = self.log
        steps_channels = {c.id for c in log.channels.values() if c.topic == fmt.STEPS_TOPIC}
        ports = {c.id: parsed for c in log.channels.values() if (parsed := fmt.parse_data_topic(c.topic))}
        read = self.read
        steps: list = []
        instant = None
        for m in _chain(messages(), (None,)):
            if m is None or m.log_time != instant:
                if steps:  # the instant's messages are read: run its steps
                    self.run_instant(steps, progress)
                if m is None:
                    break
                instant = m.log_time
                self.now = (instant, 0)  # every record before it has run
            channel = m.channel_id
            if channel in steps_channels:
                try:
                    node, microstep, consumed, produced, status, detail, wall_ns = fmt.decode_step(m.data)
                except Exception as e:
                    raise LogError(f"{log.path}: step record #{m.sequence} is malformed ({e})") from None
                steps.append(StepRecord(node, (m.log_time, microstep), consumed, produced, status, detail,
                                        m.publish_time, wall_ns))
            else:
                port = ports.get(channel)
                if port is not None:
                    read(m, port)
        return self.finish(progress)

    def read(self, m, port: tuple[str, str]) -> None:
        """An event read: to its consumers' deliveries, and to the check waiting for it."""
        try:
            microstep, raw = fmt.split_event(m.data)
        except ValueError as e:
            raise LogError(f"{self.log.path}: event {port[0]}.{port[1]} #{m.sequence} is malformed ({e})") from None
        e = LoggedEvent((m.log_time, microstep), port[0], port[1], m.sequence, raw, m.publish_time)
        event_id = (port[0], port[1], m.sequence)
        if self.keep_trace:
            self.kept_events[event_id] = e
        consumers = self.routes.get(port)
        if consumers:
            value = self.log.value(e)
            gaps, late, missed = self.gaps, self.late, self.missed
            for consumer, buf, delay_ns in consumers:
                if gaps and _in_gap(gaps.get(consumer), e):
                    continue
                arrival = (e.tag[0] + delay_ns, 0) if delay_ns else e.tag
                entry = (arrival, e.node, e.port, e.seq, value)
                seen_at = late.get((consumer, event_id)) if late else None
                if seen_at is not None:
                    if seen_at < self.now:  # a record before its time names it (a changed log): in at once
                        buf.insert(entry)
                    else:
                        self.late_at.setdefault((consumer[0], seen_at), []).append((buf, entry))
                elif not missed or not _never_had(missed.get((consumer, e.node, e.port)), arrival, e.seq):
                    heapq.heappush(self.deliveries, (arrival, self.delivered, consumer[0], buf, entry))
                    self.delivered += 1
        check = self.waiting.pop(event_id, _UNSEEN)
        if check is _UNSEEN:
            self.unclaimed[event_id] = e
        elif check is not None:
            check.originals[event_id] = e
            check.waiting -= 1
            if check.waiting == 0:
                self.decide(check)
                self.flush()

    def run_instant(self, steps: list, progress: Callable[[int, int], None] | None) -> None:
        """Run an instant's step records, its messages all read, in (tag, node) order."""
        steps.sort(key=_microstep_node)
        run, done = self.run, self.done
        for step in steps:
            if progress is not None and done % PROGRESS_EVERY == 0:
                progress(done, self.total)
            done += 1
            run(step)
        self.done = done
        steps.clear()
        self.seen_ticks.clear()

    def run(self, step) -> None:
        """One logged step: checked against its node's clock, the run's restart and late arrivals
        at it done again, then re-executed and compared; a source's, or a tick the run did not
        step, is not re-executed: its outputs are taken from the log."""
        stats = self.report.nodes[step.node]
        stats.steps += 1
        # a source is not re-executed: its records are checked against its clock (a forged
        # record between its ticks, or a second at one, is no step the run made)
        found = _off_clock(step, self.on_clock, self.seen_ticks)
        if found is not None:
            self.checks.append(_Check(step, stats, found))
            self.flush()
            return
        restarted = (step.detail or {}).get("restarted")
        if restarted is not None:
            _restart_afresh(self.session, step.node, restarted, self.floors)
        if self.late_at:
            for buf, entry in self.late_at.pop((step.node, step.tag), ()):
                buf.insert(entry)  # it arrived late: in the buffer from this record on, as in the run
        keep_trace = self.keep_trace
        if keep_trace:
            self.kept_steps.append(tuple(step))
        if step.node in self.sources or not _stepped(step):
            self.claim(step.produced, None)
            if keep_trace:  # not re-executed: its outputs as logged
                self.kept_parts.append(step.produced)
            return
        self.deliver_due(step.tag)
        replayed, events = _execute(self.session, step)
        if keep_trace:
            self.kept_parts.append(events)
        stats.replayed += 1
        self.compare(step, stats, replayed, events)

    def deliver_due(self, tag: tuple[int, int]) -> None:
        """Put in their buffers the deliveries that arrived by ``tag``, but those a restarted
        consumer no longer takes."""
        deliveries, floors = self.deliveries, self.floors
        while deliveries and deliveries[0][0] <= tag:
            _, _, consumer, buf, entry = heapq.heappop(deliveries)
            if not floors or entry[3] >= floors.get((consumer, entry[1], entry[2]), 0):
                buf.insert(entry)

    def compare(self, step, stats: NodeReplay, replayed: tuple, events: list) -> None:
        """A re-executed step against the log: its record now, its outputs once the log's are read;
        not compared when the log lost what it needs (with a dead process, or cut short)."""
        in_log = self.in_log
        if self.lost and not self.lost.isdisjoint(step.produced):
            stats.lost += 1
            self.claim(step.produced, None)
        elif self.cut_short and any(not in_log(event_id) for event_id in
                                    (*step.produced, *(i for ids in step.consumed.values() for i in ids))):
            stats.cut += 1
            self.claim(step.produced, None)
        else:
            found = _compare_record(step, replayed)
            if found is not None:
                self.claim(step.produced, None)
                self.checks.append(_Check(step, stats, found))
            else:
                check = _Check(step, stats, done=False)
                check.events, check.stamped = events, step.node in self.stamped
                self.claim(step.produced, check)
                self.checks.append(check)
                if check.waiting == 0:
                    self.decide(check)
            self.flush()

    def claim(self, ids, check: _Check | None) -> None:
        """A record's logged outputs: to its check (None: not compared, let go)."""
        unclaimed = self.unclaimed
        for event_id in ids:
            e = unclaimed.pop(event_id, None)
            if e is not None:
                if check is not None:
                    check.originals[event_id] = e
            elif self.in_log(event_id):
                self.waiting[event_id] = check
                if check is not None:
                    check.waiting += 1

    def decide(self, check: _Check) -> None:
        """A check whose logged outputs are all read (or never will be): compare them."""
        check.found = _compare_outputs(check.step, check.events, check.originals, self.encode, check.stamped)
        check.done = True
        check.events = check.originals = None

    def flush(self) -> None:
        """Report the checks decided, in step order: up to the first still waiting."""
        checks, report = self.checks, self.report
        while checks and checks[0].done:
            check = checks.popleft()
            if check.found is None:
                check.stats.identical += 1
            else:
                _diverged(report, check.stats, check.found)

    def finish(self, progress: Callable[[int, int], None] | None) -> ReplayReport:
        """The log has ended: decide what no output came for, report, keep the trace."""
        for check in self.checks:  # what no output came for: the log ends before it
            if not check.done:
                self.decide(check)
        self.flush()
        if progress is not None:
            progress(self.total, self.total)
        if self.keep_trace:
            self.report.trace = self.kept_trace()
        return self.report

    def kept_trace(self) -> Trace:
        """The run as replayed: every step record, and each step's outputs (as replayed, or as
        logged for a step not re-executed)."""
        kept = Trace()
        kept.raw_steps.extend(self.kept_steps)
        for part in self.kept_parts:
            if type(part) is tuple:
                kept.raw_events.extend((e.tag, e.node, e.port, e.seq, self.log.value(e), e.publish_ns)
                                       for e in map(self.kept_events.get, part) if e is not None)
            else:
                kept.raw_events.extend(part)
        return kept


def _microstep_node(step) -> tuple[int, str]:
    return (step.tag[1], step.node)


def _execute(session: InprocSession, step) -> tuple[tuple, list[tuple]]:
    """Run the recorded tick again: its step record and its events, taken out of ``session.trace``."""
    trace = session.trace
    try:
        session.tick(step.node, step.tag)
    except (StepError, RunEnded):
        pass  # on_error="stop", or sys.exit(0): the step is recorded; compare it like any other
    if step.status == StepStatus.LATE and step.detail.get("on_deadline_miss") in ("drop", "error"):
        session.retract(step.node)  # the run dropped what this step returned
    tape = trace.tape
    if len(tape) == 2:  # one event and the record (the commonest): as below, without the scans
        event, replayed = tape
        if type(event) is tuple and type(replayed) is tuple and len(event) == 6 and len(replayed) != 6:
            tape.clear()
            return replayed, [event]
    if tape and all(type(item) is tuple for item in tape):  # plain records (Trace): taken as they are
        events = [item for item in tape if len(item) == 6]
        records = [item for item in tape if len(item) != 6]
        del tape[:]
    else:  # expanded already (by a retract), or compact ones: through the trace
        events, records = list(trace.raw_events), list(trace.raw_steps)
        del trace.raw_events[:], trace.raw_steps[:]
    replayed, = records
    return replayed, events


def _diverged(report: ReplayReport, stats: NodeReplay, found: Divergence) -> None:
    stats.divergent += 1
    report.divergent_steps += 1
    if len(report.divergences) < MAX_DIVERGENCES_KEPT:
        report.divergences.append(found)


class TickCheck:
    """Whether a record's tag is a tick of its node's clock (``clock.may_tick_at``): a rate's tick
    after the one last found is known without the clock's arithmetic (a node's records come tick
    after tick)."""

    __slots__ = ("clocks", "next")

    def __init__(self, graph) -> None:
        self.clocks = {nid: node.clock for nid, node in graph.nodes.items()}
        self.next: dict[str, tuple[tuple[int, int], int]] = {}  # node -> (the tag of its tick k, k)

    def __call__(self, node: str, tag: tuple[int, int]) -> bool:
        expected = self.next.get(node)
        clock = self.clocks[node]
        if expected is not None and expected[0] == tag:
            k = expected[1]
        elif not clock.may_tick_at(tag):
            return False
        elif clock.triggered or clock.hz is None:
            return True
        else:
            k = clock.first_tick_at_or_after(tag[0])
        self.next[node] = ((clock.tick_time(k + 1), 0), k + 1)
        return True


def _off_clock(step, on_clock: TickCheck, seen: set[tuple[str, tuple[int, int]]]) -> Divergence | None:
    """The record at a tag where its node's clock has no tick, or at one it already recorded."""
    key = (step.node, step.tag)
    if not on_clock(step.node, step.tag):
        return Divergence(step.node, step.tag, "tick", None, f"a record at {format_tag(step.tag)}",
                          f"no tick of {on_clock.clocks[step.node]!r} there")
    if key in seen:
        return Divergence(step.node, step.tag, "tick", None, "a second record of this tick", "one record a tick")
    seen.add(key)
    return None


def _never_had(view: tuple[list, list] | None, arrival: tuple[int, int], seq: int) -> bool:
    """Whether a consumer never had an event that no record of it names late: the first of its
    ticks at or past the event's tag ran incomplete without it. Had it come afterwards, a later
    record would name it; it came after the consumer's last record, or never (a real-time run)."""
    if view is None:
        return False
    tags, seqs = view
    i = bisect.bisect_left(tags, arrival)
    return i < len(tags) and seq >= seqs[i]


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


def _compare_record(step, replayed: tuple) -> Divergence | None:
    """The replayed step record against the logged one: the ids it consumed, its status, its
    error, the ids it produced."""
    _, tag, consumed, produced, status, detail, *_ = replayed

    def differs(what: str, logged_value: Any, replayed: Any, port: str | None = None) -> Divergence:
        return Divergence(step.node, step.tag, what, port, logged_value, replayed)

    if consumed != step.consumed:
        port = next((p for p in sorted(set(consumed) | set(step.consumed)) if consumed.get(p) != step.consumed.get(p)))
        return differs("inputs (consumed event ids)", step.consumed.get(port), consumed.get(port), port)
    if status != (StepStatus.OK if step.status in STEPPED else step.status):
        return differs("status", _status(step.status, step.detail), _status(status, detail))
    if status == StepStatus.ERROR and (detail or {}).get("error") != (step.detail or {}).get("error"):
        return differs("error", step.detail.get("error"), detail.get("error"))
    if produced != step.produced:
        return differs("outputs (produced event ids)", list(step.produced), list(produced))
    return None


def _compare_outputs(step, events: list, logged: dict[tuple, LoggedEvent], encode, stamped: bool) -> Divergence | None:
    """The replayed outputs of a step whose record matched, against the logged ones (``logged``:
    by id, those the log holds): their tags and every value's msgpack bytes."""
    for ev in events:
        tag, node, port, seq, value = ev[:5]
        original = logged.get((node, port, seq))
        if original is None:
            return Divergence(step.node, step.tag, "value", port, "<not in the log: the log ends here>", value)
        if stamped:
            if original.tag <= step.tag:
                return Divergence(step.node, step.tag, "output tag (not after its tick: causality)", port,
                                  format_tag(original.tag), f"after {format_tag(step.tag)}")
        elif tag != original.tag:
            return Divergence(step.node, step.tag, "output tag", port, format_tag(original.tag), format_tag(tag))
        if encode(value) != original.raw_value:
            return Divergence(step.node, step.tag, "value", port, _logged_value(original), value)
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
    return step.status != StepStatus.SKIPPED or "missing" in (step.detail or {})


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
    if step.status == StepStatus.ERROR:
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
    if end is not None and end.get("status") == fmt.RunEnd.FINISHED:
        horizon = int(end["end_ns"])
    else:  # a recovered or failed run: its last instant may be cut short, compare before it
        horizon = max((s.tag[0] for s in original.steps), default=0)

    session = InprocSession(graph)
    values = {e.id: e.value for e in original.events}
    logged = from_the_log(graph)
    for nid in logged:
        ticks = sorted((s for s in original.steps if s.node == nid and s.status != StepStatus.SKIPPED),
                       key=lambda s: s.tag)
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
