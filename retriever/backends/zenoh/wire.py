"""The Zenoh runtime's key space and message envelopes (DESIGN.md §7).

Key space, under ``retriever/<namespace>/``::

    data/<node>/<port>     events          [1, [t, m], seq, [ft, fm], producer, port, value]
    progress/<node>        frontiers       [1, [ft, fm], producer, {port: last seq sent}]
                                           (also a queryable: ask for it)
    status/steps/<node>    step records    [1, node, [record, ...]]
    status/node/<node>     worker state    [1, node, state, info]
    ctl/run                control         [1, op, args]

A data message is a msgpack array: format version ``1``, the event's tag (``t`` in integer ns since
the run's start ``T0``, microstep ``m``), its seq (per node and port, from 0), the producer's
*frontier* after it (every later event of this producer has a tag ``≥`` it, so a consumer's edge is
complete up to any tag ``<`` it: the watermark of DESIGN.md §5), the producer node and port (as in
the key), and the value in Retriever's codec (numpy arrays, tuples, big ints and dataclasses as
msgpack extension types 1–5, see ``codec.py``). A plain Zenoh subscriber on
``retriever/<ns>/data/**`` can decode it with any msgpack library.

Zenoh keeps messages in order per key, not across keys, so a progress message says which events
it comes after: its frontier holds for a consumer of ``port`` once that consumer has received
every seq of ``port`` up to the one named (seqs are dense, so gaps show what is in flight).

Anything on the key space that does not decode exactly so raises :class:`WireError`, which the
runtime counts, logs and drops: a foreign or garbage message never reaches a flow. Values never
make the receiving process import a module it has not imported already.
"""

from __future__ import annotations

import re
from typing import Any, NamedTuple

import msgpack

from ...codec import Encoder, unpackb
from ...errors import CodecError, RetrieverError

WIRE_VERSION = 1
ROOT = "retriever"
_CHUNK = re.compile(r"[A-Za-z0-9_][A-Za-z0-9_.\-]*")

Tag = tuple[int, int]


class WireError(RetrieverError):
    """A message on the key space is not a Retriever message of this version."""


def check_chunk(kind: str, name: str) -> str:
    """A namespace, node or port must be one plain key-expression chunk."""
    if not isinstance(name, str) or not _CHUNK.fullmatch(name):
        raise ValueError(f"{kind} {name!r} cannot be a Zenoh key chunk: use letters, digits, '_', '-' and '.'"
                         " (no '/', '*', '$', '?', '#', and not empty)")
    return name


class KeySpace:
    """Key expressions of one namespace."""

    def __init__(self, namespace: str):
        self.namespace = check_chunk("namespace", namespace)
        self.prefix = f"{ROOT}/{namespace}"

    def data(self, node: str, port: str) -> str:
        return f"{self.prefix}/data/{node}/{port}"

    def all_data(self) -> str:
        return f"{self.prefix}/data/**"

    def progress(self, node: str) -> str:
        return f"{self.prefix}/progress/{node}"

    def all_progress(self) -> str:
        return f"{self.prefix}/progress/*"

    def status(self, *parts: str) -> str:
        return "/".join((self.prefix, "status", *parts))

    def steps(self, node: str) -> str:
        return f"{self.prefix}/status/steps/{node}"

    def node_status(self, node: str) -> str:
        return f"{self.prefix}/status/node/{node}"

    def run_control(self) -> str:
        return f"{self.prefix}/ctl/run"

    def workers(self, name: str = "*") -> str:
        return f"{self.prefix}/workers/{name}"

    def ctl(self, name: str) -> str:
        return f"{self.prefix}/ctl/{name}"

    def parse_data(self, key: str) -> tuple[str, str] | None:
        """``(node, port)`` of a data key of this namespace, else None."""
        head = self.prefix + "/data/"
        if not key.startswith(head):
            return None
        parts = key[len(head):].split("/")
        return (parts[0], parts[1]) if len(parts) == 2 else None


class DataMessage(NamedTuple):
    tag: Tag
    seq: int
    frontier: Tag
    producer: str
    port: str
    value: Any


class WireEncoder:
    """Encodes this process's messages (one per thread: it reuses a packer)."""

    def __init__(self) -> None:
        self._encode = Encoder().pack
        self._pack = msgpack.Packer(use_bin_type=True).pack

    def data(self, tag: Tag, seq: int, frontier: Tag, producer: str, port: str, value: Any) -> bytes:
        head = self._pack([WIRE_VERSION, tag, seq, frontier, producer, port])
        # The array's header says 7 elements; the head packed 6: patch the count, append the value.
        return b"\x97" + head[1:] + self._encode(value)

    def progress(self, frontier: Tag, producer: str, sent: dict[str, int]) -> bytes:
        return self._pack([WIRE_VERSION, frontier, producer, sent])

    def steps(self, node: str, records: list) -> bytes:
        """Step records ``(tag, consumed, produced, status, detail, wall_start_ns, wall_ns)``."""
        return self._pack([WIRE_VERSION, node, records])

    def status(self, node: str, state: str, info: dict) -> bytes:
        return self._pack([WIRE_VERSION, node, state, info])

    def control(self, op: str, args: dict) -> bytes:
        return self._pack([WIRE_VERSION, op, args])


