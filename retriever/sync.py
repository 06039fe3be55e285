"""Sync policies: what a tick consumes from an edge, decided by event time (docs/semantics.md, Sync policies).

At a tick with tag ``τ`` the runtime hands each policy the edge's history ``H``: the upstream
events with tag ``≤ τ``, oldest first (fan-in merged by tag, then producer id, then seq). The
policy returns one value or ``MISSING``. Nothing about arrival order or wall time enters.

Runtime interface (used by every backend):

    select(buf, tau) -> (value, consumed_ids, dropped, commit)
    commit_to(buf, commit)        # applied only when the tick is not skipped
    selectable(buf, after) -> buf # what a tick after ``after`` can still select: a restart's hand-over,
                                  # and what fill()/bound() keep of a buffer between its consumer's ticks

``buf`` is a :class:`PortBuffer`. Splitting select from commit is what lets a skipped tick
consume nothing: ``Queue`` and ``LatestDistinct`` events stay for the next tick. A ``commit``
of ``None`` means nothing to record; committing it is a no-op.
"""

from __future__ import annotations

from bisect import bisect_left, bisect_right
from fractions import Fraction
from typing import Any

from .time import MAX_SECONDS, NS_PER_S, exact_rational, is_finite_number, rate_problem, seconds_problem, seconds_to_ns


class _Missing:
    """The absence of a value on a port at a tick."""

    _instance = None

    def __new__(cls):
        if cls._instance is None:
            cls._instance = super().__new__(cls)
        return cls._instance

    def __repr__(self) -> str:
        return "MISSING"

    def __bool__(self) -> bool:
        return False

    def __reduce__(self):
        return "MISSING"


MISSING: Any = _Missing()

# Trim consumed history in batches so per-tick cost stays O(1) amortized.
_TRIM_BATCH = 16
#: fill() bounds a buffer (bound()) once it holds twice what its last bound left, and at least
#: this many, or twice its trim batch (a real-time one: 4 entries, each may be a camera frame)
BOUND_MIN = 4
#: the greatest microstep a tag before another at microstep 0 is given (before()): past any real one
_LAST_MICROSTEP = 1 << 62


class PortBuffer:
    """The merged, tag-ordered history of one consumer input port.

    Entries are ``(arrival_tag, producer, port, seq, value)`` tuples; the first four fields are
    unique (``producer, port, seq`` is the event id), so tuple order is exactly the fan-in order
    of docs/semantics.md's worked example 8 and values are never compared. A backend may append fields of its own
    (inproc adds the event's ``(id,)`` tuple, which its compiled ticks record as consumed);
    policies read only the first five. ``visible`` counts the entries with
    ``arrival_tag ≤`` the tag of the consumer's current tick.
    """

    __slots__ = ("entries", "visible", "cursor", "last_id", "trim_batch", "policy", "bound_at")

    def __init__(self, trim_batch: int = _TRIM_BATCH, policy: "SyncPolicy | None" = None) -> None:
        self.entries: list[tuple] = []
        self.visible = 0
        self.cursor = 0  # Queue: index of the first event not yet consumed
        self.last_id: Any = None  # LatestDistinct: id of the last event consumed
        # forget consumed entries once this many piled up: batches make it cheap in virtual time;
        # a real-time backend forgets at once (each entry may hold a camera frame)
        self.trim_batch = trim_batch
        # the policy its consumer selects with (plan.bind_inputs): what bound() asks what to keep;
        # None keeps everything. bound_at: the length at which fill() bounds it next
        self.policy = policy
        self.bound_at = max(BOUND_MIN, 2 * trim_batch)

    def insert(self, entry: tuple) -> None:
        """Put ``entry`` in its place by tag. In real time one may come *late*, after a tick at
        or past its tag ran: it goes behind entries already visible, or already consumed (a
        Queue's cursor stays on the first entry not consumed: the late one, behind it by its
        tag, is never consumed by a Queue; Latest and the others see it as any other event)."""
        entries = self.entries
        if not entries or entries[-1] < entry:
            entries.append(entry)
            return
        i = bisect_right(entries, entry)
        entries.insert(i, entry)
        if i < self.visible:
            self.visible += 1
        if i < self.cursor:
            self.cursor += 1

    def advance(self, tau: tuple[int, int]) -> int:
        entries, n = self.entries, self.visible
        end = len(entries)
        while n < end and entries[n][0] <= tau:
            n += 1
        self.visible = n
        return n

    def copy(self) -> "PortBuffer":
        """A buffer holding the same entries at the same positions: a policy may select from it
        (and trim it) without consuming anything here (InprocSession.inputs_at)."""
        twin = PortBuffer(self.trim_batch, self.policy)
        twin.entries, twin.visible, twin.cursor, twin.last_id = list(self.entries), self.visible, self.cursor, self.last_id
        return twin

    def keeping(self, spans: list[tuple[int, int]]) -> "PortBuffer":
        """A buffer of only the entries in ``spans`` (``(start, stop)`` index ranges, in order and
        disjoint; empty ones allowed), at the same positions relative to ``visible`` and ``cursor``."""
        twin = PortBuffer(self.trim_batch, self.policy)
        twin.last_id = self.last_id
        for start, stop in spans:
            if start >= stop:
                continue
            twin.entries += self.entries[start:stop]
            twin.visible += max(0, min(self.visible, stop) - start)
            twin.cursor += max(0, min(self.cursor, stop) - start)
        return twin

    def trim(self, keep_from: int) -> None:
        """Forget entries before index ``keep_from``, which no future tick can select."""
        if keep_from >= self.trim_batch:
            del self.entries[:keep_from]
            self.visible -= keep_from
            cursor = self.cursor - keep_from  # (max(0, ...) without its call: a Latest input trims per tick)
            self.cursor = cursor if cursor > 0 else 0


