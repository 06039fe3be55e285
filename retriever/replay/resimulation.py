"""The re-simulation (``retriever replay --resim``): the whole graph re-run in virtual time, its
sources emitting their logged events, and the full trace compared with the log's.

**Memory: a log larger than RAM re-simulates.** ``resim_file(path)`` (what ``--resim`` runs)
reads the file twice and keeps neither, as ``replay_file`` does:

1. ``log.reader.scan_log`` checks it whole (the same errors as ``read_log``, before anything
   runs), handing each chunk (as arrays where its indexes tile it, else message tuples) to a
   :class:`ResimSurvey`: the nodes with step records (each one checked: those without detail
   as Retriever writes them told by their bytes or parsed with numpy a chunk at a time, the
   others read), how many
   and the time of the last (the horizon of a run that did not finish), which event ids the log
   holds (``LogSurvey``'s ranges of seqs), and the first step record or event that is not one
   (in file order: the error ``read_log(path).trace()`` raises);
2. the log's records are read again in log-time order (``ScannedLog.in_order``'s batches of
   columns; an event kept as a plain tuple of its fields, a replayed source's step record too
   (as msgpack reads it, since the survey checked it), any other step record as read), as far
   as the re-simulation needs them: a
   second of virtual time at a time (``WINDOW_NS``) the session advances, each replayed source
   taking its logged ticks as it reaches them (and decoding their values), and then the records
   of that second, the log's and the session's, are compared in the order
   ``Trace.first_difference`` compares two whole traces (events by tag, node, port and seq, then
   step records by tag and node) and dropped. A second's records of both sides are first paired
   in the order they came (the log's events and step records in log-time order, ties in file
   order; the session's in the order it recorded them, its events sorted by tag alone, ties in
   that order): the same records in the same order nearly always. If each pair is the same,
   sorted they pair the same (the same keys in the same order: one permutation sorts both), so
   nothing else is sorted; at the first pair that is not, both are sorted and compared from the
   start (``_Comparison.add_steps`` and ``pair``). An event whose tag is still ahead (a LET output)
   waits for the second it is in. A logged event whose value is an array that decodes surely
   (``codec.decodes_surely``) is compared by its bytes, undecoded: the session's value packed
   to the same bytes is the same record (``_same_events``). A step record as read is the same as
   the session's if its log time is its tag's time and its data but its wall time is the
   session's packed as the log writer packs a record of the common shape (its seqs and wall time in
   fixed widths: ``log.writer.step_record_maker``, nearly all, and no record is decoded); else it
   is read and compared by its fields, and its detail, if any, packed alone (``_same_steps``);
   anything else decoded and packed, as the two traces would be.

What is held is a second of records (and the log's chunks whose times overlap), however long
the log. The report is the one a comparison of the two whole traces gives: the same first
difference, counted the same way (``record i`` over the events, then the step records).
``resim(log)`` of a log read whole takes the same steps over its message list.
"""

from __future__ import annotations

import os
from bisect import bisect_left
from collections import deque
from itertools import chain
from dataclasses import dataclass, field
from operator import itemgetter
from pathlib import Path
from typing import Callable, Iterator

import msgpack
import numpy as np

from ..backends.inproc import InprocSession
from ..codec import all_decode_surely, array_encoding_head, decodes_surely, packb, unpackb_read_only
from ..errors import LogError, ReplayedError, StepError
from ..graph import Graph
from ..log import format as fmt
from ..log.reader import ChunkMessages, LogHead, LoggedEvent, RunLog, logged_event, read_log, step_record
from ..log.writer import step_record_maker
from ..pipeline import Pipeline
from ..trace import Event, StepRecord, StepStatus, event_bytes, event_difference, semantic_detail, step_bytes
from .prepare import code_changes, from_the_log, pipeline_for, set_up_flows, surveyed
from .survey import NAMED_BEFORE, NOT_IN_LOG, LogSurvey, no_record_of, not_its_event

#: the virtual time the re-simulation advances before it compares what it and the log recorded
WINDOW_NS = 1_000_000_000
#: how the report names the two traces compared (``Trace.first_difference``'s ``names``): the log's, the session's
TRACES = ("the log", "the re-simulation")

