"""The trace of a run: every event and every step record, comparable and digestible.

Two traces are equal when they hold the same events and step records, whatever order ticks at
one tag happened to run in: both are compared in canonical order (events by tag, node, port,
seq; steps by tag, node). ``digest()`` is a SHA-256 over that canonical form, so it is stable
across processes and machines.
"""

from __future__ import annotations

import difflib
import gc
import hashlib
import threading
from contextlib import contextmanager
from enum import StrEnum
from itertools import compress, repeat
from operator import eq, ne
from typing import Any, Callable, Iterator, NamedTuple

from .codec import packb
from .errors import ValuesNotKeptError
from .time import format_tag

_U32 = 0xFFFFFFFF  # a log record's sequence number is a uint32 (the step's index, wrapped)

EventId = tuple[str, str, int]

#: the keys of a step record's detail that Retriever's backends write (docs/log.md): a skipped tick's
#: ``missing`` ports, a step's ``exit`` and ``error`` / ``on_error``, a real-time run's ``incomplete``,
#: ``had_below``, ``late``, ``deadline_miss_ns``, ``on_deadline_miss``, ``overrun_skipped`` and
#: ``restart_skipped``, a restart's ``restarted`` and ``restart_gap``, and what the flow said
#: (``flow``, Flow.add_step_detail); besides these, only an input port of the record's node, the
#: count of events its Queue dropped at the tick (tick.select_inputs): so no input port may be
#: named as one of them (graph.py refuses it)
DETAIL_KEYS = frozenset({"missing", "exit", "error", "on_error", "incomplete", "had_below", "late", "deadline_miss_ns",
                         "on_deadline_miss", "overrun_skipped", "restart_skipped", "restarted", "restart_gap", "flow"})

#: What a run may keep in memory (``pipe.run(..., keep=...)``): ``"trace"``, every event with its
#: value and every step record (what tests and short debugging runs want); ``"records"``, every
#: event's id, tag and wall time, and every step record, but no values (they are in the log, if the
#: run wrote one; on the Zenoh runtime they then never reach the coordinator at all unless it writes
#: a log); or ``"counters"``, nothing but the counters (``pipe.stats()``, ``pipe.counts()``): each
#: record is dropped once the log has it, so a run's memory stays bounded however long it runs, and
#: after a logged run ``pipe.trace`` reads the trace back from its log. The default is
#: ``"counters"`` for a logged run on a real-time backend and ``"trace"`` otherwise.
KEEP = ("trace", "records", "counters")


_held = 0  # how many holding_full_collections() are open, in any thread
_held_lock = threading.Lock()
_thresholds = gc.get_threshold()


@contextmanager
def holding_full_collections() -> Iterator[None]:
    """Hold off the cyclic GC's *full* collections (young ones go on) while a run or a read of
    its trace makes records that live as long as the trace: each full collection would walk
    them all again, which would take a long run about half its time (benchmarks/reports/step_overhead.md).
    Nests, across threads (a run in the background, its trace read meanwhile)."""
    global _held, _thresholds
    with _held_lock:
        if not _held:
            _thresholds = gc.get_threshold()
            gc.set_threshold(_thresholds[0], _thresholds[1], 1 << 30)
        _held += 1
    try:
        yield
    finally:
        with _held_lock:
            _held -= 1
            if not _held:
                gc.set_threshold(*_thresholds)


class _NotKept:
    """The value of an event in a trace that keeps no values (``keep="records"``)."""

    __slots__ = ()

    def __repr__(self) -> str:
        return "<value not kept>"

    def __reduce__(self) -> str:
        return "NOT_KEPT"


#: stands for every value a ``keep="records"`` trace left out
NOT_KEPT = _NotKept()


class Event(NamedTuple):
    """One value on one output port. ``(node, port, seq)`` is its id, unique in a run."""

    tag: tuple[int, int]
    node: str
    port: str
    seq: int
    value: Any
    #: wall-clock (Unix ns) time the event was published; recorded in the log, not compared
    publish_ns: int = 0

    @property
    def id(self) -> EventId:
        return (self.node, self.port, self.seq)

    # wall-clock fields are measurements, not part of what a run computed
    def __eq__(self, other: object) -> bool:
        return self[:5] == other[:5] if isinstance(other, Event) else NotImplemented

    def __ne__(self, other: object) -> bool:
        return self[:5] != other[:5] if isinstance(other, Event) else NotImplemented

    def __hash__(self) -> int:
        return hash(self[:5])


