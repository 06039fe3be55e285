"""The re-simulation (``retriever replay --resim``): the whole graph re-run in virtual time, its
sources emitting their logged events, and the full trace compared with the log's.

**Memory: a log larger than RAM re-simulates.** ``resim_file(path)`` (what ``--resim`` runs)
reads the file twice and keeps neither, as ``replay_file`` does:

1. ``log.reader.scan_log`` checks it whole (the same errors as ``read_log``, before anything
   runs), handing each chunk (as arrays where its indexes tile it, else message tuples) to a
   :class:`ResimSurvey`: the nodes with step records (each one read and checked), how many
   and the time of the last (the horizon of a run that did not finish), which event ids the log
   holds (``LogSurvey``'s ranges of seqs), and the first step record or event that is not one
   (in file order: the error ``read_log(path).trace()`` raises);
2. the log's records are read again in log-time order (``ScannedLog.records``), as far as the
   re-simulation needs them: a second of virtual time at a time (``WINDOW_NS``) the session
   advances, each replayed source taking its logged ticks as it reaches them, and then the
   records of that second, the log's and the session's, are compared in the order
   ``Trace.first_difference`` compares two whole traces (events by tag, node, port and seq, then
   step records by tag and node) and dropped. An event whose tag is still ahead (a LET output)
   waits for the second it is in. A logged event whose value is an array that decodes surely
   (``codec.decodes_surely``) is compared by its bytes, undecoded: the session's value packed
   to the same bytes is the same record (``_same_event``); a step record without detail by its
   fields (``_Comparison.pair``); anything else decoded and packed, as the two traces would be.

What is held is a second of records (and the log's chunks whose times overlap), however long
the log. The report is the one a comparison of the two whole traces gives: the same first
difference, counted the same way (``record i`` over the events, then the step records).
``resim(log)`` of a log read whole takes the same steps over its message list.
"""

from __future__ import annotations

import os
from collections import deque
from dataclasses import dataclass, field
from operator import itemgetter
from pathlib import Path
from typing import Callable, Iterator

import numpy as np

from ..backends.inproc import InprocSession
from ..codec import array_encoding_head, decodes_surely
from ..errors import LogError, ReplayedError, StepError
from ..log import format as fmt
from ..log.reader import ChunkMessages, LogHead, LoggedEvent, RunLog, logged_event, read_log, step_record
from ..pipeline import Pipeline
from ..trace import Event, StepRecord, StepStatus, event_bytes, step_bytes
from .prepare import code_changes, from_the_log, pipeline_for, set_up_flows, surveyed
from .survey import LogSurvey

#: the virtual time the re-simulation advances before it compares what it and the log recorded
WINDOW_NS = 1_000_000_000


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


class ResimSurvey:
    """What the re-simulation must know of the whole log before it starts, from its messages
    in file order, in memory that does not grow with the log's length (but for what was
    unusual: gaps in an output's seqs)."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self.events = LogSurvey(path)  # which event ids the log holds; its first malformed event
        self.nodes: set[str] = set()
        self.steps = 0
        self.last_ns: int | None = None  # the time of the latest step record
        self.step_error: LogError | None = None
        self._steps_channels: dict[int, bool] = {}

    def take(self, channels: dict, messages: list[tuple]) -> None:
        """Take ``messages``, message tuples in file order (log/reader.py), ``channels`` the log's by id."""
        events = []
        for message in messages:
            log_time, _, channel_id, sequence, publish_time, data = message
            if self._is_steps(channels, channel_id):
                self._step(log_time, sequence, publish_time, data)
            else:
                events.append(message)
        self.events.take(channels, events)

    def take_chunk(self, channels: dict, chunk: ChunkMessages) -> None:
        """Take a chunk's messages, as :func:`scan_log` hands them with ``take_chunk``: the step
        records read one by one in file order, as :meth:`take` reads them, the events by
        ``LogSurvey.take_chunk`` (a chunk at a time)."""
        heads = chunk.heads
        channel_ids = heads["channel_id"]
        steps = [c for c in np.unique(channel_ids).tolist() if self._is_steps(channels, c)]
        if steps and self.step_error is None:
            which = np.flatnonzero(channel_ids == steps[0] if len(steps) == 1 else np.isin(channel_ids, steps))
            step = self._step
            for log_time, sequence, publish_time, data in zip(heads["log_time"][which].tolist(),
                                                              heads["sequence"][which].tolist(),
                                                              heads["publish_time"][which].tolist(), chunk.data(which)):
                step(log_time, sequence, publish_time, data)
        self.events.take_chunk(channels, chunk)

    def _is_steps(self, channels: dict, channel_id: int) -> bool:
        steps = self._steps_channels.get(channel_id)
        if steps is None:
            steps = self._steps_channels[channel_id] = channels[channel_id].topic == fmt.STEPS_TOPIC
        return steps

    def _step(self, log_time: int, sequence: int, publish_time: int, data: bytes) -> None:
        if self.step_error is not None:
            return
        try:
            node = step_record(self.path, log_time, sequence, publish_time, data).node
        except LogError as e:
            self.step_error = e
            return
        self.nodes.add(node)
        self.steps += 1
        if self.last_ns is None or log_time > self.last_ns:
            self.last_ns = log_time

    def logged_nodes(self) -> set[str]:
        """The nodes the log has steps of (or the error of its first step record that is not one)."""
        if self.step_error is not None:
            raise self.step_error
        return self.nodes

    def check_events(self) -> None:
        """Raise the error of the log's first event that is not one."""
        if self.events.event_error is not None:
            raise self.events.event_error