_STEPS = "steps"  # _Feed.kinds: the channel of step records
#: how many records a replayed source's tick reads on at a time, as far as its own
_READ_AHEAD = 64


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
    unusual: gaps in an output's seqs): a ``LogSurvey`` that checks every step record
    (``check_steps``: those without detail as Retriever writes them parsed with numpy a chunk at
    a time, with their statuses; the others read), and the time of the latest step record."""

    def __init__(self, path: Path) -> None:
        self.path = path
        #: the nodes with steps and how many, which event ids the log holds, its first malformed
        #: step record and event
        self.events = LogSurvey(path, check_steps=True)
        self.last_ns: int | None = None  # the time of the latest step record
        self._steps_channels: dict[int, bool] = {}

    @property
    def nodes(self) -> set[str]:
        return self.events.nodes

    @property
    def steps(self) -> int:
        return self.events.steps

    @property
    def step_error(self) -> LogError | None:
        return self.events.step_error

    def take(self, channels: dict, messages: list[tuple]) -> None:
        """Take ``messages``, message tuples in file order (log/reader.py), ``channels`` the log's by id."""
        for log_time, _, channel_id, _, _, _ in messages:
            if self._is_steps(channels, channel_id) and (self.last_ns is None or log_time > self.last_ns):
                self.last_ns = log_time
        self.events.take(channels, messages)

    def take_chunk(self, channels: dict, chunk: ChunkMessages) -> None:
        """Take a chunk's messages, as :func:`scan_log` hands them with ``take_chunk`` (as arrays)."""
        heads = chunk.heads
        channel_ids = heads["channel_id"]
        steps = [c for c in np.unique(channel_ids).tolist() if self._is_steps(channels, c)]
        if steps:
            at = channel_ids == steps[0] if len(steps) == 1 else np.isin(channel_ids, steps)
            last = int(heads["log_time"][at].max())
            if self.last_ns is None or last > self.last_ns:
                self.last_ns = last
        self.events.take_chunk(channels, chunk)

    def _is_steps(self, channels: dict, channel_id: int) -> bool:
        steps = self._steps_channels.get(channel_id)
        if steps is None:
            steps = self._steps_channels[channel_id] = channels[channel_id].topic == fmt.STEPS_TOPIC
        return steps

    def logged_nodes(self) -> set[str]:
        """The nodes the log has steps of (or the error of its first step record that is not one)."""
        if self.step_error is not None:
            raise self.step_error
        return self.nodes

    def check_events(self) -> None:
        """Raise the error of the log's first event that is not one (an event logged twice is
        not: each copy is expected of the re-simulation)."""
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
    return _resim(log, survey, lambda: _in_order(messages), pipeline, progress)


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
    return _resim(log, survey, log.in_order, pipeline, steps)


def _in_order(messages: list[tuple]) -> Iterator[tuple[list, ...]]:
    """A log read whole's messages in log-time order (ties in file order), from its message
    tuples, as one batch of columns, as ``ScannedLog.in_order`` hands them."""
    if messages:
        log_times, _, channel_ids, sequences, publish_times, data = map(list, zip(*sorted(messages)))
        yield log_times, channel_ids, sequences, publish_times, data


def _resim(log: LogHead, survey: ResimSurvey, batches: Callable[[], Iterator], pipeline: Pipeline | None,
           progress: Callable[[int, int], None] | None) -> ResimReport:
    if log.faults:  # the run lost state with a process: no re-run from the start can match it
        nodes = ", ".join(sorted({fault["node"] for fault in log.faults}))
        raise LogError(f"{log.path}: a process of the run died (of {nodes}), so its flow lost its state there: "
                       "--resim re-runs every flow from its start, which this run did not",
                       "retriever replay LOG (without --resim) follows the run through its restarts")
    pipeline = pipeline_for(log, pipeline, survey.logged_nodes)
    graph = pipeline.compile()
    survey.events.check_details(graph)
    changes = code_changes(log, graph)
    survey.check_events()
    end = log.end
    if end is not None and end.get("status") == fmt.RunEnd.FINISHED:
        horizon = int(end["end_ns"])
    else:  # a recovered or failed run: its last instant may be cut short, compare before it
        horizon = survey.last_ns or 0

    session = InprocSession(graph)
    logged = from_the_log(graph)
    feed = _Feed(log, survey, batches(), logged, horizon)
    for nid in logged:
        session.replace_step(nid, feed.outputs(nid))
    comparison = _Comparison(log, graph)

    def compare_before(t: int | None) -> None:
        events_again, steps_again = _drained(session)
        produced = comparison.add_steps(feed.steps_before(t), steps_again)
        comparison.add_events(feed.events_before(t, produced), events_again)
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
        if isinstance(e.__cause__, LogError):  # a replayed source's tick found the log damaged
            raise e.__cause__ from None
        if not isinstance(e.__cause__, ReplayedError):  # (a logged source's error stopped the run too)
            return ResimReport(horizon, 0, 0, f"the re-simulation stopped: {e}", changes)
    finally:
        session.close()
    # what the session recorded is all in; the rest of the log, a second at a time
    events_again, steps_again = _drained(session)
    comparison.add_steps([], steps_again)
    comparison.add_events([], events_again)
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
    """The records the session recorded since the last call, taken out of its trace, in the order it
    recorded them: plain tuples of the fields of an :class:`Event` and a :class:`StepRecord` (made
    those to be reported)."""
    trace = session.trace
    events, steps = trace.raw_events, trace.raw_steps
    taken = list(events), list(steps)
    trace.discard(len(events), len(steps))
    return taken


