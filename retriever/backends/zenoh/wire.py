"""The Zenoh runtime's key space and message envelopes (docs/deploy.md).

Key space, under ``retriever/<namespace>/``::

    data/<node>/<port>     events          [envelope, buffer, ...]   (bins; see below)
    progress/<node>        frontiers       [2, [ft, fm], producer, {port: last seq sent}]
                                           (also a queryable: ask for it)
    status/report/<node>   for the run's   [2, node, [step record, ...], [[wall_ns, data message], ...]]
                           coordinator     (a big message on the coordinator's host: a file name)
    status/node/<node>     worker state    [2, node, state, info]
    ctl/run                control         [2, op, args]

The reports, statuses and control are the records of protocol/ (its table has every message of
the key space, and their exact decoders); this module keeps the events and progress of the data
plane.

A data message is a msgpack array of bins. The first is the *envelope*, the msgpack array
``[2, [t, m], seq, [ft, fm], producer, port, value]``: format version ``2``, the event's tag
(``t`` in integer ns since the run's start ``T0``, microstep ``m``), its seq (per node and port,
from 0), the producer's *frontier* after it (every later event of this producer has a tag ``≥``
it, so a consumer's edge is complete up to any tag ``<`` it: the watermark of docs/realtime.md), the
producer node and port (as in the key), and the value in Retriever's codec (tuples, big ints,
dataclasses and numpy scalars as msgpack extension types 2–5, see ``codec.py``). Numpy arrays
travel *out of band*: in the value an array is extension type 6, ``[dtype descr, shape, i]``, and
its raw bytes (C order) are the bin after the envelope numbered ``i`` (from 0). The sender copies
an array once, into the message, and the receiver's arrays are read-only views of the message.
A step's ``Burst`` on a port is one message of several events, the envelope
``[2, [t, m], seq, [ft, fm], producer, port, values, count]``: ``count`` events at the tag, seqs
``seq`` to ``seq + count - 1``, the frontier holding after the last. ``values`` is a list of
``count`` values, or one array of ``count`` rows (each row an event's array: a burst of arrays of
one dtype and shape), or nil (values left out: the coordinator records that they were sent).
A plain Zenoh subscriber on ``retriever/<ns>/data/**`` can decode it with any msgpack library.

Zenoh keeps messages in order per key, not across keys, so a progress message says which events
it comes after: its frontier holds for a consumer of ``port`` once that consumer has received
every seq of ``port`` up to the one named (seqs are dense, so gaps show what is in flight).

Workers do not make the coordinator subscribe to their data: they report the data messages they
published, with their step records, in batches (``status/report``), off the path of the events.
Each status and report is put with the MAC of its worker process's own key as Zenoh attachment
(origin.py): the coordinator takes none that no process of the node signed. The other way, the
coordinator seals its control (``ctl/run`` and its answers) for each process it started
(protocol/seal.py): a worker takes none that does not open with its own key.

Anything on the key space that does not decode exactly so raises :class:`WireError`, which the
runtime counts, logs and drops: a foreign or garbage message never reaches a flow. Values never
decode only into classes the receiving process registered as value types (``@io``): nothing
in a message is ever imported or called.
"""

from __future__ import annotations

import mmap
import re
import reprlib
import struct
from typing import Any, NamedTuple

import msgpack
import numpy as np
import zenoh

from ...codec import OutOfBandEncoder, unpackb_out_of_band
from ...errors import CodecError, WireError
from ...flow.burst import MAX_BURST, Burst, travels_as_rows

_SHORT = reprlib.Repr()  # (Python 3.11's takes no settings as arguments)
_SHORT.maxlevel, _SHORT.maxlist, _SHORT.maxdict = 2, 4, 4
_SHORT.maxstring = _SHORT.maxother = _SHORT.maxlong = 40


def shown(value: Any, limit: int = 60) -> str:
    """``value`` (decoded from the network) as an error message shows it: at most ``limit``
    characters, and bounded work whatever it holds (a repr of a list nested a thousand deep
    raised RecursionError; of a big one, built it all before cutting it)."""
    return _SHORT.repr(value)[:limit]

#: every message of a run is needed: block rather than drop when a link is congested (a dropped
#: event would leave a gap in its stream's seqs that no frontier can cross)
RELIABLE = zenoh.CongestionControl.BLOCK

