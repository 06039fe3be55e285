"""The hand-over state file: a restarting worker process → the process that takes its node over.

A flow's step raised and its node restarts (``on_error="restart"``): the old process writes its
loop's state to ``<run dir>/<node>.handover`` (node/handover.py: ``handover_state``, encoded by
the project codec, since values may be numpy arrays or registered value types), and the new one
reads it back here, exactly, as a :class:`HandoverState`: every field there, none more, each of
its type. What only the new process's loop can check (its input ports, its streams) it checks
itself (node/handover.py: ``decode_state``).

The codec decodes tuples as tuples: tags, early messages, promises and held outputs travel as
tuples, buffers and streams as lists. An error names the field by its path in quotes
(``'buffers[0][1][2][3]' must be an integer >= 0, got str '1'``).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from ....codec import unpackb
from ....errors import WireError
from ....flow.burst import travels_as_rows
from ..wire import shown
from .schema import (MAX_NAME_CHARS, Bool, Document, Int, Kind, ListOf, MapOf, Nullable, Record, Row, Text,
                     field, got)
from .to_worker import RESTART_SEQ_GAP

#: The most input events a restarting flow's old process hands over. Of a buffer it hands over
#: only what the input's policy can still select (SyncPolicy.selectable): the newest event of
#: each tag for Latest, however big the bursts that came while the flow restarted; every event
#: for a Queue, which may be millions when its flow falls behind. Writing them and reading them
#: back takes time in proportion (seconds for a million), while the new process's inbox fills
#: and the run's end waits FINISH_SLACK_S (coordinator/waiting.py): past this many, the run
#: stops saying why (node/handover.py: too_many_to_hand_over) rather than restart into a backlog
#: it would not work off in time. The reader refuses a state that holds more, and bounds by it
#: the lists that have no tighter bound (pending ticks, held outputs).
HANDOVER_EVENTS_MAX = 1 << 20


# ---------------------------------------------------------------------------------------------
# The kinds of the state's fields
# ---------------------------------------------------------------------------------------------
class Quoted(Kind):
    """A kind whose refusal names the field's path in quotes: ``where`` is a path here
    (``buffers[0][2]``), not a sentence."""

    def refuse(self, value: Any, where: str) -> WireError:
        return WireError(f"'{where}' must be {self.expects}, got {got(value)}")


class Count(Quoted, Int):
    """An integer >= ``low`` (the codec decodes none past 2**64 - 1)."""

    def __init__(self, low: int = 0):
        super().__init__(low, (1 << 64) - 1)
        self.expects = f"an integer >= {low}"


class Flag(Quoted, Bool):
    """True or false."""


class Label(Quoted, Text):
    """A node's or a port's name: text of 1 to MAX_NAME_CHARS characters (as schema.port)."""

    def __init__(self) -> None:
        super().__init__(MAX_NAME_CHARS, min_chars=1)
        self.expects = "a name"


class Tag(Quoted):
    """A tag, as the codec decodes it: a tuple ``(t_ns, microstep)`` of integers, t_ns >= ``low``
    (the last tick run before the first is at -1), microstep >= 0."""

    expects = "a tag (t_ns, microstep)"

    def __init__(self, low: int = 0):
        self.low = low

    def read(self, value: Any, where: str) -> tuple[int, int]:
        if (type(value) is not tuple or len(value) != 2 or type(value[0]) is not int or type(value[1]) is not int
                or value[0] < self.low or value[1] < 0):
            raise self.refuse(value, where)
        return value


class Value(Kind):
    """A flow's value, as the codec decoded it (it refused any type not registered with it)."""

    def read(self, value: Any, where: str) -> Any:
        return value


class Fixed(Quoted, Row):
    """A list or a tuple (``of``) of a fixed length, each item of its own kind, held as a tuple."""

    def __init__(self, of: type[list] | type[tuple], *items: Kind):
        super().__init__(*items, expects=f"a {of.__name__} of {len(items)}", of=of)


class Items(Quoted, ListOf):
    """A list of ``item`` values (at most ``max_items``), held as a tuple."""


class Seqs(Quoted, MapOf):
    """A map of output ports to seqs (each >= ``low``): ``seqs[port]`` names one."""

    def __init__(self, low: int):
        super().__init__(Label(), Count(low))
        self.expects = "a map of ports to seqs"

    def at(self, where: str, key: Any) -> str:
        return f"{where}[{key}]"


class Detail(Quoted, Document):
    """What the next step record must tell (node/notes.py), read as it came."""


LABEL, VALUE = Label(), Value()


class RunValues(Quoted):
    """A run's values: a list of them, or an array whose rows they are (as a burst of arrays
    travels: flow/burst.py's travels_as_rows, which no array of empty rows passes)."""

    expects = "a list of the run's values or an array of them"

    def read(self, value: Any, where: str) -> list | np.ndarray:
        if type(value) is np.ndarray and travels_as_rows(value):
            return value
        if type(value) is not list or not value:
            raise self.refuse(value, where)
        return value


class Entries(Items):
    """A buffer's entries (arrival tag, producer, port, seq, value), written as runs of one tag,
    producer and port with consecutive seqs: ``[tag, producer, port, first seq, values]``
    (node/handover.py). The entries must be in order (PortBuffer.insert bisects them), at most
    HANDOVER_EVENTS_MAX."""

    def __init__(self) -> None:
        super().__init__(Fixed(list, Tag(), LABEL, LABEL, Count(), RunValues()), max_items=HANDOVER_EVENTS_MAX)

    def read(self, value: Any, where: str) -> tuple:
        entries: list[tuple] = []
        for i, (tag, producer, port, seq, values) in enumerate(super().read(value, where)):
            if entries and entries[-1][:4] >= (tag, producer, port, seq):
                raise WireError(f"'{where}[{i}]' starts at {shown((tag, producer, port, seq), 80)}, not after the "
                                "run before it")
            if len(entries) + len(values) > HANDOVER_EVENTS_MAX:
                raise WireError(f"'{where}[{i}]' takes the buffer past {HANDOVER_EVENTS_MAX:,} entries "
                                "(HANDOVER_EVENTS_MAX)")
            entries += [(tag, producer, port, seq + j, v) for j, v in enumerate(values)]
        return tuple(entries)