def _logged_outputs(step: tuple, values: Callable[[tuple], object]) -> list | ReplayedError:
    """What a replayed source's tick gives the re-simulation: its logged events, or its logged
    error (raised again, so that the tick is an error record, handled by ``on_error``, as in
    the run). ``step``: the fields of its :class:`StepRecord`, a plain tuple."""
    if step[4] == StepStatus.ERROR:
        error = (step[5] or {}).get("error")
        return ReplayedError(error if type(error) is str else "an error (the log does not say which)")
    return [(i[1], values(i)) for i in step[3]]


class _Feed:
    """The log's records in log-time order, read as far as asked: by a replayed source's next
    tick (its record and the events it produced) or by the comparison (every record before a
    time). Held until the comparison takes them; the sources' values until their tick. A record
    is held as a plain tuple of the fields of a ``LoggedEvent`` (its value undecoded) or of a
    :class:`StepRecord`, read from the batches of columns ``ScannedLog.in_order`` hands: a
    replayed source's step record without detail as msgpack reads it, unchecked, since the
    survey checked every one (``ResimSurvey``: the log is refused before anything runs if one is
    not one); any other step record as read (``(None, (log time,), data, publish time,
    sequence)``: :func:`_step_of` reads it, where the comparison must)."""

    def __init__(self, log: LogHead, survey: ResimSurvey, batches: Iterator[tuple[list, ...]],
                 logged: frozenset[str], horizon: int) -> None:
        self.log, self.survey, self.batches, self.horizon = log, survey, batches, horizon
        self.ticks: dict[str, deque[tuple]] = {nid: deque() for nid in logged}
        #: the replayed sources' nodes as a step record's data has them, after its head (fixstrs)
        self.sources = {msgpack.packb(nid) for nid in logged}
        #: a replayed source's logged events, until its tick takes them (and decodes their values)
        self.values: dict[tuple, tuple] = {}
        self.events: list[tuple] = []  # read, not yet taken by the comparison (in log-time order)
        self.steps: list[tuple] = []
        #: the ids that steps before the horizon produced, whose events are still to be taken
        #: (the events the comparison expects; those of later steps are not compared)
        self.owed: set[tuple] = set()
        #: the ids that steps at or after the horizon produced (not compared, nor their events)
        self.past_horizon: set[tuple] = set()
        #: a log whose writer was killed, recovered or read with salvage=True may keep an event
        #: and lose the step record that produced it (another chunk): such an event is let go
        self.cut_short = not log.complete or fmt.RECOVERED_METADATA in log.metadata
        self.steps_kept = 0
        self.read_ns = 0  # the log time of the latest record read
        #: per channel id: _STEPS, the (node, port) of an event's, or None (neither: not read)
        self.kinds: dict[int, object] = {c.id: _STEPS if c.topic == fmt.STEPS_TOPIC else fmt.parse_data_topic(c.topic)
                                         for c in log.channels.values()}
        self.batch: tuple[list, ...] = ([], [], [], [], [])  # the columns being read, from ...
        self.at = 0  # ... this message on
        self.exhausted = False
        self._next_batch()

    def _next_batch(self) -> bool:
        """Go on to the next batch of columns with a message; False (and exhausted) at the log's end."""
        for batch in self.batches:
            if batch[0]:
                self.batch, self.at = batch, 0
                return True
        self.batch, self.at, self.exhausted = ([], [], [], [], []), 0, True
        return False

    def _read_some(self) -> bool:
        """Read a few records on (``_READ_AHEAD``: a replayed source's tick reads as far as its
        record, one at a time would cost a call each); False at the log's end."""
        if self.at == len(self.batch[0]) and not self._next_batch():
            return False
        self._read_to(min(self.at + _READ_AHEAD, len(self.batch[0])))
        return True

    def read_to(self, t: int) -> None:
        """Read every record before log time ``t``."""
        while True:
            log_times = self.batch[0]
            if self.at < len(log_times) and log_times[self.at] < t:
                self._read_to(bisect_left(log_times, t, self.at))
            if self.at < len(log_times) or not self._next_batch():
                return

    def _read_to(self, stop: int) -> None:
        """Read the batch's messages up to ``stop``."""
        log_times, channel_ids, sequences, publish_times, data = self.batch
        kinds, ticks, values, path = self.kinds, self.ticks, self.values, self.log.path
        add_step, add_event, sources = self.steps.append, self.events.append, self.sources
        skipped = StepStatus.SKIPPED
        start, self.at = self.at, stop
        self.read_ns = max(self.read_ns, log_times[stop - 1])
        for k in range(start, stop):
            kind = kinds.get(channel_ids[k])
            if kind is _STEPS:
                one = data[k]
                record = (None, (log_times[k],), one, publish_times[k], sequences[k])
                if len(one) > 1 and 0xA0 <= one[1] <= 0xBF and one[1:one[1] - 0x9E] not in sources:
                    add_step(record)  # not a replayed source's (its node a fixstr, not theirs): as read
                    continue
                record = _step_of(path, record)
                add_step(record)
                if record[0] in ticks and record[4] != skipped:
                    ticks[record[0]].append(record)
            elif kind is not None:
                node, port = kind
                one = data[k]
                if len(one) >= 3 and one[0] == 0x92 and one[1] < 0x80:  # [microstep < 128, value]: nearly all
                    record = (log_times[k], one[1]), node, port, sequences[k], one[2:], publish_times[k]
                else:
                    e = logged_event(path, kind, log_times[k], sequences[k], publish_times[k], one)
                    record = e.tag, node, port, e.seq, e.raw_value, e.publish_ns
                add_event(record)
                if node in ticks:
                    values[record[1:4]] = record

    def outputs(self, node: str) -> Iterator[list | ReplayedError]:
        """A replayed source's ticks: its logged records that were not skipped, in log order."""
        ticks = self.ticks[node]
        while True:
            while not ticks:
                if not self._read_some():
                    self._no_record_of(node)
                    return
            step = ticks.popleft()
            try:
                outputs = _logged_outputs(step, self._value)
            except KeyError as e:  # (raised in the source's tick: _resim refuses the log with it)
                which = NAMED_BEFORE if self.survey.events.in_log(e.args[0]) else NOT_IN_LOG
                raise not_its_event(self.log.path, step, e.args[0], which) from None
            yield outputs

    def _no_record_of(self, node: str) -> None:
        """The log has ended, and a replayed source's tick is due that it has no record for: an
        event of it that no tick took (in ``values``) is one no record of it names (the log is
        refused, but where it was cut short); else its ticks ran out (the re-simulation stops)."""
        if not self.cut_short:
            for event_id in self.values:
                if event_id[0] == node:
                    raise no_record_of(self.log.path, event_id)

    def _value(self, event_id: tuple) -> object:
        values = self.values
        while event_id not in values and self.survey.events.in_log(event_id) and self._read_some():
            pass
        # (a KeyError if the log lacks it, as when the log was read whole)
        record = values.pop(event_id)
        try:  # (an array as a read-only view of the logged bytes: the tick's emit makes it read-only)
            return unpackb_read_only(record[4])
        except Exception:  # RunLog.value's error for it (the same decoding, which says what is wrong)
            return self.log.value(LoggedEvent(*record))

    def steps_before(self, t: int | None) -> list[tuple]:
        """The step records read before ``t`` (None: all) that the comparison expects: those
        before the horizon, in log-time order, ties in file order (the comparison sorts them as a
        trace compares them, where it must): a replayed source's as the fields of a
        :class:`StepRecord`, any other left as read (``_RAW``, :func:`_step_of` reads it). (The
        records are read in log-time order: those before ``t`` come first.)"""
        steps = self.steps
        if t is None:
            now, self.steps = steps, []
        else:
            cut = len(steps)
            while cut and steps[cut - 1][1][0] >= t:
                cut -= 1
            now = steps[:cut]
            del steps[:cut]
        horizon = self.horizon
        if now and now[-1][1][0] >= horizon:
            path = self.log.path
            past = [_step_of(path, s) for s in now if s[1][0] >= horizon]
            self.past_horizon.update(chain.from_iterable(map(_produced, past)))
            now = [s for s in now if s[1][0] < horizon]
        self.steps_kept += len(now)
        return now

    def events_before(self, t: int | None, produced: list[tuple]) -> list[Event | tuple]:
        """The events read before ``t`` (None: all) that the comparison expects, ``produced`` the
        ids the step records before ``t`` that it expects produced (:meth:`steps_before`): those,
        and those no step record produced (the log lacks the record: compared, as in the two whole
        traces; a replayed source's refuses the log, as plain replay refuses it; let go where the
        log was cut short); an event as read, a plain tuple, when its value decodes surely, else
        an :class:`Event`, value decoded; in log-time order, ties in file order."""
        events = self.events
        if t is None:
            ready, self.events = events, []
        else:
            cut = len(events)
            while cut and events[cut - 1][0][0] >= t:
                cut -= 1
            ready = events[:cut]
            del events[:cut]
        twice = self.survey.events.twice is not None  # an id logged twice: each copy is expected
        owed, log = self.owed, self.log
        values = self.values
        if values and not values.keys().isdisjoint(map(_event_id, ready)):
            # a source's events no tick took (at the horizon, after the session's end): decoded, as read
            for event_id in list(map(_event_id, ready)):
                if event_id in values:
                    log.value(LoggedEvent(*values.pop(event_id)))
        if not owed and not twice and _the_ids_of(produced, ready):
            # the events read are exactly those these steps produced, nothing else owed: nearly
            # always (what owed's bookkeeping below would find, without it and without a set of
            # them: each id expected once, every produced id in the log, owed left empty)
            return ready if all_decode_surely(map(_raw_value, ready)) else [
                e if decodes_surely(e[4]) else _decoded(log, e) for e in ready]
        ids = list(map(_event_id, ready))
        owed.update(produced)
        if not twice and len(owed.intersection(ids)) == len(ids):  # each one expected: nearly always
            owed.difference_update(ids)
            # a value that decodes surely is compared by its bytes, decoded only if they differ;
            # any other is decoded here, so that a damaged one refuses the log here, as it did
            expected = ready if all_decode_surely(map(_raw_value, ready)) else [
                e if decodes_surely(e[4]) else _decoded(log, e) for e in ready]
        else:
            expected = []
            for e, event_id in zip(ready, ids):
                if event_id in owed:
                    if not twice:
                        owed.discard(event_id)
                elif event_id in self.past_horizon or self.cut_short:
                    continue
                elif event_id[0] in self.ticks:  # a replayed source's, which no record of it names
                    raise no_record_of(log.path, event_id)
                # (else an event whose step record the log lacks: compared, as the two traces are)
                expected.append(e if decodes_surely(e[4]) else _decoded(log, e))
        if produced:  # an id the log lacks is expected of no event: not held
            in_log = self.survey.events.in_log
            for event_id in owed.intersection(produced):
                if not in_log(event_id):
                    owed.discard(event_id)
        return expected