WIRE_VERSION = 2
SEQ_LIMIT = 1 << 63  # seqs are below it
ROOT = "retriever"
_CHUNK = re.compile(r"[A-Za-z0-9_][A-Za-z0-9_.\-]*")
_BIN32 = struct.Struct(">BI")
_U32 = struct.Struct(">I")
_BIN_SIZE = {0xC4: struct.Struct(">B"), 0xC5: struct.Struct(">H"), 0xC6: struct.Struct(">I")}

Tag = tuple[int, int]


def check_chunk(kind: str, name: str) -> str:
    """A namespace, node or port must be one plain key-expression chunk."""
    if not isinstance(name, str) or not _CHUNK.fullmatch(name):
        raise ValueError(f"{kind} {name!r} cannot be a Zenoh key chunk: use letters, digits, '_', '-' and '.'"
                         " (no '/', '*', '$', '?', '#', and not empty)")
    return name


class KeySpace:
    """Key expressions of one namespace."""

    #: the names under ``ctl/`` that a run's coordinator answers on (:meth:`run_control`,
    #: :meth:`start`): no worker daemon's ``ctl/<name>`` may be one of them
    COORDINATOR_CONTROL = ("run", "start")

    def __init__(self, namespace: str):
        self.namespace = check_chunk("namespace", namespace)
        self.prefix = f"{ROOT}/{namespace}"

    def everything(self) -> str:
        """Every key of this namespace (a router's access rules grant it to the run's users)."""
        return f"{self.prefix}/**"

    def data(self, node: str, port: str) -> str:
        return f"{self.prefix}/data/{node}/{port}"

    def all_data(self) -> str:
        return f"{self.prefix}/data/**"

    def progress(self, node: str) -> str:
        return f"{self.prefix}/progress/{node}"

    def warm(self, node: str) -> str:
        """Where a node puts empty messages to warm its send path before a tick it foresees;
        its consumers that may step on their receiving thread subscribe, and rehearse there
        (node/timing.py). Their content is never read."""
        return f"{self.prefix}/warm/{node}"

    def status(self, *parts: str) -> str:
        return "/".join((self.prefix, "status", *parts))

    def report(self, node: str) -> str:
        return f"{self.prefix}/status/report/{node}"

    def node_status(self, node: str) -> str:
        return f"{self.prefix}/status/node/{node}"

    def finished(self) -> str:
        """The coordinator's queryable: which nodes are done."""
        return f"{self.prefix}/status/finished"

    def run_control(self) -> str:
        return self.ctl("run")

    def start(self) -> str:
        """The coordinator's queryable: the run's ``start`` (T0 and the end), once there is one."""
        return self.ctl("start")

    def workers(self, name: str = "*") -> str:
        return f"{self.prefix}/workers/{name}"

    def ctl(self, name: str) -> str:
        return f"{self.prefix}/ctl/{name}"

    @staticmethod
    def every_control() -> str:
        """The control (``ctl/**``) of every namespace: what a watcher is never sent (access.py)."""
        return f"{ROOT}/*/ctl/**"

    def worker_events(self, name: str) -> str:
        """Where the worker daemon ``name`` tells what became of its processes (remote.py)."""
        return f"{self.prefix}/workers/{name}/events"

    def deployment(self) -> str:
        """The running deployment's coordinator: its liveliness token and its queryable (status, stop)."""
        return f"{self.prefix}/deployment"


class DataMessage(NamedTuple):
    tag: Tag
    seq: int
    frontier: Tag
    producer: str
    port: str
    value: Any


_new_tuple = tuple.__new__


class WireEncoder:
    """Encodes this process's messages (one per thread: it reuses packers)."""

    def __init__(self) -> None:
        self._values = OutOfBandEncoder()
        self._pack = msgpack.Packer(use_bin_type=True).pack

    def data(self, tag: Tag, seq: int, frontier: Tag, producer: str, port: str, value: Any) -> bytes:
        return b"".join(self.data_parts(tag, seq, frontier, producer, port, value))  # the one copy of each array

    def data_parts(self, tag: Tag, seq: int, frontier: Tag, producer: str, port: str, value: Any) -> list:
        """The pieces of :meth:`data`'s message, uncopied: its arrays' memory is among them. A
        :class:`Burst` ``value`` makes one message of its events (seqs from ``seq``)."""
        head = self._pack([WIRE_VERSION, tag, seq, frontier, producer, port])
        if type(value) is Burst:  # [..., values, count]: 8 elements
            values = value.stacked()
            if values is None:
                values = list(value.values) if value.values[0] is not None else None  # None: a blank burst
            body, buffers = self._values.pack(values)
            body, fields = body + self._pack(len(value.values)), b"\x98"
        else:
            body, buffers = self._values.pack(value)
            fields = b"\x97"
        count = 1 + len(buffers)
        # the envelope's array header says 7 (8) elements; the head packed 6: patch the count
        header = _FIXARRAY_HEADERS[count] if count < 16 else _array_header(count)
        parts = [header, _BIN32.pack(0xC6, len(head) + len(body)), fields, memoryview(head)[1:], body]
        for buf in buffers:
            parts.append(_BIN32.pack(0xC6, buf.nbytes))
            parts.append(buf)
        return parts

    def progress(self, frontier: Tag, producer: str, sent: dict[str, int]) -> bytes:
        return self._pack([WIRE_VERSION, frontier, producer, sent])