class StepStatus(StrEnum):
    """What a step record's status may be (docs/log.md). A ``str``: a log and the wire carry its
    value (``"ok"``), and a status read back from either compares equal to its member."""

    #: stepped and returned
    OK = "ok"
    #: did not step: an input's policy had nothing (``detail["missing"]``); or, realtime="hard",
    #: an incomplete edge stopped the run
    SKIPPED = "skipped"
    #: in real time, stepped with an edge not complete up to the tick (``detail["incomplete"]``)
    INCOMPLETE = "incomplete"
    #: in real time, a LET step finished after tick + latency (``detail["on_deadline_miss"]``
    #: says what became of its outputs)
    LATE = "late"
    #: in real time, the step outlasted its Rate period
    OVERRUN = "overrun"
    #: step() raised
    ERROR = "error"


#: every status, in the order docs/log.md lists them
STEP_STATUSES = tuple(StepStatus)
#: statuses of a step that returned
STEPPED = frozenset({StepStatus.OK, StepStatus.INCOMPLETE, StepStatus.LATE, StepStatus.OVERRUN})
#: statuses that say when a step ran, not what it did: they compare as ``ok``
TIMING_STATUSES = frozenset({StepStatus.LATE, StepStatus.OVERRUN})

#: step-record detail keys that say *when* things happened in a real-time run, not *what*: a LET
#: output released late, events that arrived after their tick, ticks skipped after an overrun.
#: They are logged but, like the wall-clock fields, never compared.
TIMING_DETAIL = frozenset({"deadline_miss_ns", "on_deadline_miss", "late", "overrun_skipped"})


def semantic_status(status: str) -> str:
    """``status`` (a :class:`StepStatus`, or its value as a log reads it back) as traces compare
    it: timing statuses read ``ok``."""
    return StepStatus.OK if status in TIMING_STATUSES else status


def semantic_detail(detail: dict | None) -> dict | None:
    """``detail`` without its timing keys (None when nothing else is left)."""
    if not detail or TIMING_DETAIL.isdisjoint(detail):
        return detail
    rest = {k: v for k, v in detail.items() if k not in TIMING_DETAIL}
    return rest or None


class StepRecord(NamedTuple):
    """What one tick of one node did.

    ``consumed`` maps each input port to the ids of the events its policy selected (ports that
    got MISSING or a default are absent); ``produced`` lists the ids of the events emitted;
    ``status`` is a :class:`StepStatus` (its value, read back from a log); ``detail`` holds the missing ports, Queue
    drop counts or the error text, when there are any. ``wall_start_ns`` (Unix ns) and
    ``wall_ns`` say when ``step()`` ran and for how long; they are logged but never compared,
    and neither are the timing keys of ``detail`` (:data:`TIMING_DETAIL`).
    """

    node: str
    tag: tuple[int, int]
    consumed: dict[str, tuple[EventId, ...]]
    produced: tuple[EventId, ...]
    status: str
    detail: dict | None = None
    wall_start_ns: int = 0
    wall_ns: int = 0

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, StepRecord):
            return NotImplemented
        return (self[:4] == other[:4] and semantic_status(self.status) == semantic_status(other.status)
                and semantic_detail(self.detail) == semantic_detail(other.detail))

    def __ne__(self, other: object) -> bool:
        equal = self.__eq__(other)
        return equal if equal is NotImplemented else not equal

    def __hash__(self) -> int:
        return hash((self.node, self.tag, semantic_status(self.status)))

    def __str__(self) -> str:
        extra = f" {self.detail}" if self.detail else ""
        return f"{self.node} @ {format_tag(self.tag)}: {self.status}{extra}"


def event_bytes(e: Event) -> bytes:
    """What traces compare of an event: its tag, node, port, seq and value, packed."""
    return packb(("event", e.tag, e.node, e.port, e.seq, e.value))


def step_bytes(s: StepRecord) -> bytes:
    """What traces compare of a step record: no wall-clock fields, no timing status or detail."""
    consumed = sorted(s.consumed.items())
    # str(): the codec packs exact strs only, and a status is a StepStatus or its value
    return packb(("step", s.node, s.tag, consumed, s.produced, str(semantic_status(s.status)),
                  semantic_detail(s.detail)))


#: how :meth:`Trace.first_difference` names the two traces (the one it is called on, the other)
TRACES = ("the first trace", "the second")