def _step_of(path: Path, record: tuple) -> tuple:
    """A step record as the fields of a :class:`StepRecord`, a plain tuple, from one left as read
    (``(None, (log time,), data, publish time, sequence)``, :meth:`_Feed._read_to`; any other is
    one already): one without detail as msgpack reads it (the survey checked it), else as
    ``step_record`` reads it (or its error)."""
    if record[0] is not None:
        return record
    _, (log_time,), one, publish_ns, sequence = record
    try:
        node, microstep, consumed, produced, status, detail, wall_ns = msgpack.unpackb(one, use_list=False)
    except Exception:
        detail = ()
    if detail is None:
        return node, (log_time, microstep), consumed, produced, status, None, publish_ns, wall_ns
    return tuple(step_record(path, log_time, sequence, publish_ns, one))


def _no_record(step: tuple, sequence: int) -> None:
    """A step record's maker's ``otherwise`` (``log.writer.step_record_maker``) for ``--resim``:
    a step of another shape than the common one is not packed, but read and compared."""
    return None


def _step_packers(graph: Graph) -> dict[str, Callable[[tuple, int], bytes | None]]:
    """Per node that has the common shape: ``pack(step, sequence)``, the data of a step record of
    it (the fields of a :class:`StepRecord`, a plain tuple) as the log writer packs one of that
    shape (``log.writer.step_record_maker``: ``ok``, no detail, a microstep below 128, one event on
    the node's one output and one consumed on each input port an edge feeds, its seqs uint32s, its
    wall time a uint64), or None for a step of another shape, or of a wall time of 2**32 ns or
    more (the uint64's first 4 bytes zeros: a uint32's pack, the cheaper; such a step is read and
    compared instead)."""
    makers = {node: step_record_maker(graph, node, None, _no_record, wall_bytes=4) for node in graph.nodes}
    return {node: make for node, make in makers.items() if make is not _no_record}