#: msgpack's fixarray headers, by count: a message's, without a call (most carry under 15 arrays)
_FIXARRAY_HEADERS = tuple(bytes((0x90 + count,)) for count in range(16))


def _array_header(count: int) -> bytes:
    if count < 16:
        return bytes((0x90 + count,))
    return b"\xdc" + count.to_bytes(2, "big") if count < 0x10000 else b"\xdd" + count.to_bytes(4, "big")


def _tag(what: str, raw: Any) -> Tag:
    if (type(raw) is not list or len(raw) != 2 or type(raw[0]) is not int or type(raw[1]) is not int
            or raw[0] < 0 or raw[1] < 0):
        raise WireError(f"{what} must be [t_ns, microstep] of two integers >= 0, got {shown(raw, 80)}")
    return (raw[0], raw[1])


def _fields(data: bytes, count: int, kind: str) -> list:
    if not isinstance(data, (bytes, bytearray, memoryview)):
        raise WireError(f"a {kind} message must be bytes, got {type(data).__name__}")
    try:
        fields = msgpack.unpackb(data, raw=False, strict_map_key=False)
    except Exception as e:  # msgpack's own errors on garbage: ExtraData, ValueError, ...
        raise WireError(f"a {kind} message is not valid msgpack ({type(e).__name__})") from None
    if type(fields) is not list:
        raise WireError(f"a {kind} message must be a msgpack array")
    if len(fields) != count:
        raise WireError(f"a {kind} message must be an array of {count}, got {len(fields)} elements")
    if fields[0] != WIRE_VERSION:
        raise WireError(f"a {kind} message of wire format {shown(fields[0], 20)}; this process speaks {WIRE_VERSION}")
    return fields


def _bins(data: bytes) -> list[memoryview]:
    """The bins of a msgpack array of bins, as views of ``data`` (no copy)."""
    try:
        first = data[0]
        if first == 0x92 and data[1] == 0xC6:  # (an envelope and one array, as sent: most messages)
            end = 6 + _U32.unpack_from(data, 2)[0]
            start = end + 5
            if data[end] == 0xC6 and start + _U32.unpack_from(data, end + 1)[0] == len(data):
                view = memoryview(data)
                return [view[6:end], view[start:]]
        if 0x90 <= first <= 0x9F:
            count, pos = first - 0x90, 1
        elif first == 0xDC:
            count, pos = int.from_bytes(data[1:3], "big"), 3
        elif first == 0xDD:
            count, pos = int.from_bytes(data[1:5], "big"), 5
        else:
            raise WireError("a data message must be a msgpack array of bins")
        view, bins = memoryview(data), []
        for _ in range(count):
            size_format = _BIN_SIZE.get(data[pos])
            if size_format is None:
                raise WireError("a data message must be a msgpack array of bins")
            start = pos + 1 + size_format.size
            end = start + size_format.unpack_from(data, pos + 1)[0]
            if end > len(data):
                raise WireError("a data message is truncated")
            bins.append(view[start:end])
            pos = end
    except (IndexError, struct.error):
        raise WireError("a data message is truncated") from None
    if pos != len(data):
        raise WireError("a data message has trailing bytes")
    if not bins:
        raise WireError("a data message must hold an envelope")
    return bins