def before(tag: tuple[int, int]) -> tuple[int, int]:
    """The tag just before ``tag``: a tick past it is at or after ``tag``."""
    t, m = tag
    return (t, m - 1) if m else (t - 1, _LAST_MICROSTEP)


def fill(buf: PortBuffer, entry: tuple, after, *args) -> None:
    """Put ``entry`` in ``buf`` (PortBuffer.insert), and once the buffer has grown to its
    ``bound_at``, forget what no tick of its consumer past ``after`` can select (:func:`bound`).
    Every backend fills its buffers so, or inlines it (inproc's generated ticks): a consumer that
    rarely ticks (a Trigger on a rare event) holds what its policy may still select, not every
    event since its last tick. ``after`` is a tag, or a function of ``args`` returning one, called
    only when a bound is due (a real-time node's looks at its schedule and frontiers)."""
    buf.insert(entry)
    if len(buf.entries) >= buf.bound_at:
        bound(buf, after(*args) if callable(after) else after)


def bound(buf: PortBuffer, after: tuple[int, int], visible: int | None = None) -> None:
    """Forget the entries of ``buf`` that no tick of its consumer with a tag past ``after`` can
    select, whatever is inserted later: what ``buf.policy.selectable`` leaves out. The first
    ``visible`` entries (``buf.visible`` by default; the live count where a generated tick keeps
    its own, inproc_ticks) stay where they are, so the consumer's count of them stays true:
    keeping more than ``selectable`` asks is safe (an entry it leaves out is hidden at every tick
    to come by entries it keeps, which stay). The list is changed in place (generated ticks hold
    it). The next bound is due at twice what stays, at least :data:`BOUND_MIN` and twice the
    trim batch (what a consumer's ticks let pile up): amortized O(1) per event."""
    entries = buf.entries
    policy = buf.policy
    if policy is not None:
        visible = buf.visible if visible is None else visible
        kept = policy.selectable(buf, after).entries
        if len(kept) < len(entries):
            start = bisect_right(kept, entries[visible - 1]) if visible else 0
            if len(entries) - visible > len(kept) - start:
                entries[visible:] = kept[start:]
    buf.bound_at = max(BOUND_MIN, 2 * buf.trim_batch, 2 * len(entries))