def resim(log: RunLog, pipeline: Pipeline | None = None,
          progress: Callable[[int, int], None] | None = None) -> ResimReport:
    """Re-run the graph in virtual time from the logged source events; compare the trace.
    ``progress(steps compared, steps in the log)`` is called as it goes."""
    survey = ResimSurvey(log.path)
    # as message tuples (log/reader.py), positioned by their index: sorted, in log-time order, ties in file order
    messages = [(m.log_time, i, m.channel_id, m.sequence, m.publish_time, m.data) for i, m in enumerate(log.messages)]
    survey.take(log.channels, messages)
    return _resim(log, survey, lambda: _records(log, sorted(messages)), pipeline, progress)


def resim_file(path: str | os.PathLike, pipeline: Pipeline | Callable[[], Pipeline] | None = None,
               progress: Callable[[str, int, int], None] | None = None) -> ResimReport:
    """:func:`resim` of the log at ``path`` that holds no more than a second of its records at a
    time, however long the log (the module docstring says how). ``pipeline``: as for
    :func:`resim`, or a function that makes it, called once the log has been read.
    ``progress(what, done, total)``: ``"reading"`` with bytes as the file is checked, then
    ``"replaying"`` with steps. A log with messages outside its chunks is read whole."""
    survey = ResimSurvey(Path(path))
    log, pipeline, steps = surveyed(path, survey, pipeline, progress)
    if log.loose:
        return resim(read_log(path), pipeline, steps)
    return _resim(log, survey, log.records, pipeline, steps)


def _records(log: RunLog, messages: list[tuple]) -> Iterator[LoggedEvent | StepRecord]:
    """A log read whole's events and step records, from its message tuples in log-time order."""
    kinds = {c.id: (True if c.topic == fmt.STEPS_TOPIC else fmt.parse_data_topic(c.topic))
             for c in log.channels.values()}
    for log_time, _, channel_id, sequence, publish_time, data in messages:
        kind = kinds.get(channel_id)
        if kind is True:
            yield step_record(log.path, log_time, sequence, publish_time, data)
        elif kind is not None:
            yield logged_event(log.path, kind, log_time, sequence, publish_time, data)