def _the_ids_of(produced: list[tuple], events: list[tuple]) -> bool:
    """Whether ``produced`` (event ids) are the ids of ``events`` (plain tuples, their ids distinct),
    each once, told in one pass as far as the two orders agree (nearly all: an event is logged at
    the time of the step that produced it, but for a LET output, logged later, whose id waits in a
    set for its event). False says nothing when both hold the same ids in another order than that
    (an event before the step record that produced it)."""
    n = len(produced)
    if n != len(events):
        return False
    ahead: set[tuple] = set()  # produced, their events not met yet
    i = 0
    for e in events:
        while True:
            if i < n:
                p = produced[i]
                if p[2] == e[3] and p[1] == e[2] and p[0] == e[1]:
                    i += 1
                    break
            event_id = e[1:4]
            if event_id in ahead:
                ahead.discard(event_id)
                break
            if i == n:  # an event none of them produced (so too if one was produced twice: as many)
                return False
            ahead.add(p)
            i += 1
    return True


def _same_events(mine: deque, theirs: deque, heads: dict[int, tuple[bytes, np.dtype, tuple]]) -> int:
    """Pair off the events at the front of ``mine`` (the log's) and ``theirs`` (the session's)
    whose ``event_bytes`` are the same, told from the logged value's bytes, where they tell it
    exactly, in one loop; how many. Stops at the first pair it cannot tell (left in place): the
    comparison's own loop compares it decoded. A logged value that decodes surely (left a plain
    tuple by ``_Feed.events_before``: an array of a dtype and shape decoded before) packs again as
    it was logged, so the two are the same if the session's is an array of a plain dtype (no
    fields, no objects: packed by its dtype's string, which decodes to the same dtype) that
    packs to those bytes, its encoding's head (``codec.array_encoding_head``) then its raw
    bytes. The head is looked up by the logged value's length (``heads``: per length, a head of
    that long an encoding, with its array's dtype and shape, as the session's arrays had them):
    the session's value has that head when its dtype and shape are those, and the two are the
    same if that head and the session's raw bytes are the logged bytes (one join and one
    compare: ``startswith`` and ``endswith`` parse their arguments, 1.4k instructions an event
    more). ``mine``'s: the fields of a ``LoggedEvent``
    or an :class:`Event`; ``theirs``: the fields of an :class:`Event`, plain tuples."""
    paired = 0
    ndarray = np.ndarray
    while mine and theirs:
        a, b = mine.popleft(), theirs.popleft()
        value = b[4]
        if type(a) is tuple and type(value) is ndarray and a[3] == b[3] and a[0] == b[0] and a[2] == b[2] \
                and a[1] == b[1]:
            raw, dtype, shape = a[4], value.dtype, value.shape
            known = heads.get(len(raw))
            if known is None or (known[1] is not dtype and known[1] != dtype) or known[2] != shape:
                known = None
                if dtype.fields is None and not dtype.hasobject:
                    head = array_encoding_head(value)
                    if len(head) + value.nbytes == len(raw):
                        known = heads[len(raw)] = head, dtype, shape
            if known is not None and known[0] + value.tobytes() == raw:
                paired += 1
                continue
        mine.appendleft(a)
        theirs.appendleft(b)
        return paired
    return paired