class SyncPolicy:
    """Base of sync policies. Subclasses are small immutable values."""

    __slots__ = ()
    #: key of this policy in the IR's ``adapter`` object
    ir_name: str = ""

    def params(self) -> dict:
        return {}

    def to_ir(self) -> dict:
        return {self.ir_name: self.params()}

    #: whether a consumer receives a list of upstream values (Window, Queue) rather than one
    delivers_list = False

    def select(self, buf: PortBuffer, tau: tuple[int, int]):
        raise NotImplementedError

    def commit_to(self, buf: PortBuffer, commit: Any) -> None:
        """Record consumption; called only for ticks that run ``step``."""

    def selectable(self, buf: PortBuffer, after: tuple[int, int]) -> PortBuffer:
        """A copy of ``buf`` holding only what a tick with a tag past ``after`` (the last tick run)
        can still select, whatever events are inserted later: a restarted consumer's new process
        takes this over (zenoh/node/handover.py), and selects from it exactly what it would have
        selected from ``buf``. This one keeps every entry; the policies that forget some say which."""
        return buf.copy()

    def __eq__(self, other: object) -> bool:
        return type(self) is type(other) and self.params() == other.params()

    def __hash__(self) -> int:
        return hash((type(self), tuple(sorted(self.params().items()))))

    def __repr__(self) -> str:
        args = ", ".join(f"{k}={v!r}" for k, v in self.params().items() if v is not None)
        return f"{type(self).__name__}({args})"


def _nonneg_seconds(owner: str, name: str, value: object, allow_none: bool = True) -> int | None:
    if value is None and allow_none:
        return None
    problem = seconds_problem(name, value)
    if problem is not None:
        raise ValueError(f"{owner}({name}={value!r}): {problem}")
    return seconds_to_ns(value)


def _positive_int(owner: str, name: str, value: object, allow_none: bool = True) -> None:
    if value is None and allow_none:
        return
    if not isinstance(value, int) or isinstance(value, bool) or value < 1:
        raise ValueError(f"{owner}({name}={value!r}): {name} must be an integer >= 1")


def _past(tag: tuple[int, int]) -> tuple:
    """A bisect key between the entries at ``tag`` and those after it (a 1-tuple sorts before
    every entry that starts with the same tag)."""
    return ((tag[0], tag[1] + 1),)


def _past_time(tag: tuple[int, int]) -> tuple:
    """A bisect key between the entries at ``tag``'s time (any microstep) and those after it."""
    return ((tag[0] + 1,),)


def _tag_runs(entries: list[tuple], start: int, past=_past):
    """``(start, stop)`` of each run of entries at one tag (``past=_past_time``: at one time), the
    first from ``start`` to its run's end. A burst is one run: its events share their tag."""
    end = len(entries)
    while start < end:
        stop = bisect_left(entries, past(entries[start][0]), start, end)
        yield start, stop
        start = stop


def _newest_of_each_tag(buf: PortBuffer, after: tuple[int, int]) -> PortBuffer:
    """What Latest and LatestDistinct can still select: the newest entry at each tag, from the
    newest at or before ``after`` on. An older one at its tag is never the newest of H again."""
    entries = buf.entries
    first = max(bisect_left(entries, _past(after)) - 1, 0)
    return buf.keeping([(stop - 1, stop) for _, stop in _tag_runs(entries, first)])


class Latest(SyncPolicy):
    """The newest event of H; MISSING if H is empty or the newest is older than ``staleness`` s."""

    __slots__ = ("staleness", "_staleness_ns")
    ir_name = "latest"

    def __init__(self, staleness: float | None = None):
        self._staleness_ns = _nonneg_seconds("Latest", "staleness", staleness)
        self.staleness = staleness

    def params(self) -> dict:
        return {"staleness": self.staleness}

    def select(self, buf, tau):
        entries, n = buf.entries, buf.visible
        end = len(entries)
        while n < end and entries[n][0] <= tau:  # PortBuffer.advance, inlined: the hottest path
            n += 1
        buf.visible = n
        if not n:
            return MISSING, None, 0, None
        entry = entries[n - 1]
        if self._staleness_ns is not None and tau[0] - entry[0][0] > self._staleness_ns:
            return MISSING, None, 0, None
        if n > buf.trim_batch:
            buf.trim(n - 1)
        return entry[4], ((entry[1], entry[2], entry[3]),), 0, None

    def selectable(self, buf, after):
        return _newest_of_each_tag(buf, after)