def _resim(log: LogHead, survey: ResimSurvey, records: Callable[[], Iterator], pipeline: Pipeline | None,
           progress: Callable[[int, int], None] | None) -> ResimReport:
    if log.faults:  # the run lost state with a process: no re-run from the start can match it
        nodes = ", ".join(sorted({fault["node"] for fault in log.faults}))
        raise LogError(f"{log.path}: a process of the run died (of {nodes}), so its flow lost its state there: "
                       "--resim re-runs every flow from its start, which this run did not",
                       "retriever replay LOG (without --resim) follows the run through its restarts")
    pipeline = pipeline_for(log, pipeline, survey.logged_nodes)
    graph = pipeline.compile()
    changes = code_changes(log, graph)
    survey.check_events()
    end = log.end
    if end is not None and end.get("status") == fmt.RunEnd.FINISHED:
        horizon = int(end["end_ns"])
    else:  # a recovered or failed run: its last instant may be cut short, compare before it
        horizon = survey.last_ns or 0

    session = InprocSession(graph)
    logged = from_the_log(graph)
    feed = _Feed(log, survey, records(), logged, horizon)
    for nid in logged:
        session.replace_step(nid, feed.outputs(nid))
    comparison = _Comparison(log.value)

    def compare_before(t: int | None) -> None:
        comparison.add(feed.take_before(t), _drained(session))
        comparison.pair(t)
        if progress is not None:
            progress(feed.steps_kept, survey.steps)

    try:
        set_up_flows(session, logged)
        t = 0
        while t < horizon and comparison.event_difference is None:
            t = min(t + WINDOW_NS, horizon)
            session.advance(t)
            feed.read_to(t)
            compare_before(t)
            if getattr(session, "ended", None) is not None:  # a step's sys.exit(0): the run is over
                break
    except StepError as e:
        if not isinstance(e.__cause__, ReplayedError):  # (a logged source's error stopped the run too)
            return ResimReport(horizon, 0, 0, f"the re-simulation stopped: {e}", changes)
    finally:
        session.close()
    # what the session recorded is all in; the rest of the log, a second at a time
    comparison.add(([], []), _drained(session))
    comparison.session_done = True
    t = feed.read_ns
    while not feed.exhausted:
        t += WINDOW_NS
        feed.read_to(t)
        compare_before(t)
    compare_before(None)
    if progress is not None:
        progress(survey.steps, survey.steps)
    return ResimReport(horizon, feed.steps_kept, comparison.counts[0][0], comparison.difference(), changes)


def _drained(session: InprocSession) -> tuple[list[tuple], list[tuple]]:
    """The records the session recorded since the last call, taken out of its trace: plain tuples
    of the fields of an :class:`Event` and a :class:`StepRecord` (made those to be reported)."""
    trace = session.trace
    events, steps = trace.raw_events, trace.raw_steps
    taken = list(events), sorted(steps, key=_raw_step_key)
    trace.discard(len(events), len(steps))
    return taken


def _logged_outputs(step: StepRecord, values: Callable[[tuple], object]) -> list | ReplayedError:
    """What a replayed source's tick gives the re-simulation: its logged events, or its logged
    error (raised again, so that the tick is an error record, handled by ``on_error``, as in
    the run)."""
    if step.status == StepStatus.ERROR:
        error = (step.detail or {}).get("error")
        return ReplayedError(error if type(error) is str else "an error (the log does not say which)")
    return [(i[1], values(i)) for i in step.produced]