def _same_events_in_order(mine: list, theirs: list[tuple], heads: dict[int, tuple[bytes, np.dtype, tuple]]) -> bool:
    """Whether each event of ``mine`` (the log's) is the same as the one at its place in ``theirs``
    (the session's, as many) as :func:`_same_events` tells a pair by its bytes (a head it has not
    found yet: not told here)."""
    ndarray = np.ndarray
    for a, b in zip(mine, theirs):
        value = b[4]
        if type(a) is not tuple or type(value) is not ndarray or a[3] != b[3] or a[0] != b[0] or a[2] != b[2] \
                or a[1] != b[1]:
            return False
        raw, dtype = a[4], value.dtype
        known = heads.get(len(raw))
        if known is None or (known[1] is not dtype and known[1] != dtype) or known[2] != value.shape \
                or known[0] + value.tobytes() != raw:
            return False
    return True


def _same_detail(a: dict | None, b: dict | None) -> bool:
    """Whether two step records whose other compared fields are the same (as Python values, as
    :func:`_same_steps` has them) are the same record: their details (but the timing keys) packed
    as ``step_bytes`` packs them. (Packing the detail alone, not the whole record, whose tag and
    ids go through the codec's tuple extension.)"""
    return packb(semantic_detail(a)) == packb(semantic_detail(b))