class LatestDistinct(SyncPolicy):
    """The newest event of H if this consumer has not consumed it on this port before, else MISSING."""

    __slots__ = ()
    ir_name = "latest_distinct"

    def select(self, buf, tau):
        n = buf.advance(tau)
        if not n:
            return MISSING, None, 0, None
        entry = buf.entries[n - 1]
        eid = (entry[1], entry[2], entry[3])
        if eid == buf.last_id:
            return MISSING, None, 0, None
        buf.trim(n - 1)
        return entry[4], (eid,), 0, eid

    def commit_to(self, buf, commit):
        if commit is not None:  # None: this tick saw MISSING here and consumed nothing
            buf.last_id = commit

    def selectable(self, buf, after):
        return _newest_of_each_tag(buf, after)


class Window(SyncPolicy):
    """The values of H within ``duration`` s of τ (inclusive), the newest ``buffer_size``, oldest first.

    Never MISSING: an empty window is an empty list.
    """

    __slots__ = ("buffer_size", "duration", "_duration_ns")
    ir_name = "window"
    delivers_list = True

    def __init__(self, buffer_size: int | None = None, duration: float | None = None):
        _positive_int("Window", "buffer_size", buffer_size)
        self._duration_ns = _nonneg_seconds("Window", "duration", duration)
        self.buffer_size = buffer_size
        self.duration = duration

    def params(self) -> dict:
        return {"buffer_size": self.buffer_size, "duration": self.duration}

    def select(self, buf, tau):
        n = buf.advance(tau)
        entries = buf.entries
        lo = 0
        if self.buffer_size is not None:
            lo = max(0, n - self.buffer_size)
        if self._duration_ns is not None:
            horizon = tau[0] - self._duration_ns
            while lo < n and entries[lo][0][0] < horizon:
                lo += 1
        window = entries[lo:n]
        if self.buffer_size is not None or self._duration_ns is not None:
            buf.trim(lo)
        return [e[4] for e in window], tuple((e[1], e[2], e[3]) for e in window), 0, None

    def selectable(self, buf, after):
        """All but what no later tick reaches: the events more than ``duration`` older than
        ``after``; with a ``buffer_size``, those that ``buffer_size`` later events are visible
        beside at every tick to come (of those at or before ``after``, all but the last
        ``buffer_size``; of a burst's, all but its last ``buffer_size``)."""
        size, entries = self.buffer_size, buf.entries
        if size is None and self._duration_ns is None:
            return buf.copy()
        lo = 0 if self._duration_ns is None else bisect_left(entries, ((after[0] - self._duration_ns,),))
        if size is None:
            return buf.keeping([(lo, len(entries))])
        seen = bisect_left(entries, _past(after))
        return buf.keeping([(max(lo, seen - size), seen),
                            *((max(start, stop - size), stop) for start, stop in _tag_runs(entries, seen))])


class Queue(SyncPolicy):
    """The events of H this consumer has not consumed yet, oldest first.

    Beyond ``maxsize`` the oldest are dropped (and count as consumed); the step record counts
    the drops. Never MISSING: nothing new is an empty list.
    """

    __slots__ = ("maxsize",)
    ir_name = "queue"
    delivers_list = True

    def __init__(self, maxsize: int | None = None):
        _positive_int("Queue", "maxsize", maxsize)
        self.maxsize = maxsize

    def params(self) -> dict:
        return {"maxsize": self.maxsize}

    def select(self, buf, tau):
        n = buf.advance(tau)
        start = buf.cursor
        dropped = 0
        if self.maxsize is not None and n - start > self.maxsize:
            dropped = n - start - self.maxsize
            start = n - self.maxsize
        batch = buf.entries[start:n]
        return [e[4] for e in batch], tuple((e[1], e[2], e[3]) for e in batch), dropped, n

    def commit_to(self, buf, commit):
        buf.cursor = commit
        buf.trim(commit)