class Buffer(Fixed):
    """An input port's buffer: ``[port, runs, visible, cursor, last_id]`` (sync.PortBuffer), its
    runs read as entries; ``visible`` and ``cursor`` index them."""

    def __init__(self) -> None:
        super().__init__(list, LABEL, Entries(), Count(), Count(), Nullable(Fixed(tuple, LABEL, LABEL, Count())))

    def read(self, value: Any, where: str) -> tuple:
        buffer = super().read(value, where)
        entries = buffer[1]
        for i, what in ((2, "visible"), (3, "cursor")):
            if buffer[i] > len(entries):
                raise WireError(f"'{where}[{i}]' ({what}) is {buffer[i]}, past the buffer's {len(entries)} entries")
        return buffer


class Buffers(Items):
    """The input buffers, one per port, which hold at most HANDOVER_EVENTS_MAX entries together."""

    def __init__(self) -> None:
        super().__init__(Buffer())

    def read(self, value: Any, where: str) -> tuple:
        buffers = super().read(value, where)
        total = sum(len(entries) for _, entries, *_ in buffers)
        if total > HANDOVER_EVENTS_MAX:
            raise WireError(f"'{where}' hold {total:,} entries, past {HANDOVER_EVENTS_MAX:,} (HANDOVER_EVENTS_MAX)")
        return buffers


#: an early data message: (tag, seq, frontier, producer, port, value); a promise: (seq, frontier)
MESSAGE = Fixed(tuple, Tag(), Count(), Tag(), LABEL, LABEL, VALUE)
PROMISE = Fixed(tuple, Count(), Tag())
#: an input stream: [producer, port, frontier, next seq expected, early messages, promises waiting];
#: an early message is at most RESTART_SEQ_GAP + EARLY_SEQS_MAX (4,096) seqs ahead of its stream
#: (node/frontiers.py), promises at most WAITING_MAX (4,096) a stream
EARLY_MAX = 2 * RESTART_SEQ_GAP
INPUT_STREAM = Fixed(list, LABEL, LABEL, Tag(), Count(), Items(MESSAGE, EARLY_MAX), Items(PROMISE))


class Held(Quoted):
    """A held LET output: ``(tag, port, value, seq)``, or a burst's ``(tag, port, values, seq,
    "burst")`` (the codec encodes values, not bursts)."""

    expects = "a held burst (tag, port, values, seq, 'burst')"
    single = Fixed(tuple, Tag(), LABEL, VALUE, Count())
    burst = Fixed(tuple, Tag(), LABEL, VALUE, Count(), VALUE)

    def read(self, value: Any, where: str) -> tuple:
        if type(value) is not tuple or len(value) != 5:
            return self.single.read(value, where)
        values, mark = value[2], value[4]
        if type(mark) is not str or mark != "burst" or type(values) is not tuple or not values:
            raise self.refuse(value, where)
        return self.burst.read(value, where)


# ---------------------------------------------------------------------------------------------
# The state
# ---------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class HandoverState(Record):
    """A restarting loop's state as its new process reads it: the map node/handover.py's
    ``handover_state`` makes, every field checked. Tags are ``(t, m)`` tuples, events and held
    outputs tuples, values what the codec decodes (registered value types only). It travels in
    a file, as the codec's bytes (:func:`decode_handover_state`), on no channel."""

    buffers: tuple = field(Buffers())  # (port, entries, visible, cursor, last_id) per input port
    # (producer, port, frontier, expect, early messages, waiting (seq, frontier)) per input stream
    streams: tuple = field(Items(INPUT_STREAM))
    pending: tuple = field(Items(Tag(), HANDOVER_EVENTS_MAX))  # trigger tags not yet run
    k: int = field(Count())
    next_rate: tuple | None = field(Nullable(Tag()))
    last_tick: tuple = field(Tag(low=-1))
    last_stamp: int = field(Count())
    seqs: dict = field(Seqs(low=0))
    sent: dict = field(Seqs(low=-1))
    held: tuple = field(Items(Held(), HANDOVER_EVENTS_MAX))  # (tag, port, value, seq), or a burst's
    pending_detail: dict = field(Detail())
    values: bool = field(Flag())

    @classmethod
    def from_fields(cls, fields: Any, where: str) -> HandoverState:
        """The state of a decoded map (exact: every field read, none missing, none more)."""
        if type(fields) is not dict:
            raise WireError(f"{where} is a map of its fields, got {got(fields)}")
        names = [name for name, _, _ in cls.schema()]
        missing = sorted(set(names).difference(fields))
        if missing:
            raise WireError(f"fields missing: {', '.join(missing)}")
        extra = [k for k in fields if k not in names]
        if extra:
            raise WireError(f"a field {where} has none of: {shown(extra[0], 40)}")
        return cls(**{name: kind.read(fields[name], name) for name, kind, _ in cls.schema()})


def decode_handover_state(data: bytes) -> HandoverState:
    """The state file's bytes as a :class:`HandoverState`; WireError naming the field otherwise."""
    try:
        given = unpackb(data)
    except Exception as e:  # msgpack's own errors on garbage, or the codec's (CodecError)
        raise WireError(f"not Retriever codec data ({type(e).__name__}: {e})"[:300]) from None
    return HandoverState.from_fields(given, "the state")