def _same_steps(mine: deque, theirs: deque) -> int:
    """Pair off the step records at the front of ``mine`` (the log's) and ``theirs`` (the
    session's) that are the same, in one loop; how many. Stops at the first pair that is not
    (left in place): the comparison's own loop takes it. (The same fields pack the same,
    ``step_bytes``: the log's are exact strs and ints, ``format.decode_step`` checks them, the
    session's the backend's own; a detail, which may hold anything msgpack reads, is compared
    packed, :func:`_same_detail`.)"""
    paired = 0
    while mine and theirs:
        a, b = mine.popleft(), theirs.popleft()
        if a[:5] == b[:5] and (a[5] is None and b[5] is None or _same_detail(a[5], b[5])):
            paired += 1
            continue
        mine.appendleft(a)
        theirs.appendleft(b)
        return paired
    return paired


_produced, _event_id, _raw_value = itemgetter(3), itemgetter(1, 2, 3), itemgetter(4)  # of the plain tuples

#: how a trace sorts its events (tag, node, port, seq) and step records (tag, node), of an Event or
#: StepRecord and of the plain tuples of their fields alike
_raw_event_key, _raw_step_key = itemgetter(0, 1, 2, 3), itemgetter(1, 0)
_tag = itemgetter(0)  # of an event's plain tuple: (time, microstep), sorted before (t,) when time < t


def _decoded(log: LogHead, e: tuple | Event) -> Event:
    """A logged event as the comparison of two whole traces has it: its value decoded.
    ``e``: the fields of a ``LoggedEvent``, a plain tuple, or an Event already."""
    if type(e) is not tuple:
        return e
    return Event(e[0], e[1], e[2], e[3], log.value(LoggedEvent(*e)), e[5])


