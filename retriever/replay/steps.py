"""The replay of a log's steps (:class:`StepReplay`): each logged step of a flow the replay
re-executes runs again on inputs rebuilt from the logged events, as the run delivered them, and
is compared with the log (compare.py), the comparisons reported in step order."""

from __future__ import annotations

import bisect
import functools
from heapq import heappop, heappush
from collections import deque
from typing import Callable, Iterator

from ..backends.inproc import PLAIN_TYPES, InprocSession
from ..codec import Encoder, decodes_surely, unpackb
from ..errors import LogError, RunEnded, StepError
from ..flow.read_only import make_read_only
from ..log import format as fmt
from ..log.reader import LogHead, LoggedEvent
from ..sync import Latest, before, bound, fill
from ..trace import STEPPED, StepRecord, StepStatus, Trace
from .compare import TickCheck, compare_outputs, compare_record, off_clock
from .report import MAX_DIVERGENCES_KEPT, Divergence, NodeReplay, ReplayReport
from .survey import NAMED_BEFORE, NOT_IN_LOG, LogSurvey, no_record_of, not_its_event

PROGRESS_EVERY = 2000
_SKIPPED, _LATE, _OK = StepStatus.SKIPPED, StepStatus.LATE, StepStatus.OK
_UNSEEN = object()  # the default of waiting.pop: no record claimed the event yet (None: one let it go)


class _Check:
    """One logged step's comparison, in step order: decided when every logged output it needs
    has been read (a LET step's outputs come later in the log than its tick)."""

    __slots__ = ("step", "stats", "events", "stamped", "originals", "waiting", "found", "done")

    def __init__(self, step, stats: NodeReplay, found: Divergence | None = None, done: bool = True) -> None:
        self.step, self.stats, self.found, self.done = step, stats, found, done
        self.originals: dict[tuple, tuple] = {}  # id -> (tag, raw value): a logged output read
        self.waiting = 0


class _Logged:
    """A logged value that decodes surely (codec.decodes_surely), decoded when a tick first takes
    it (then that one value at every tick that takes it, as in the run): routed to Latest inputs
    only, whose policy never looks at it, and most of which no tick takes (the quickstart's
    policy takes 1 in 100 of the controller's states)."""

    __slots__ = ("raw", "value")

    def __init__(self, raw: bytes) -> None:
        self.raw, self.value = raw, _Logged


def _take_logged(values: dict) -> None:
    """A tick's input values, those still logged decoded (InprocSession.prepare_inputs)."""
    for port, value in values.items():
        if type(value) is _Logged:
            if value.value is _Logged:
                value.value = unpackb(value.raw)
                make_read_only(value.value)  # an emitted value is immutable, as in the run (see read())
            values[port] = value.value