def decode_events(data: bytes, expected: tuple[str, str] | None = None, blank_ok: bool = False) -> list[DataMessage]:
    """Decode and validate a data message; ``expected`` is the ``(node, port)`` of its key.
    Returns its events: one, or a burst's, in seq order (every one but the last with its own
    tag as frontier, the last with the message's). Its arrays are read-only views of ``data``.
    ``blank_ok``: a burst may come without its values (in a report: the coordinator keeps none)."""
    if not isinstance(data, (bytes, bytearray, mmap.mmap, memoryview)):  # a view: of a dora input's buffer
        raise WireError(f"a data message must be bytes, got {type(data).__name__}")
    envelope, *buffers = _bins(data)
    try:
        fields = unpackb_out_of_band(envelope, buffers)
    except CodecError as e:
        raise WireError(f"the value of a data message cannot be decoded: {e}") from None
    except Exception as e:  # msgpack's own errors on garbage: ExtraData, ValueError, ...
        raise WireError(f"a data message is not valid msgpack ({type(e).__name__})") from None
    if type(fields) is not list or len(fields) not in (7, 8):
        raise WireError("a data message's envelope must be an array of 7 (an event) or 8 (a burst)")
    version, tag, seq, frontier, producer, port, value, *count = fields
    if type(version) is not int or version != WIRE_VERSION:  # an array's != is an array
        raise WireError(f"a data message of wire format {shown(version, 20)}; this process speaks {WIRE_VERSION}")
    # _tag's check, inline for the tags that pass it (two calls saved per message); _tag says
    # what is wrong with one that does not
    if (type(tag) is list and len(tag) == 2 and type(tag[0]) is int and type(tag[1]) is int
            and tag[0] >= 0 and tag[1] >= 0):
        tag = (tag[0], tag[1])
    else:
        tag = _tag("tag", tag)
    if (type(frontier) is list and len(frontier) == 2 and type(frontier[0]) is int and type(frontier[1]) is int
            and frontier[0] >= 0 and frontier[1] >= 0):
        frontier = (frontier[0], frontier[1])
    else:
        frontier = _tag("frontier", frontier)
    if type(seq) is not int or not 0 <= seq < SEQ_LIMIT:
        raise WireError(f"seq must be an integer from 0 to 2**63 - 1, got {shown(seq, 40)}")
    if type(producer) is not str or type(port) is not str:
        raise WireError("producer and port must be strings")
    if expected is not None and (producer, port) != expected:
        raise WireError(f"a message for {producer}.{port} arrived on the key of {expected[0]}.{expected[1]}")
    if frontier < tag:
        raise WireError(f"frontier {frontier} is before the event's own tag {tag}")
    if not count:  # (the tuple made without DataMessage's Python __new__: one call less per message)
        return [_new_tuple(DataMessage, (tag, seq, frontier, producer, port, value))]
    (count,) = count
    if type(count) is not int or not 1 <= count <= MAX_BURST:
        raise WireError(f"a burst's count must be an integer from 1 to {MAX_BURST}, got {shown(count, 20)}")
    if seq + count > SEQ_LIMIT:
        raise WireError(f"a burst of {count} from seq {seq} runs past the last seq a stream has")
    if value is None and blank_ok:  # its values were left out (the coordinator records that they were sent)
        value = [None] * count
    elif type(value) is np.ndarray and travels_as_rows(value) and len(value) == count:
        value = list(value)  # its rows: read-only views of the message (of a 1-D array, numpy scalars)
    elif type(value) is not list or len(value) != count:
        raise WireError(f"a burst must hold a list of as many values as its count, or an array of as many rows, "
                        f"got {shown(count, 20)} and {type(value).__name__}")
    last = count - 1
    return [DataMessage(tag, seq + i, frontier if i == last else tag, producer, port, item)
            for i, item in enumerate(value)]


def decode_data(data: bytes, expected: tuple[str, str] | None = None) -> DataMessage:
    """:func:`decode_events` of a message of one event (not a burst): that event."""
    events = decode_events(data, expected)
    if len(events) != 1:
        raise WireError(f"a burst of {len(events)} events where one event was expected")
    return events[0]


class Progress(NamedTuple):
    frontier: Tag
    producer: str
    sent: dict[str, int]  # port -> the last seq published on it before this message


def decode_progress(data: bytes, expected: str | None = None) -> Progress:
    """Decode and validate a progress message."""
    _, frontier, producer, sent = _fields(data, 4, "progress")
    frontier = _tag("frontier", frontier)
    if type(producer) is not str:
        raise WireError("producer must be a string")
    if expected is not None and producer != expected:
        raise WireError(f"progress of {producer} arrived on the key of {expected}")
    if type(sent) is not dict or not all(type(k) is str and type(v) is int and v >= -1 for k, v in sent.items()):
        raise WireError("the seqs of a progress message must map port names to integers >= -1")
    return Progress(frontier, producer, sent)