class Exact(SyncPolicy):
    """The value whose tag time is within ``tolerance`` s of τ's time (nearest; earlier on ties), else MISSING."""

    __slots__ = ("tolerance", "_tolerance_ns")
    ir_name = "exact"

    def __init__(self, tolerance: float = 0.0):
        self._tolerance_ns = _nonneg_seconds("Exact", "tolerance", tolerance, allow_none=False)
        self.tolerance = tolerance

    def params(self) -> dict:
        return {"tolerance": self.tolerance}

    def select(self, buf, tau):
        n = buf.advance(tau)
        if not n:
            return MISSING, None, 0, None
        entries = buf.entries
        best_t = entries[n - 1][0][0]  # every event of H is at or before τ: the newest is nearest
        if tau[0] - best_t > self._tolerance_ns:
            return MISSING, None, 0, None
        i = n - 1
        while i > 0 and entries[i - 1][0][0] == best_t:  # earliest of the events at that time
            i -= 1
        entry = entries[i]
        buf.trim(i)
        return entry[4], ((entry[1], entry[2], entry[3]),), 0, None

    def selectable(self, buf, after):
        """The earliest entry at each time, from the time of the newest at or before ``after`` on:
        the newest time of H is all a tick looks at, and it takes that time's earliest entry."""
        entries = buf.entries
        seen = bisect_left(entries, _past(after))
        first = 0 if not seen else bisect_left(entries, ((entries[seen - 1][0][0],),))
        return buf.keeping([(start, start + 1) for start, _ in _tag_runs(entries, first, past=_past_time)])