class _Comparison:
    """The log's records (expected) and the session's, compared as two whole traces would be,
    as they come: the events, in order, pair by pair, then the step records, the first
    difference of each kept; what is held is what one side has that the other has not yet."""

    def __init__(self, log: LogHead, graph: Graph) -> None:
        self.log = log  # whose events' values are decoded (RunLog.value)
        #: per node: its step records' data as the log writer packs those of the common shape (_step_packers)
        self.packers = _step_packers(graph)
        #: per side (0: the log's, 1: the session's): events and step records not yet paired
        #: (the log's events as read, plain tuples, when their value decodes surely: _Feed.events_before;
        #: its step records and the session's records as plain tuples too, _Feed and _drained)
        self.events: tuple[deque, deque] = (deque(), deque())
        self.steps: tuple[deque, deque] = (deque(), deque())
        self.counts = [[0, 0], [0, 0]]  # [side][events, steps]
        self.event_difference: str | None = None
        self.step_difference: tuple[int, StepRecord, StepRecord] | None = None
        self.arrived: tuple[list, list] = ([], [])  # events whose tag is still ahead (a LET output)
        self.paired_events = self.paired_steps = 0
        self.session_done = False  # the session's records are all in
        #: per length of a logged value: (the head of an array's encoding that long, its dtype, its shape),
        #: of a plain dtype, as the session's arrays had them (_same_events)
        self._heads: dict[int, tuple[bytes, np.dtype, tuple]] = {}

    def add_steps(self, steps: list[tuple], again: list[tuple]) -> list[tuple]:
        """Take a second's step records of each side (the log's as :meth:`_Feed.steps_before`
        gives them, the session's as it recorded them; each in any order: sorted here as a trace
        compares them, as far as needed), paired at once when they are the same in the order they
        came (then, sorted, they pair the same: the same records, in the same order); the ids the
        log's produced, in their order."""
        self.counts[0][1] += len(steps)
        self.counts[1][1] += len(again)
        mine, theirs = self.steps
        if self.step_difference is None and not mine and not theirs and len(steps) == len(again):
            produced = self._same_in_order(steps, again)
            if produced is not None:
                self.paired_steps += len(steps)
                return produced
        path = self.log.path
        steps = [_step_of(path, s) for s in steps]
        produced = list(chain.from_iterable(map(_produced, steps)))
        if self.step_difference is None:
            steps.sort(key=_raw_step_key)
            again.sort(key=_raw_step_key)
            mine.extend(steps)
            theirs.extend(again)
        return produced

    def _same_in_order(self, mine: list[tuple], theirs: list[tuple]) -> list[tuple] | None:
        """Whether each step record of ``mine`` (the log's) is the same as the one at its place in
        ``theirs`` (the session's, as many), as :func:`_same_steps` tells a pair: the ids the log's
        produced, or None. One left as read is the same as the session's if its log time is its tag's
        time and its data but its wall time's 8 bytes is the session's packed as the log writer
        packs it (``packers``: one of the common shape, nearly all); else it is read, and compared
        field by field (no slices made)."""
        packers, path = self.packers, self.log.path
        produced: list[tuple] = []
        add = produced.extend
        for a, b in zip(mine, theirs):
            if a[0] is None:
                pack = packers.get(b[0])
                if pack is not None and a[1][0] == b[1][0]:
                    data = pack(b, 0)
                    if data is not None and data[:-8] == a[2][:-8]:
                        add(b[3])
                        continue
                a = _step_of(path, a)
            if a[1] != b[1] or a[0] != b[0] or a[3] != b[3] or a[2] != b[2] or a[4] != b[4] \
                    or (a[5] is not None or b[5] is not None) and not _same_detail(a[5], b[5]):
                return None
            add(a[3])
        return produced

    def add_events(self, expected: list[Event | tuple], again: list[tuple]) -> None:
        """Take a second's events of each side (the log's as :meth:`_Feed.events_before` gives
        them, the session's as it recorded them): paired by :meth:`pair`."""
        self.arrived[0].extend(expected)
        self.arrived[1].extend(again)

    def pair(self, t: int | None) -> None:
        """Pair off the events before ``t`` (None: all) and the step records in."""
        arrived, arrived_again = self.arrived
        ready = arrived[:]  # (the log's are all before t: _Feed.events_before)
        arrived.clear()
        # the session's before t: first once sorted by tag (a stable sort: ties in the order recorded)
        arrived_again.sort(key=_tag)
        cut = len(arrived_again) if t is None else bisect_left(arrived_again, (t,), key=_tag)
        ready_again = arrived_again[:cut]
        del arrived_again[:cut]
        self.counts[0][0] += len(ready)
        self.counts[1][0] += len(ready_again)
        mine, theirs = self.events
        if self.event_difference is None:
            if not mine and not theirs and len(ready) == len(ready_again):
                # as they came (the log's in log-time order, ties in file order; nearly always the
                # order the session recorded them in): if each pair is the same, sorted they pair the
                # same (the same keys in the same order: the same permutation sorts both)
                if _same_events_in_order(ready, ready_again, self._heads):
                    self.paired_events += len(ready)
                    ready = ready_again = []
            ready.sort(key=_raw_event_key)
            ready_again.sort(key=_raw_event_key)
            mine.extend(ready)
            theirs.extend(ready_again)
        while mine and theirs and self.event_difference is None:
            self.paired_events += _same_events(mine, theirs, self._heads)
            if not (mine and theirs):
                break
            a, b = _decoded(self.log, mine.popleft()), Event._make(theirs.popleft())
            if event_bytes(a) != event_bytes(b):
                self.event_difference = event_difference(self.paired_events, a, b, TRACES)
                mine.clear()
                theirs.clear()
            self.paired_events += 1
        if self.session_done and not theirs and not self.arrived[1]:
            while len(mine) > 1:  # nothing more to pair them with: only the first matters
                mine.pop()
        mine, theirs = self.steps
        while mine and theirs and self.step_difference is None:
            self.paired_steps += _same_steps(mine, theirs)
            if not (mine and theirs):
                break
            a, b = StepRecord._make(mine.popleft()), StepRecord._make(theirs.popleft())
            if step_bytes(a) != step_bytes(b):
                self.step_difference = (self.paired_steps, a, b)
                mine.clear()
                theirs.clear()
            self.paired_steps += 1
        if self.session_done and not theirs:
            mine.clear()  # nothing more to pair them with (they are counted)

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
        # one side has more events: the first of those it has left is the other's to lack
        if events < events_again:
            return event_difference(events, None, Event._make(self.events[1][0]), TRACES)
        return event_difference(events_again, _decoded(self.log, self.events[0][0]), None, TRACES)