class _Feed:
    """The log's records in log-time order, read as far as asked: by a replayed source's next
    tick (its record and the events it produced) or by the comparison (every record before a
    time). Held until the comparison takes them; the sources' values until their tick."""

    def __init__(self, log: LogHead, survey: ResimSurvey, records: Iterator, logged: frozenset[str],
                 horizon: int) -> None:
        self.log, self.survey, self.records, self.horizon = log, survey, records, horizon
        self.ticks: dict[str, deque[StepRecord]] = {nid: deque() for nid in logged}
        self.values: dict[tuple, object] = {}  # a replayed source's logged events, until its tick takes them
        self.events: list[LoggedEvent] = []  # read, not yet taken by the comparison
        self.steps: list[StepRecord] = []
        #: the ids that steps before the horizon produced, whose events are still to be taken
        #: (the events the comparison expects; those of later steps are not compared)
        self.owed: set[tuple] = set()
        self.steps_kept = 0
        self.read_ns = 0  # the log time of the latest record read
        self.ahead = next(records, None)

    @property
    def exhausted(self) -> bool:
        return self.ahead is None

    def _read_one(self) -> bool:
        record = self.ahead
        if record is None:
            return False
        self.ahead = next(self.records, None)
        self.read_ns = max(self.read_ns, record.tag[0])
        if type(record) is StepRecord:
            self.steps.append(record)
            ticks = self.ticks.get(record.node)
            if ticks is not None and record.status != StepStatus.SKIPPED:
                ticks.append(record)
        else:
            self.events.append(record)
            if record.node in self.ticks:
                self.values[record.id] = self.log.value(record)
        return True

    def read_to(self, t: int) -> None:
        """Read every record before log time ``t``."""
        while self.ahead is not None and self.ahead.tag[0] < t:
            self._read_one()

    def outputs(self, node: str) -> Iterator[list | ReplayedError]:
        """A replayed source's ticks: its logged records that were not skipped, in log order."""
        ticks = self.ticks[node]
        while True:
            while not ticks:
                if not self._read_one():
                    return
            yield _logged_outputs(ticks.popleft(), self._value)

    def _value(self, event_id: tuple) -> object:
        values = self.values
        while event_id not in values and self.survey.events.in_log(event_id) and self._read_one():
            pass
        return values.pop(event_id)  # (a KeyError if the log lacks it, as when the log was read whole)

    def take_before(self, t: int | None) -> tuple[list[Event], list[StepRecord]]:
        """The records read before ``t`` (None: all) that the comparison expects: the step records
        before the horizon and the events they produced, values decoded; each list sorted as a
        trace compares them."""
        steps, events = self.steps, self.events
        if t is None:
            now, self.steps = steps, []
            ready, self.events = events, []
        else:
            now, self.steps = [s for s in steps if s.tag[0] < t], [s for s in steps if s.tag[0] >= t]
            ready, self.events = [e for e in events if e.tag[0] < t], [e for e in events if e.tag[0] >= t]
        kept = [s for s in now if s.tag[0] < self.horizon]
        twice = self.survey.events.twice is not None  # an id logged twice: each copy is expected
        owed, in_log = self.owed, self.survey.events.in_log
        for s in kept:  # (an id the log lacks is expected of no event: not held)
            owed.update(i for i in s.produced if in_log(i))
        self.steps_kept += len(kept)
        value = self.log.value
        expected = []
        for e in ready:
            event_id = e.id
            if event_id in owed:
                if not twice:
                    owed.discard(event_id)
                # a value that decodes surely is compared by its bytes, decoded only if they differ;
                # any other is decoded here, so that a damaged one refuses the log here, as it did
                expected.append(e if decodes_surely(e.raw_value) else
                                Event(e.tag, e.node, e.port, e.seq, value(e), e.publish_ns))
        expected.sort(key=_event_key)
        kept.sort(key=_step_key)
        return expected, kept


def _same_event(logged: LoggedEvent, again: tuple) -> bool:
    """Whether ``event_bytes`` of the logged event, its value decoded, is that of the session's,
    told from the logged value's bytes, where they tell it exactly: a value that decodes surely
    (an array of a dtype and shape decoded before) packs again as it was logged, so the two are
    the same if the session's is an array of a plain dtype (no fields, no objects: packed by its
    dtype's string, which decodes to the same dtype) that packs to those bytes. False says
    nothing: compare them decoded. ``again``: the fields of an :class:`Event`, a plain tuple."""
    tag, node, port, seq, value = again[:5]
    if type(value) is not np.ndarray or value.dtype.fields is not None or value.dtype.hasobject:
        return False
    return (logged.seq == seq and logged.tag == tag and logged.port == port and logged.node == node
            and array_encoding_head(value) + value.tobytes() == logged.raw_value)


def _event_key(e: Event) -> tuple:
    return e.tag, e.node, e.port, e.seq


#: _event_key and _step_key of the session's records, plain tuples (_drained)
_raw_event_key, _raw_step_key = itemgetter(0, 1, 2, 3), itemgetter(1, 0)


def _step_key(s: StepRecord) -> tuple:
    return s.tag, s.node