def _tag(what: str, raw: Any) -> Tag:
    if (type(raw) is not list or len(raw) != 2 or type(raw[0]) is not int or type(raw[1]) is not int
            or raw[0] < 0 or raw[1] < 0):
        raise WireError(f"{what} must be [t_ns, microstep] of two integers >= 0, got {raw!r:.80}")
    return (raw[0], raw[1])


def _fields(data: bytes, count: int, kind: str) -> list:
    if not isinstance(data, (bytes, bytearray, memoryview)):
        raise WireError(f"a {kind} message must be bytes, got {type(data).__name__}")
    unpacker = msgpack.Unpacker(raw=False, strict_map_key=False, max_buffer_size=len(data) + 1)
    unpacker.feed(data)
    try:
        size = unpacker.read_array_header()
    except Exception:
        raise WireError(f"a {kind} message must be a msgpack array") from None
    if size != count:
        raise WireError(f"a {kind} message must be an array of {count}, got {size} elements")
    fields = []
    try:
        for _ in range(count - 1 if kind == "data" else count):
            fields.append(unpacker.unpack())
    except Exception as e:
        raise WireError(f"a {kind} message is not valid msgpack ({type(e).__name__})") from None
    if fields[0] != WIRE_VERSION:
        raise WireError(f"a {kind} message of wire format {fields[0]!r:.20}; this process speaks {WIRE_VERSION}")
    if kind == "data":
        fields.append(data[unpacker.tell():])  # the value, decoded by the codec
    elif unpacker.tell() != len(data):
        raise WireError(f"a {kind} message has trailing bytes")
    return fields


def decode_data(data: bytes, expected: tuple[str, str] | None = None) -> DataMessage:
    """Decode and validate a data message; ``expected`` is the ``(node, port)`` of its key."""
    _, tag, seq, frontier, producer, port, value = _fields(data, 7, "data")
    tag, frontier = _tag("tag", tag), _tag("frontier", frontier)
    if type(seq) is not int or seq < 0:
        raise WireError(f"seq must be an integer >= 0, got {seq!r:.40}")
    if type(producer) is not str or type(port) is not str:
        raise WireError("producer and port must be strings")
    if expected is not None and (producer, port) != expected:
        raise WireError(f"a message for {producer}.{port} arrived on the key of {expected[0]}.{expected[1]}")
    if frontier < tag:
        raise WireError(f"frontier {frontier} is before the event's own tag {tag}")
    try:
        value = unpackb(value, import_modules=False)
    except CodecError as e:
        raise WireError(f"the value of {producer}.{port} #{seq} cannot be decoded: {e}") from None
    except Exception as e:  # msgpack's own errors on garbage: ExtraData, ValueError, ...
        raise WireError(f"the value of {producer}.{port} #{seq} is not valid msgpack ({type(e).__name__})") from None
    return DataMessage(tag, seq, frontier, producer, port, value)


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


class StepBatch(NamedTuple):
    node: str
    records: list  # (tag, consumed, produced, status, detail, wall_start_ns, wall_ns)


def decode_steps(data: bytes, expected: str | None = None) -> StepBatch:
    """Decode a batch of step records; ids come back as tuples, as in the trace."""
    _, node, records = _fields(data, 3, "steps")
    if type(node) is not str or (expected is not None and node != expected) or type(records) is not list:
        raise WireError(f"a steps message must carry its node ({expected}) and a list of records")
    out = []
    try:
        for tag, consumed, produced, status, detail, start, wall in records:
            out.append((_tag("tag", tag),
                        {port: tuple(map(tuple, ids)) for port, ids in consumed.items()},
                        tuple(map(tuple, produced)), str(status), detail, int(start), int(wall)))
    except WireError:
        raise
    except Exception as e:
        raise WireError(f"a steps message of {node} has a malformed record ({type(e).__name__}: {e})") from None
    return StepBatch(node, out)


def decode_status(data: bytes) -> tuple[str, str, dict]:
    """``(node, state, info)`` of a worker's status message."""
    _, node, state, info = _fields(data, 4, "status")
    if type(node) is not str or type(state) is not str or type(info) is not dict:
        raise WireError("a status message is [1, node, state, info]")
    return node, state, info


def decode_control(data: bytes) -> tuple[str, dict]:
    """``(op, args)`` of a control message."""
    _, op, args = _fields(data, 3, "control")
    if type(op) is not str or type(args) is not dict:
        raise WireError("a control message is [1, op, args]")
    return op, args