class StepReplay:
    """One replay of a log's steps (:meth:`play`): the log's messages read once in log-time
    order (``messages()``), an instant at a time::

        an instant's messages ─┬─ events ─→ read: decoded once (_Logged: once taken), to the
                               │            consumers' deliveries (a heap by arrival) and to
                               │            the check waiting for them
                               └─ records → run, in (tag, node) order: checked against the clock,
                                            the deliveries due put in, the tick re-executed,
                                            compared (its outputs once read: decide), the
                                            comparisons reported in step order (flush)
        the log's end ─────────→ finish: the checks no output came for; the kept trace

    What is held is what the instants still to come need (deliveries not due, comparisons waiting
    for a LET output, the survey's exceptions)."""

    __slots__ = ("log", "session", "sources", "keep_trace", "encode", "routes", "put_off", "late", "gaps", "missed", "in_log",
                 "lost", "floors", "stamped", "cut_short", "report", "total", "done", "on_clock", "next_ticks",
                 "last_ticks",
                 "deliveries", "delivered", "late_at", "unclaimed", "waiting", "checks", "now",
                 "kept_steps", "kept_parts", "kept_events", "unchecked", "tick", "tape", "expected", "died",
                 "deaths_timed", "reborn", "run_step")

    def __init__(self, log: LogHead, survey: LogSurvey, graph, session: InprocSession, sources: frozenset[str],
                 keep_trace: bool) -> None:
        survey.check_events()
        self.log, self.session, self.sources, self.keep_trace = log, session, sources, keep_trace
        self.encode = Encoder().pack
        self.routes = session.take_routes()
        self.tick, self.tape = session.tick, session.trace.tape  # a tick run again, and where it records
        # the ports whose every consumer takes them with Latest: their values decoded once taken
        self.put_off = {port for port, consumers in self.routes.items()
                        if consumers and all(type(buf.policy) is Latest for _, buf, _ in consumers)}
        for node in {consumer[0] for port in self.put_off for consumer, _, _ in self.routes[port]}:
            session.prepare_inputs(node, _take_logged)
        self.late, self.gaps, self.missed = survey.late, survey.gaps, survey.views()
        self.in_log, self.unchecked = survey.in_log, survey.unchecked
        # a lost process's outputs that its records claim and no report carried: not comparable (a
        # consumer may still have carried one in: that one is in the log, and compared)
        self.lost = {event_id for fault in log.faults for event_id in fault["lost_events"] if not self.in_log(event_id)}
        # per node whose process died: per death, in time order, [its time, the tag of the node's last
        # step record at or before it] (_run_noting_deaths; _died_with_its_record). A fault's time is
        # the coordinator's clock; a deployment's nodes stamp by their workers' HLCs, up to the
        # furthest ahead a worker said its clock was (else an event stamped just before a death that
        # the coordinator noticed sooner than that was refused): the death is taken that much later
        ahead = 0 if log.deployment is None else log.deployment.clock_ahead_ns()
        self.died: dict[str, list[list]] = {}
        for fault in sorted(log.faults, key=lambda fault: int(fault.get("at_ns", "0"))):
            self.died.setdefault(fault["node"], []).append([int(fault.get("at_ns", "0")) + ahead, None])
        # a virtual-time run's fault has the coordinator's wall time since T0, which says nothing
        # of its tags (the run goes as fast as its steps do): any event of a flow that died is let go
        self.deaths_timed = log.run.get("time") != "virtual"
        self.reborn: dict[str, int] = {}  # node -> how many of its deaths a new process followed (_run_noting_deaths)
        self.run_step = self._run_noting_deaths if self.died and self.deaths_timed else self.run
        self.floors: dict[tuple[str, str, str], int] = {}  # (consumer, producer, port) -> first seq it takes
        # In real time a flow without latency stamps its outputs when it finishes (ASAP): the tag
        # is then checked for causality (after the tick), not recomputed.
        realtime = log.run.get("backend", "inproc") != "inproc"
        self.stamped = {nid for nid, node in graph.nodes.items() if realtime and not node.settings.latency_ns}
        # a log whose writer was killed, recovered or read with salvage=True, may keep a step record
        # (one chunk) and lose the events it consumed or produced (another): such a step cannot be compared
        self.cut_short = not log.complete or fmt.RECOVERED_METADATA in log.metadata
        self.report = ReplayReport({nid: NodeReplay(from_log=nid in sources) for nid in sorted(graph.nodes)})
        self.total, self.done = survey.steps, 0
        self.on_clock = TickCheck(graph)
        self.next_ticks = self.on_clock.next  # node -> its rate's next tick after the last found (TickCheck)
        self.last_ticks: dict[str, tuple[int, int]] = {}  # node -> the tag of its last record on its clock
        self.deliveries: list = []  # heap of (arrival, n, consumer node, buffer, entry)
        self.delivered = 0  # events put on the heap: its tie-break, the order the log was read in
        self.late_at: dict[tuple[str, tuple[int, int]], list] = {}  # (consumer node, record tag) -> [(buf, entry)]
        # events read whose step record has not been replayed yet: id -> (tag, raw value)
        self.unclaimed: dict[tuple, tuple] = {}
        self.waiting: dict[tuple, _Check | None] = {}  # outputs a replayed record named, not read yet -> its check
        self.expected: dict[tuple, tuple] = {}  # a source's outputs its record named, not read yet -> the record
        self.checks: deque[_Check] = deque()  # in step order, from the first not decided
        self.now = (-1, 0)  # the tag of the instant whose steps run
        # keep_trace: every step record, and in step order the outputs of each
        self.kept_steps, self.kept_parts, self.kept_events = [], [], {}

    def play(self, messages: Callable[[], Iterator], progress: Callable[[int, int], None] | None) -> ReplayReport:
        """Replay the log: each instant's messages read, then its step records run. ``messages()``
        gives them in log-time order (ties in file order) in batches of columns, as
        ``ScannedLog.in_order`` does: ``(log_times, channel_ids, sequences, publish_times, data)``."""
        log = self.log
        steps_channels = {c.id for c in log.channels.values() if c.topic == fmt.STEPS_TOPIC}
        ports = {c.id: parsed for c in log.channels.values() if (parsed := fmt.parse_data_topic(c.topic))}
        read, run = self.read, self.run_step
        record = _step_record
        unchecked = self.unchecked
        steps: list = []
        instant = None
        for log_times, channels, sequences, publish_times, datas in messages():
            for log_time, channel, sequence, publish_time, data in zip(log_times, channels, sequences,
                                                                       publish_times, datas):
                if log_time != instant:
                    if steps:  # the instant's messages are read: run its steps
                        if len(steps) == 1 and progress is None:  # (the commonest, run_instant's loop inlined)
                            self.done += 1
                            run(steps.pop())
                        else:
                            self.run_instant(steps, progress)
                    instant = log_time
                    self.now = (instant, 0)  # every record before it has run
                if channel in steps_channels:
                    try:  # (found plain by the survey, which read the same file: its status to check)
                        node, microstep, consumed, produced, status, detail, wall_ns = (
                            fmt.decode_step(data) if unchecked is None or sequence in unchecked
                            else fmt.decode_plain_step(data))
                    except Exception as e:
                        raise LogError(f"{log.path}: step record #{sequence} is malformed ({e})") from None
                    steps.append(record((node, (log_time, microstep), consumed, produced, status, detail,
                                         publish_time, wall_ns)))
                else:
                    port = ports.get(channel)
                    if port is not None:
                        read(port, log_time, sequence, publish_time, data)
        if steps:
            self.run_instant(steps, progress)
        return self.finish(progress)

    def read(self, port: tuple[str, str], log_time: int, seq: int, publish_time: int, data: bytes) -> None:
        """An event read: to its consumers' deliveries, and to the check waiting for it."""
        if len(data) > 2 and data[0] == 0x92 and data[1] < 0x80:  # fmt.split_event's commonest case, inlined
            tag, raw = (log_time, data[1]), data[2:]
        else:
            try:
                microstep, raw = fmt.split_event(data)
            except ValueError as e:
                raise LogError(f"{self.log.path}: event {port[0]}.{port[1]} #{seq} is malformed ({e})") from None
            tag = (log_time, microstep)
        # (a LoggedEvent only where one is needed: the kept trace, a value that does not decode)
        node, port_name = port
        event_id = (node, port_name, seq)
        if self.keep_trace:
            self.kept_events[event_id] = LoggedEvent(tag, node, port_name, seq, raw, publish_time)
        consumers = self.routes.get(port)
        if consumers:
            if port in self.put_off and decodes_surely(raw):
                value = _Logged(raw)
            else:
                try:
                    value = unpackb(raw)
                except Exception:  # what it is, said as the log says it
                    self.log.value(LoggedEvent(tag, node, port_name, seq, raw, publish_time))
                    raise
                if type(value) not in PLAIN_TYPES:  # (the commonest, a number, has no array)
                    # an emitted value is immutable: its arrays read-only, as the run's consumers
                    # had them (the codec decodes a copy, writable), so that a step that wrote into
                    # its input fails in the replay as it did in the run
                    make_read_only(value)
            gaps, late, missed = self.gaps, self.late, self.missed
            if gaps or late or missed:
                self.deliver_later(consumers, tag, node, port_name, seq, event_id, value)
            else:  # (the commonest: no restart gap, no late arrival, no incomplete tick in the log)
                delivered = self.delivered
                for consumer, buf, delay_ns in consumers:
                    arrival = (log_time + delay_ns, 0) if delay_ns else tag
                    heappush(self.deliveries, (arrival, delivered, consumer[0], buf, (arrival, node, port_name, seq, value)))
                    delivered += 1
                self.delivered = delivered
        check = self.waiting.pop(event_id, _UNSEEN)
        if check is _UNSEEN:
            self.unclaimed[event_id] = (tag, raw)
        elif check is not None:
            check.originals[event_id] = (tag, raw)
            check.waiting -= 1
            if check.waiting == 0:
                self.decide(check)
                self.flush()
        elif self.expected:
            self.expected.pop(event_id, None)

    def deliver_later(self, consumers: list, tag: tuple[int, int], node: str, port_name: str, seq: int,
                      event_id: tuple, value) -> None:
        """An event read, to its consumers' deliveries, in a log with restart gaps, late arrivals
        or incomplete ticks: but those a restart gap withholds, or that a consumer never had."""
        gaps, late, missed = self.gaps, self.late, self.missed
        for consumer, buf, delay_ns in consumers:
            if gaps and _in_gap(gaps.get(consumer), node, port_name, seq):
                continue
            arrival = (tag[0] + delay_ns, 0) if delay_ns else tag
            entry = (arrival, node, port_name, seq, value)
            seen_at = late.get((consumer, event_id)) if late else None
            if seen_at is not None:
                if seen_at < self.now:  # a record before its time names it (a changed log): in at once
                    buf.insert(entry)
                else:
                    self.late_at.setdefault((consumer[0], seen_at), []).append((buf, entry))
            elif not missed or not _never_had(missed.get((consumer, node, port_name)), arrival, seq):
                heappush(self.deliveries, (arrival, self.delivered, consumer[0], buf, entry))
                self.delivered += 1

    def run_instant(self, steps: list, progress: Callable[[int, int], None] | None) -> None:
        """Run an instant's step records, its messages all read, in (tag, node) order."""
        if len(steps) > 1:
            steps.sort(key=_microstep_node)
        run, done = self.run_step, self.done
        for step in steps:
            if progress is not None and done % PROGRESS_EVERY == 0:
                progress(done, self.total)
            done += 1
            run(step)
        self.done = done
        steps.clear()

    def _run_noting_deaths(self, step) -> None:
        """:meth:`run`, in a log whose fault records say a process died: a record of its node
        at or before a death is the node's last so far before it (records run in tag order), but
        one of a process that replaced the dead one: a record with ``detail.restarted`` (its new
        process's first) ends the earliest death still open, which no later record is then of
        (a restart within the workers' clock lead of the death, taken later by it, was taken for
        the dead process's last record)."""
        node = step.node
        deaths = self.died.get(node)
        if deaths is not None:
            if step.detail and "restarted" in step.detail:
                self.reborn[node] = self.reborn.get(node, 0) + 1
            for death in deaths[self.reborn.get(node, 0):]:
                if step.tag[0] <= death[0]:
                    death[1] = step.tag
        self.run(step)

    def _died_with_its_record(self, event_id: tuple, tag: tuple[int, int]) -> bool:
        """Whether an event that no step record names may be one whose record its process died
        with: on ``zenoh`` a node reports its events before its records, which it sends in order
        and may hold back (backends/zenoh/node/reports.py), and a consumer that took an event may
        carry it in (docs/log.md); a kill loses the records not sent yet, none before one that was.
        So: an event of a node whose process died at or after its tag, later than every record of
        the node at or before that death (the first death at or after its tag: a fresh process's
        records come after it). Any other such event is no output of a step the run made. In a
        virtual-time log the deaths' times are not the tags': any event of a node that died."""
        if not self.deaths_timed:
            return event_id[0] in self.died
        for at_ns, last in self.died.get(event_id[0], ()):
            if tag[0] <= at_ns:
                return last is None or last < tag
        return False

    def run(self, step) -> None:
        """One logged step: checked against its node's clock, the run's restart and late arrivals
        at it done again, then re-executed and compared; a source's, or a tick the run did not
        step, is not re-executed: its outputs are taken from the log."""
        node, tag, detail = step.node, step.tag, step.detail
        stats = self.report.nodes[node]
        stats.steps += 1
        # a source is not re-executed: its records are checked against its clock (a forged
        # record between its ticks, or a second at one, is no step the run made)
        expected = self.next_ticks.get(node)
        if expected is not None and expected[0] == tag:  # its rate's next tick (TickCheck, inlined): no second one
            _, k, offset, num, den = expected
            k += 1
            self.next_ticks[node] = ((offset + k * num // den, 0), k, offset, num, den)
            self.last_ticks[node] = tag
        else:
            found = off_clock(step, self.on_clock, self.last_ticks)
            if found is not None:
                if node in self.sources:  # (a record twice names its events twice)
                    self.take_logged(step)
                self.checks.append(_Check(step, stats, found))
                self.flush()
                return
        if detail:
            restarted = detail.get("restarted")
            if restarted is not None:
                _restart_afresh(self.session, node, restarted, self.floors)
        if self.late_at:
            for buf, entry in self.late_at.pop((node, tag), ()):
                fill(buf, entry, before(tag))  # it arrived late: in the buffer from this record on, as in the run
        keep_trace = self.keep_trace
        if keep_trace:
            self.kept_steps.append(tuple(step))
        # the run called step() at every tick but one that a real-time run stopped before stepping
        # (realtime="hard", an incomplete edge): a skipped tick without "missing"
        if node in self.sources:
            self.take_logged(step)
            if keep_trace:  # not re-executed: its outputs as logged
                self.kept_parts.append(step.produced)
            return
        if step.status == _SKIPPED and not (detail and "missing" in detail):
            self.claim(step.produced, None)
            if keep_trace:  # not re-executed: its outputs as logged
                self.kept_parts.append(step.produced)
            return
        deliveries = self.deliveries
        if deliveries and deliveries[0][0] <= tag:
            # the deliveries that arrived by its tag in their buffers, but those a restarted consumer
            # no longer takes (sync.fill inlined, and PortBuffer.insert's commonest case: the newest entry)
            floors, after = self.floors, None
            while deliveries and deliveries[0][0] <= tag:
                _, _, consumer, buf, entry = heappop(deliveries)
                if not floors or entry[3] >= floors.get((consumer, entry[1], entry[2]), 0):
                    entries = buf.entries
                    if entries and entries[-1] >= entry:
                        buf.insert(entry)
                    else:
                        entries.append(entry)
                    if len(entries) >= buf.bound_at:
                        if after is None:
                            after = before(tag)  # steps run in tag order: every tick to come is at or after this one
                        bound(buf, after)
        try:
            self.tick(node, tag)
        except (StepError, RunEnded):
            pass  # on_error="stop", or sys.exit(0): the step is recorded; compare it like any other
        tape = self.tape
        if len(tape) == 2 and step.status != _LATE:  # one event and the record (the commonest): as _taken, without the scans
            event, replayed = tape
            if type(event) is tuple and type(replayed) is tuple and len(event) == 6 and len(replayed) != 6:
                tape.clear()
                events = [event]
            else:
                replayed, events = _taken(self.session, step)
        else:
            replayed, events = _taken(self.session, step)
        if keep_trace:
            self.kept_parts.append(events)
        stats.replayed += 1
        produced = step.produced
        if (len(produced) == 1 and len(events) == 1 and replayed[4] is _OK and not self.lost and not self.cut_short
                and replayed[3] == produced and replayed[2] == step.consumed and step.status in STEPPED
                and node not in self.stamped):
            # the same record, of one output (the commonest; a record's ids are its events', in order):
            # compare's checks, compare_record's and, once the output is read, compare_outputs', the one way they pass
            unclaimed, (event_id,) = self.unclaimed, produced
            original = unclaimed.get(event_id)
            if original is not None:
                event = events[0]
                if event[0] == original[0] and self.encode(event[4]) == original[1]:
                    del unclaimed[event_id]
                    stats.identical += 1
                    return
        self.compare(step, stats, replayed, events)

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
            produced = step.produced
            consumed, replayed_produced, status = replayed[2:5]
            # the same record (the commonest): compare_record's checks, the one way they can all pass
            if (status is _OK and replayed_produced == produced and consumed == step.consumed
                    and step.status in STEPPED):
                found = None
            else:
                found = compare_record(step, replayed)
            if found is not None:
                self.claim(step.produced, None)
                self.checks.append(_Check(step, stats, found))
            else:
                unclaimed = self.unclaimed
                for event_id in produced:
                    if event_id not in unclaimed:
                        break
                else:  # every logged output read (the commonest): decided now, then let go
                    found = compare_outputs(step, events, unclaimed, self.encode, step.node in self.stamped)
                    for event_id in produced:
                        del unclaimed[event_id]
                    if found is None:  # an identical step is a count: it needs no place in step order
                        stats.identical += 1
                        return
                    self.checks.append(_Check(step, stats, found))
                    self.flush()
                    return
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

    def take_logged(self, step) -> None:
        """A source's record (or a flow's the replay does not re-execute): its events as it names
        them, taken out of those read (the commonest: read already, in its instant), the others
        expected (:meth:`expect`)."""
        unclaimed = self.unclaimed
        for event_id in step.produced:
            if unclaimed.pop(event_id, None) is None:
                self.expect(step, event_id)

    def expect(self, step, event_id: tuple) -> None:
        """An event a source's record names that was not read before it: one the log holds, still
        to come (a source with latency logs its outputs later), or refused: the log lacks it (but
        where it was cut short or lost it with a process), or a record named it before."""
        if not self.in_log(event_id):
            if self.cut_short or event_id in self.lost:
                return
            raise not_its_event(self.log.path, step, event_id, NOT_IN_LOG)
        if event_id in self.expected:
            raise not_its_event(self.log.path, step, event_id, NAMED_BEFORE)
        self.waiting[event_id] = None  # (read: let go)
        self.expected[event_id] = step

    def decide(self, check: _Check) -> None:
        """A check whose logged outputs are all read (or never will be): compare them."""
        check.found = compare_outputs(check.step, check.events, check.originals, self.encode, check.stamped)
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
        """The log has ended: decide what no output came for, report, keep the trace. A source's
        event that a record named and that never came after it came before it, and an earlier
        record took it (or the same record named it twice); an event (a source's, or a re-executed
        flow's, then compared with nothing) that no record of its node named is no output of a
        step: the log is refused (but where it was cut short, or one whose record a process
        that died took with it, :meth:`_died_with_its_record`)."""
        if self.expected:
            event_id, step = next(iter(self.expected.items()))
            raise not_its_event(self.log.path, step, event_id, NAMED_BEFORE)
        if not self.cut_short:
            for event_id, (tag, _) in self.unclaimed.items():
                if not self._died_with_its_record(event_id, tag):
                    raise no_record_of(self.log.path, event_id)
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


#: StepRecord(*fields) without its Python-level __new__: one a logged step
_step_record = functools.partial(tuple.__new__, StepRecord)


def _microstep_node(step) -> tuple[int, str]:
    return (step.tag[1], step.node)


def _taken(session: InprocSession, step) -> tuple[tuple, list[tuple]]:
    """The recorded tick run again (``session.tick``): its step record and its events, taken out
    of ``session.trace`` (what a LET step that missed its deadline returned, dropped as in the run)."""
    trace = session.trace
    if step.status == _LATE and step.detail.get("on_deadline_miss") in ("drop", "error"):
        session.retract(step.node)  # the run dropped what this step returned
    tape = trace.tape
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


def _never_had(view: tuple[list, list] | None, arrival: tuple[int, int], seq: int) -> bool:
    """Whether a consumer never had an event that no record of it names late: the first of its
    ticks at or past the event's tag ran incomplete without it. Had it come afterwards, a later
    record would name it; it came after the consumer's last record, or never (a real-time run)."""
    if view is None:
        return False
    tags, seqs = view
    i = bisect.bisect_left(tags, arrival)
    return i < len(tags) and seq >= seqs[i]


def _in_gap(ranges: list[tuple[str, str, int, int]] | None, node: str, port: str, seq: int) -> bool:
    """Whether the event ``(node, port, seq)`` falls in one of a consumer port's restart gaps."""
    return ranges is not None and any(src == node and out == port and lo <= seq < hi for src, out, lo, hi in ranges)


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