class _Comparison:
    """The log's records (expected) and the session's, compared as two whole traces would be,
    as they come: the events, in order, pair by pair, then the step records, the first
    difference of each kept; what is held is what one side has that the other has not yet."""

    def __init__(self, value: Callable[[LoggedEvent], object]) -> None:
        self.value = value  # a logged event's value, decoded (RunLog.value)
        #: per side (0: the log's, 1: the session's): events and step records not yet paired
        #: (the log's events as read, LoggedEvent, when their value decodes surely: _Feed.take_before;
        #: the session's records as plain tuples, _drained)
        self.events: tuple[deque, deque] = (deque(), deque())
        self.steps: tuple[deque, deque] = (deque(), deque())
        self.counts = [[0, 0], [0, 0]]  # [side][events, steps]
        self.first_step: list[StepRecord | tuple | None] = [None, None]
        self.event_difference: str | None = None
        self.step_difference: tuple[int, StepRecord, StepRecord] | None = None
        self.arrived: tuple[list, list] = ([], [])  # events whose tag is still ahead (a LET output)
        self.paired_events = self.paired_steps = 0
        self.session_done = False  # the session's records are all in

    def add(self, expected: tuple[list[Event | LoggedEvent], list[StepRecord]], again: tuple[list[tuple], list[tuple]]) -> None:
        for side, (events, steps) in enumerate((expected, again)):
            self.counts[side][1] += len(steps)
            if steps and self.first_step[side] is None:
                self.first_step[side] = steps[0]
            if self.step_difference is None:
                self.steps[side].extend(steps)
            self.arrived[side].extend(events)

    def pair(self, t: int | None) -> None:
        """Pair off the events before ``t`` (None: all) and the step records in."""
        for side in (0, 1):
            arrived = self.arrived[side]
            if t is None:
                ready, later = list(arrived), []
            elif side:
                ready, later = [e for e in arrived if e[0][0] < t], [e for e in arrived if e[0][0] >= t]
            else:
                ready, later = [e for e in arrived if e.tag[0] < t], [e for e in arrived if e.tag[0] >= t]
            self.arrived[side][:] = later
            ready.sort(key=_raw_event_key if side else _event_key)
            self.counts[side][0] += len(ready)
            if self.event_difference is None:
                self.events[side].extend(ready)
        mine, theirs = self.events
        while mine and theirs and self.event_difference is None:
            a, b = mine.popleft(), theirs.popleft()
            if type(a) is LoggedEvent:
                if _same_event(a, b):
                    self.paired_events += 1
                    continue
                a = self._decoded(a)
            b = Event._make(b)
            if event_bytes(a) != event_bytes(b):
                self.event_difference = f"record {self.paired_events}: {a!r} != {b!r}"
                mine.clear()
                theirs.clear()
            self.paired_events += 1
        if self.session_done and not theirs and not self.arrived[1]:
            while len(mine) > 1:  # nothing more to pair them with: only the first matters
                mine.pop()
        mine, theirs = self.steps
        while mine and theirs and self.step_difference is None:
            a, b = mine.popleft(), theirs.popleft()
            # the same fields without detail pack the same (step_bytes): the log's are exact strs and
            # ints (format.decode_step checks them), the session's the backend's own
            if a.detail is None and b[5] is None and a[:5] == b[:5]:
                self.paired_steps += 1
                continue
            b = StepRecord._make(b)
            if step_bytes(a) != step_bytes(b):
                self.step_difference = (self.paired_steps, a, b)
                mine.clear()
                theirs.clear()
            self.paired_steps += 1
        if self.session_done and not theirs:
            mine.clear()  # nothing more to pair them with (they are counted)

    def _decoded(self, e: LoggedEvent | Event) -> Event:
        """A logged event as the comparison of two whole traces has it: its value decoded."""
        if type(e) is not LoggedEvent:
            return e
        return Event(e.tag, e.node, e.port, e.seq, self.value(e), e.publish_ns)

    def difference(self) -> str | None:
        """What ``expected.first_difference(again)`` says of the two whole traces."""
        if self.event_difference is not None:
            return self.event_difference
        (events, steps), (events_again, steps_again) = self.counts
        if events == events_again:
            if self.step_difference is not None:
                j, a, b = self.step_difference
                return f"record {events + j}: {a!r} != {b!r}"
            if steps != steps_again:
                return f"lengths differ: {events + steps} records vs {events_again + steps_again}"
            return None
        # one side has more events: where the other's step records begin, an event meets a step
        if events < events_again:
            a, b = self.first_step[0], Event._make(self.events[1][0])
        else:
            a, b = self._decoded(self.events[0][0]), self.first_step[1]
            b = None if b is None else StepRecord._make(b)
        if a is None or b is None:
            return f"lengths differ: {events + steps} records vs {events_again + steps_again}"
        return f"record {min(events, events_again)}: {a!r} != {b!r}"