def event_difference(i: int, a: Event | None, b: Event | None, names: tuple[str, str] = TRACES) -> str:
    """What :meth:`Trace.first_difference` says of the first events of two traces, in their
    canonical order, that are not the same: ``a`` and ``b``, each the ``i``-th of its trace (None:
    that trace has no more). The same event (node, port, seq) in both: the two, as they are. Else
    the lesser (by tag, node, port, seq; or the one left) is an event the other trace has not
    (``names[0]`` has ``a``, ``names[1]`` has ``b``): every event of the other up to ``i`` is the
    same as this one's, and its ``i``-th comes after it, or it has none."""
    if a is not None and b is not None and a[1:4] == b[1:4]:
        return f"record {i}: {a!r} != {b!r}"
    if b is None or a is not None and _event_key(a) < _event_key(b):
        one, has, lacks = a, names[0], names[1]
    else:
        one, has, lacks = b, names[1], names[0]
    assert one is not None
    return (f"record {i}: event {one.node}.{one.port} #{one.seq} at {format_tag(one.tag)} is in {has}, "
            f"not in {lacks}: {one!r}")


def _event_key(ev: Event):
    return (ev.tag, ev.node, ev.port, ev.seq)


def _step_key(rec: StepRecord):
    return (rec.tag, rec.node)