class ActionChunking(SyncPolicy):
    """Sample a time-indexed action chunk at the consumer's tick (docs/semantics.md, worked example 7; docs/wiring.md).

    The upstream value is a chunk: a sequence of action rows (list, tuple or array), or an
    object/dict with ``actions`` (the rows) and optionally ``t0`` (its start: int ns, or float
    seconds). Without ``t0`` a chunk starts at its event's tag time. At τ the newest chunk that
    has started gives row ``floor((τ.t − t0) · control_hz / 1e9)``; past its ``chunk_steps``
    rows the last row is held, or MISSING with ``on_exhausted="missing"``.

    ``control_hz`` defaults to the consumer's own rate; ``chunk_steps`` to the chunk's length.
    ``horizon_ms`` (the paper's Appendix D-D spelling) bounds a chunk's validity in time as well:
    at ``τ.t − t0 ≥ horizon`` it is exhausted like a chunk past its last row.
    """

    __slots__ = ("control_hz", "chunk_steps", "on_exhausted", "horizon_ms", "_hz", "_horizon_ns")
    ir_name = "action_chunking"

    def __init__(self, control_hz: float | None = None, chunk_steps: int | None = None,
                 on_exhausted: str = "hold", horizon_ms: float | None = None):
        problem = None if control_hz is None else rate_problem("control_hz", control_hz)
        if problem is not None:
            raise ValueError(f"ActionChunking(control_hz={control_hz!r}): {problem}")
        _positive_int("ActionChunking", "chunk_steps", chunk_steps)
        if on_exhausted not in ("hold", "missing"):
            raise ValueError(
                f"ActionChunking(on_exhausted={on_exhausted!r}): expected 'hold' or 'missing'"
            )
        if horizon_ms is not None and (not is_finite_number(horizon_ms) or horizon_ms <= 0):
            raise ValueError(f"ActionChunking(horizon_ms={horizon_ms!r}): horizon_ms must be a finite number > 0")
        if horizon_ms is not None and horizon_ms > MAX_SECONDS * 1e3:
            raise ValueError(f"ActionChunking(horizon_ms={horizon_ms!r}): horizon_ms must be at most "
                             f"{MAX_SECONDS * 1e3:.4g} (about 292 years: times are int64 nanoseconds)")
        self.control_hz = control_hz
        self.chunk_steps = chunk_steps
        self.on_exhausted = on_exhausted
        self.horizon_ms = horizon_ms
        self._hz: Fraction | None = None if control_hz is None else exact_rational(control_hz)
        self._horizon_ns = None if horizon_ms is None else round(horizon_ms * 1e6)

    def params(self) -> dict:
        return {"control_hz": self.control_hz, "chunk_steps": self.chunk_steps,
                "on_exhausted": self.on_exhausted, "horizon_ms": self.horizon_ms}

    def bound_to_rate(self, hz: float | None) -> "ActionChunking":
        """This policy with ``control_hz`` filled in from the consumer's clock, if it was left out."""
        if self.control_hz is not None or hz is None:
            return self
        return ActionChunking(control_hz=hz, chunk_steps=self.chunk_steps, on_exhausted=self.on_exhausted,
                              horizon_ms=self.horizon_ms)

    def select(self, buf, tau):
        if self._hz is None:
            raise ValueError("ActionChunking has no control_hz and its consumer has no rate to take it from")
        n = buf.advance(tau)
        entries = buf.entries
        t = tau[0]
        for i in range(n - 1, -1, -1):
            entry = entries[i]
            rows, t0 = chunk_rows(entry[4], entry[0][0])
            if t0 <= t:
                break
        else:
            return MISSING, None, 0, None
        buf.trim(i)
        hz = self._hz
        length = len(rows) if self.chunk_steps is None else min(self.chunk_steps, len(rows))
        if length == 0:
            return MISSING, None, 0, None
        row = ((t - t0) * hz.numerator) // (NS_PER_S * hz.denominator)
        exhausted = row >= length
        if self._horizon_ns is not None and t - t0 >= self._horizon_ns:
            exhausted = True  # past the horizon; "hold" keeps the last row that started before it
            length = min(length, -(-(self._horizon_ns * hz.numerator) // (NS_PER_S * hz.denominator)))
        if exhausted:
            if self.on_exhausted == "missing":
                return MISSING, None, 0, None
            row = length - 1
        return rows[row], ((entry[1], entry[2], entry[3]),), 0, None

    def selectable(self, buf, after):
        """From the newest chunk at or before ``after`` that has started by ``after``'s time on:
        every tick to come sees it, past its start, so it hides every older one."""
        entries = buf.entries
        t = after[0]
        for i in range(bisect_left(entries, _past(after)) - 1, -1, -1):
            entry = entries[i]
            try:
                started = chunk_rows(entry[4], entry[0][0])[1] <= t
            except Exception:  # (a value select fails on: kept, for select to say so)
                return buf.copy()
            if started:
                return buf.keeping([(i, len(entries))])
        return buf.copy()


def chunk_rows(value: Any, tag_time: int) -> tuple[Any, int]:
    """Split an action-chunk value into (rows, start time in ns)."""
    t0 = None
    if isinstance(value, dict) and "actions" in value:
        rows, t0 = value["actions"], value.get("t0")
    elif hasattr(value, "actions"):
        rows, t0 = value.actions, getattr(value, "t0", None)
    else:
        rows = value
    if t0 is None:
        return rows, tag_time
    if isinstance(t0, float):
        return rows, seconds_to_ns(t0)
    return rows, int(t0)


POLICIES: dict[str, type[SyncPolicy]] = {
    cls.ir_name: cls for cls in (Latest, LatestDistinct, Window, Queue, Exact, ActionChunking)
}


def policy_from_ir(doc: object) -> SyncPolicy:
    """Rebuild a policy from its IR form, e.g. ``{"latest": {"staleness": 0.1}}``."""
    if not isinstance(doc, dict) or len(doc) != 1:
        raise ValueError(f"an adapter must be an object with one key, got {doc!r}")
    (name, params), = doc.items()
    cls = POLICIES.get(name)
    if cls is None:
        raise ValueError(f"unknown sync policy {name!r}; known: {', '.join(sorted(POLICIES))}")
    if not isinstance(params, dict):
        raise ValueError(f"adapter {name}: parameters must be an object, got {params!r}")
    try:
        return cls(**params)
    except TypeError as e:
        raise ValueError(f"adapter {name}: bad parameters {params!r} ({e})") from None