class Trace:
    """Events and step records of a run, in the order the backend recorded them.

    ``raw_events`` and ``raw_steps`` hold plain tuples of every field (named tuples cost several
    times more to build, and most runs never look at most records); ``events`` and ``steps``
    present them as :class:`Event` and :class:`StepRecord`, converted on first access.

    A backend appends records to ``raw_events`` and ``raw_steps``, or, in recording order, to the
    ``tape``, which is expanded into them the first time either is read. The in-process backend
    does, because a record in the tape costs a fraction of its tuples
    (benchmarks/reports/step_overhead.md). An item of the tape is a plain record, an event (6 fields) or a step
    record (8 fields), or the function that heads a compact record and expands it:
    ``tape[i](tape, i, add_event, add_step)`` appends the records that the compact one at ``i``
    stands for, and returns the index of the item after it.
    """

    def __init__(self, events: list | None = None, steps: list | None = None, *, keep: str = "trace"):
        # full-length tuples, so the lazy conversion below can use the fast ``_make``
        self._raw_events: list[tuple] = [tuple(Event(*e)) for e in events or ()]
        self._raw_steps: list[tuple] = [tuple(StepRecord(*s)) for s in steps or ()]
        self.tape: list = []
        self._expanding = threading.Lock()  # a background run appends while another thread reads
        self._expander: int | None = None  # the thread expanding the tape, while it does
        self._events: list[Event] = []
        self._steps: list[StepRecord] = []
        #: what the run keeps (KEEP); whether events hold their values (``keep="trace"``), or
        #: :data:`NOT_KEPT` in their place
        self.keep = keep
        self.values_kept = keep == "trace"
        self._forgotten = 0  # raw_events before this index hold NOT_KEPT (keep="records")
        #: the run's nodes and each one's output ports (None: any name may be one), when a backend
        #: says: latest() and values_of() then refuse a name that is none of them rather than
        #: return nothing, as for no event yet
        self.ports: dict[str, frozenset[str] | None] | None = None
        self._newest: dict[tuple[str, str], tuple] = {}  # latest(): each port's newest raw event ...
        self._newest_upto = 0  # ... among raw_events before this index
        self.log_path = None  # where the values are, when the run wrote a log (set by the pipeline)
        # the log's step and event records made as the tape is expanded (log_records), and the
        # index in the log of the first of each; what an expander makes them with (_log_with)
        self._step_log: list | None = None
        self._step_log_base = 0
        self._event_log: list = []
        self._event_log_base = 0
        self._log_with: tuple | None = None

    @property
    def raw_events(self) -> list[tuple]:
        """Every event as a plain ``(tag, node, port, seq, value, publish_ns)``, in recording order."""
        self.expand()
        return self._raw_events

    @property
    def raw_steps(self) -> list[tuple]:
        """Every step record as a plain tuple of the :class:`StepRecord` fields, in recording order."""
        self.expand()
        return self._raw_steps

    def expand(self, then: Callable[[], None] | None = None, wait: bool = True) -> None:
        """Move the tape's records to ``raw_events`` and ``raw_steps``. The tape only grows while
        this runs (a backend appends each record at once), so what it held at the start goes.
        ``then``: called after, under the same lock (what the tape's expanders counted, read).
        Nothing if this thread is expanding it already (a signal handler that came meanwhile),
        or, without ``wait``, if any thread is (counts read where a wait could hang: a signal
        handler in the middle of taking the lock)."""
        if not self.tape and then is None or self._expander == threading.get_ident():
            return
        if not self._expanding.acquire(blocking=wait):
            return
        try:
            self._expander = threading.get_ident()
            if wait:
                with holding_full_collections():
                    self._expand(then)
            else:
                self._expand(then)
        finally:
            self._expander = None
            self._expanding.release()

    def _expand(self, then: Callable[[], None] | None) -> None:
        tape = self.tape
        add_event, add_step = self._raw_events.append, self._raw_steps.append
        i, end = 0, len(tape)
        if end and all(map(isinstance, tape, repeat(tuple, end))):
            self._expand_plain(tape, end)
            i = end
        elif self._step_log is not None:
            self._expand_logged(tape, end, add_event, add_step)
            i = end
        while i < end:
            item = tape[i]
            if type(item) is tuple:
                (add_event if len(item) == 6 else add_step)(item)
                i += 1
            else:
                i = item(tape, i, add_event, add_step)
        del tape[:end]
        if then is not None:
            then()

    def _expand_plain(self, tape: list, end: int) -> None:
        """_expand of the first ``end`` items of a tape that holds plain records only (every tick
        generic: no compact record), split into events and step records by their length with no
        Python loop (benchmarks/reports/logging_overhead.md); the log's records of them are all
        the writer's. (Each iterator stops after ``end`` items: another thread may append meanwhile.)"""
        events, steps = self._raw_events, self._raw_steps
        n_events, n_steps = len(events), len(steps)
        events.extend(compress(tape, map(eq, repeat(6, end), map(len, tape))))
        steps.extend(compress(tape, map(ne, repeat(6, end), map(len, tape))))
        if self._step_log is not None:
            self._event_log.extend(repeat(None, len(events) - n_events))
            self._step_log.extend(repeat(None, len(steps) - n_steps))

    def _expand_logged(self, tape: list, end: int, add_event: Callable, add_step: Callable) -> None:
        """_expand, with each step record's and each event's log record made by its expander, or
        None for the log writer to make (a plain record's, an expander's of another shape)."""
        log = self._step_log
        assert log is not None and self._log_with is not None
        with_log, add_record, add_event_record = self._log_with, log.append, self._event_log.append
        n, i = self._step_log_base + len(log), 0
        while i < end:
            item = tape[i]
            if type(item) is tuple:
                if len(item) == 6:
                    add_event(item)
                    add_event_record(None)
                else:
                    add_step(item)
                    add_record(None)
                    n += 1
                i += 1
            else:  # an expander adds one step record, and its events
                i = item(tape, i, add_event, add_step, with_log, n & _U32)
                n += 1

    def log_records(self, head: Callable[..., bytes], step_head: Callable[[int], bytes],
                    event_heads: Callable[[str, str], tuple[bytes, ...] | None],
                    record_pack: Callable[[str], Callable[..., bytes]]) -> None:
        """From now on, as the tape is expanded, have each step record's Message record, and each
        event's, made by its expander where it can (a compiled tick's: a step record's msgpack data
        in one ``struct.pack``, a float or int event's in another), for the log writer to take
        (:meth:`take_log`). A record is ``head(fixed, sequence, log_time, publish_time) + data``,
        ``fixed`` the record's first bytes (opcode, length, channel): ``step_head(len(data))`` for
        a step record, whose sequence is its index among the trace's step records (those
        :meth:`discard` dropped counted in); ``event_heads(node, port)[len(data)]`` for an event
        (None: the writer makes those of that port); or the whole record in one call,
        ``record_pack(data_format)(fixed, sequence, log_time, publish_time, *data)``, of data
        whose bytes have no byte order. Records expanded before this call have none."""
        with self._held():
            self._step_log, self._event_log = [], []
            self._step_log_base, self._event_log_base = len(self._raw_steps), len(self._raw_events)
            self._log_with = (self._step_log.append, self._event_log.append, head, step_head, event_heads, record_pack)

    def take_log(self, released_events: int, released_steps: int) -> tuple[list, int, int, list, int, int]:
        """Expand the tape; hand over the log's records made since the last call: ``(step records,
        index of the first, step records in the trace, event records, index of the first, events
        in the trace)``. A record is bytes, or None where the expander left it to the writer. The
        indexes count from :meth:`log_records`, ``released_*`` the records dropped from the
        trace since (discard)."""
        out: list = []

        def swap() -> None:
            if self._step_log is not None:
                out[:] = [self._step_log, self._step_log_base, len(self._raw_steps),
                          self._event_log, self._event_log_base, len(self._raw_events)]
                self._step_log, self._event_log = [], []
                self._step_log_base = released_steps + len(self._raw_steps)
                self._event_log_base = released_events + len(self._raw_events)
                with_log = self._log_with
                assert with_log is not None
                self._log_with = (self._step_log.append, self._event_log.append, *with_log[2:])

        self.expand(then=swap)
        if not out:  # not logging, or this thread is expanding already (a signal handler's write)
            return [], -1, len(self._raw_steps), [], -1, len(self._raw_events)
        return tuple(out)  # type: ignore[return-value]

    def stop_log(self) -> None:
        """The log is done: expanding makes no more of its records."""
        with self._held():
            self._step_log = self._log_with = None
            self._event_log = []

    @contextmanager
    def _held(self) -> Iterator[None]:
        """The expanding lock, unless this thread holds it already (a signal handler's, that came
        while it expanded the tape)."""
        if self._expander == threading.get_ident():
            yield
            return
        with self._expanding:
            yield

    def forget_values(self, upto: int | None = None) -> None:
        """Put :data:`NOT_KEPT` in place of the values of the events recorded before ``upto``
        (all, by default); a trace that keeps values keeps them."""
        if self.values_kept:
            return
        raw, done = self.raw_events, self._events
        upto = len(raw) if upto is None else min(upto, len(raw))
        for i in range(self._forgotten, upto):
            tag, node, port, seq, value, wall = raw[i]
            if value is not NOT_KEPT:
                raw[i] = (tag, node, port, seq, NOT_KEPT, wall)
                if i < len(done):
                    done[i] = Event._make(raw[i])
        self._forgotten = max(self._forgotten, upto)

    def discard(self, events: int, steps: int) -> None:
        """Drop the first ``events`` events and ``steps`` step records (``keep="counters"``: the
        log has them, or nothing is to keep them)."""
        del self.raw_events[:events], self.raw_steps[:steps]
        self._newest.clear()
        self._newest_upto = 0
        self._events.clear()
        self._steps.clear()

    def _need_records(self, what: str) -> None:
        if self.keep == "counters":
            where = ("it was logged: read_log('run.mcap').trace() reads it back" if self.log_path is None
                     else f"read_log('{self.log_path}').trace() reads it back")
            raise ValuesNotKeptError(
                f"{what} needs the run's records, and this run kept only counters (keep='counters')\n"
                f"    hint: pipe.stats() and pipe.counts() hold the counters; if {where}; or run with "
                "keep='records' or keep='trace' to keep the records in memory")

    def _need_values(self, what: str) -> None:
        self._need_records(what)
        if not self.values_kept:
            where = (f"read_log('{self.log_path}').trace()" if self.log_path is not None
                     else "run it again with log='run.mcap' and read_log('run.mcap').trace()")
            raise ValuesNotKeptError(
                f"{what} needs the events' values, and this run kept none (keep='records')\n"
                f"    hint: {where} holds them; or run with keep='trace' (the default) to keep them in memory")

    @property
    def events(self) -> list[Event]:
        """Every event, as :class:`Event`, in recording order."""
        self._need_records("trace.events")
        done, raw = self._events, self.raw_events
        if len(done) < len(raw):
            done.extend(map(Event._make, raw[len(done):]))
        return done

    @property
    def steps(self) -> list[StepRecord]:
        """Every step record, as :class:`StepRecord`, in recording order."""
        self._need_records("trace.steps")
        done, raw = self._steps, self.raw_steps
        if len(done) < len(raw):
            done.extend(map(StepRecord._make, raw[len(done):]))
        return done

    # -- queries ---------------------------------------------------------------------------
    def events_of(self, node: str, port: str | None = None) -> list[Event]:
        """Events of one node (one port, if given), in tag order."""
        found = [e for e in self.events if e.node == node and (port is None or e.port == port)]
        return sorted(found, key=_event_key)

    def latest(self, node: str, port: str) -> Event | None:
        """The newest event on ``node.port`` (greatest tag), or None if it had none: cheap enough
        to call after every ``pipe.step(dt)``, since each call reads only the events recorded
        since the last one."""
        self._need_values("trace.latest()")
        raw, newest = self.raw_events, self._newest
        for i in range(self._newest_upto, len(raw)):
            event = raw[i]
            key = (event[1], event[2])
            held = newest.get(key)
            if held is None or (event[0], event[3]) > (held[0], held[3]):
                newest[key] = event
        self._newest_upto = len(raw)
        found = newest.get((node, port))
        if found is None:
            self._check_port("trace.latest()", node, port)
            return None
        return Event._make(found)

    def _check_port(self, what: str, node: str, port: str) -> None:
        """Refuse a ``node.port`` that is no output of the run (a typo reads as 'no event yet')."""
        if self.ports is None:
            return
        if node not in self.ports:
            nodes = sorted(self.ports)
            close = difflib.get_close_matches(node, nodes, n=1)
            raise ValueError(f"{what}: the run has no node '{node}' (nodes: {', '.join(nodes)})"
                             + (f"\n    hint: did you mean '{close[0]}'?" if close else ""))
        if self.ports[node] is None or port in self.ports[node]:
            return
        own = sorted(self.ports[node])
        close = difflib.get_close_matches(port, own, n=1)
        raise ValueError(f"{what}: '{node}' has no output port '{port}' (outputs: {', '.join(own) or 'none'})"
                         + (f"\n    hint: did you mean '{close[0]}'?" if close else ""))

    def values_of(self, node: str, port: str) -> list[Any]:
        self._need_values("trace.values_of()")
        values = [e.value for e in self.events_of(node, port)]
        if not values:
            self._check_port("trace.values_of()", node, port)
        return values

    def steps_of(self, node: str) -> list[StepRecord]:
        """Step records of one node, in tick order."""
        return sorted((s for s in self.steps if s.node == node), key=_step_key)

    def canonical(self) -> tuple[list[Event], list[StepRecord]]:
        return sorted(self.events, key=_event_key), sorted(self.steps, key=_step_key)

    # -- comparison ------------------------------------------------------------------------
    def _encoded(self, canonical: tuple[list[Event], list[StepRecord]] | None = None) -> Iterator[bytes]:
        events, steps = canonical or self.canonical()
        for e in events:
            yield event_bytes(e)
        for s in steps:
            yield step_bytes(s)

    def digest(self) -> str:
        """Hex SHA-256 of the canonical trace: equal traces, equal digests, on any machine."""
        self._need_values("trace.digest()")
        h = hashlib.sha256()
        for chunk in self._encoded():
            h.update(len(chunk).to_bytes(8, "little"))
            h.update(chunk)
        return h.hexdigest()

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, Trace):
            return NotImplemented
        self._need_values("comparing traces")
        other._need_values("comparing traces")
        if len(self.raw_events) != len(other.raw_events) or len(self.raw_steps) != len(other.raw_steps):
            return False
        return all(a == b for a, b in zip(self._encoded(), other._encoded()))

    __hash__ = None  # type: ignore[assignment]

    def first_difference(self, other: "Trace", names: tuple[str, str] = TRACES) -> str | None:
        """Describe the first canonical record where two traces differ, or None if equal: the
        events (sorted by tag, node, port, seq), then the step records (by tag, node), ``record
        i`` counted over both. Where one trace has an event the other has not, it names that
        event, and which trace has it (``names``: this trace's, the other's; :func:`event_difference`)."""
        self._need_values("trace.first_difference()")
        other._need_values("trace.first_difference()")
        (events_a, steps_a), (events_b, steps_b) = self.canonical(), other.canonical()
        for i, (a, b) in enumerate(zip(events_a, events_b)):
            if event_bytes(a) != event_bytes(b):
                return event_difference(i, a, b, names)
        n = min(len(events_a), len(events_b))
        if len(events_a) != len(events_b):  # one has events left: the first of them is the other's to lack
            return event_difference(n, events_a[n] if n < len(events_a) else None,
                                    events_b[n] if n < len(events_b) else None, names)
        for j, (a, b) in enumerate(zip(steps_a, steps_b)):
            if step_bytes(a) != step_bytes(b):
                return f"record {n + j}: {a!r} != {b!r}"
        if len(steps_a) != len(steps_b):
            return f"lengths differ: {n + len(steps_a)} records vs {n + len(steps_b)}"
        return None

    def __len__(self) -> int:
        self._need_records("len(trace)")
        return len(self.raw_events)

    def __repr__(self) -> str:
        if self.keep == "counters":
            return "<Trace: counters only (keep='counters')>"
        values = "" if self.values_kept else ", values not kept"
        return f"<Trace {len(self.raw_events)} events, {len(self.raw_steps)} steps{values}>"
