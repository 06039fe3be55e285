"""Exact readers of the protocol's fields, and the record every message is.

A message is plain msgpack: no extension type is ever decoded into anything but a refusal, so
nothing in a message is imported or called. Each field of a record names its *kind*, which
reads the decoded value (str, int, float, bool, None, list, dict) into what the record holds
(tuples for lists, enum members for names of a closed set) or raises :class:`WireError` naming
the field, what it expects and what arrived. A record's fields are its message's map, in the
order the record declares them; a field marked optional may be absent from the map (the record
then holds :data:`ABSENT`, or the field's default), every other one must be there, and no other
key may.
"""

from __future__ import annotations

import dataclasses
import math
import re
from enum import Enum
from typing import Any, ClassVar

import msgpack

from ....errors import WireError
from ..wire import WIRE_VERSION, shown

#: the largest ns count (a tag's time, a T0 in ns since the epoch, an end) and seq a field holds
NS_MAX = (1 << 63) - 1
SEQ_MAX = (1 << 63) - 1
#: a node, port or worker name: one Zenoh key chunk (wire.check_chunk), at most this long
MAX_NAME_CHARS = 1024
#: free text (an error, a traceback, a warning, an output line), at most this long
MAX_TEXT_CHARS = 1 << 20
#: a list or map of a message holds at most this many items
MAX_ITEMS = 1 << 16
#: a message of the control envelope, at most (its longest fields: an error, a traceback)
MAX_MESSAGE_BYTES = 16 << 20
#: a process id, as Linux numbers them (pid_t)
PID_MAX = (1 << 31) - 1

_CHUNK = re.compile(r"[A-Za-z0-9_][A-Za-z0-9_.\-]*")


class _Absent:
    """The value of an optional field its message did not carry."""

    _instance: _Absent | None = None

    def __new__(cls) -> _Absent:
        if cls._instance is None:
            cls._instance = super().__new__(cls)
        return cls._instance

    def __repr__(self) -> str:
        return "ABSENT"

    def __bool__(self) -> bool:
        return False


ABSENT: Any = _Absent()


def got(value: Any) -> str:
    """A decoded value as an error says what arrived: its type, then the value, short (wire.shown)."""
    return f"{type(value).__name__} {shown(value, 60)}"


class Kind:
    """How one field travels: :meth:`read` a decoded value (or raise), :meth:`write` one back."""

    #: what the field must be, for error messages
    expects = "a value"

    def read(self, value: Any, where: str) -> Any:
        raise NotImplementedError

    def write(self, value: Any) -> Any:
        return value

    def refuse(self, value: Any, where: str) -> WireError:
        return WireError(f"{where} must be {self.expects}, got {got(value)}")


class Int(Kind):
    def __init__(self, low: int, high: int):
        self.low, self.high = low, high
        self.expects = f"an integer from {low} to {high}"

    def read(self, value: Any, where: str) -> int:
        if type(value) is not int or not self.low <= value <= self.high:
            raise self.refuse(value, where)
        return value


class Float(Kind):
    def __init__(self, low: float, high: float):
        self.low, self.high = low, high
        self.expects = f"a finite float from {low:g} to {high:g}"

    def read(self, value: Any, where: str) -> float:
        if type(value) is not float or not math.isfinite(value) or not self.low <= value <= self.high:
            raise self.refuse(value, where)
        return value


class Bool(Kind):
    expects = "true or false"

    def read(self, value: Any, where: str) -> bool:
        if type(value) is not bool:
            raise self.refuse(value, where)
        return value


class Text(Kind):
    """A string of at most ``max_chars`` characters (at least ``min_chars``)."""

    def __init__(self, max_chars: int = MAX_TEXT_CHARS, min_chars: int = 0):
        self.max_chars, self.min_chars = max_chars, min_chars
        self.expects = f"a string of {min_chars} to {max_chars} characters"

    def read(self, value: Any, where: str) -> str:
        if type(value) is not str or not self.min_chars <= len(value) <= self.max_chars:
            raise self.refuse(value, where)
        return value


class Name(Kind):
    """A node, port or worker name: one plain Zenoh key chunk (as wire.check_chunk admits)."""

    expects = f"a name of letters, digits, '_', '-' and '.' (at most {MAX_NAME_CHARS} characters)"

    def read(self, value: Any, where: str) -> str:
        if type(value) is not str or len(value) > MAX_NAME_CHARS or not _CHUNK.fullmatch(value):
            raise self.refuse(value, where)
        return value


def port() -> Text:
    """A port's name: the IR checks node ids (Name) but not every port's, so a port is any
    non-empty text of at most MAX_NAME_CHARS."""
    return Text(MAX_NAME_CHARS, min_chars=1)


class OneOf(Kind):
    """A name of a closed set: one of ``enum``'s values, read as its member."""

    def __init__(self, enum: type[Enum]):
        self.enum = enum
        self.expects = "one of " + ", ".join(repr(m.value) for m in enum)

    def read(self, value: Any, where: str) -> Enum:
        try:
            return self.enum(value)
        except (ValueError, TypeError):
            raise self.refuse(value, where) from None

    def write(self, value: Enum | str) -> Any:
        """The member's value; a text is taken only if it is one (ValueError: no message says a
        name outside the set)."""
        return self.enum(value).value


class Nullable(Kind):
    """None, or a value of ``inner``."""

    def __init__(self, inner: Kind):
        self.inner = inner
        self.expects = f"nil or {inner.expects}"

    def read(self, value: Any, where: str) -> Any:
        return None if value is None else self.inner.read(value, where)

    def write(self, value: Any) -> Any:
        return None if value is None else self.inner.write(value)


class ListOf(Kind):
    """A list of ``item`` values (``min_items`` to ``max_items``), held as a tuple."""

    def __init__(self, item: Kind, max_items: int = MAX_ITEMS, min_items: int = 0):
        self.item, self.max_items, self.min_items = item, max_items, min_items
        self.expects = f"a list of {min_items} to {max_items} items"

    def read(self, value: Any, where: str) -> tuple:
        if type(value) is not list or not self.min_items <= len(value) <= self.max_items:
            raise self.refuse(value, where)
        read = self.item.read
        return tuple(read(item, f"{where}[{i}]") for i, item in enumerate(value))

    def write(self, value: tuple) -> list:
        write = self.item.write
        return [write(item) for item in value]


class Row(Kind):
    """A list of a fixed length whose items have kinds of their own (``[node, port, seq]``), held as a tuple.
    ``of=tuple``: a tuple, as the project codec decodes one (codec.unpackb; plain msgpack has none)."""

    def __init__(self, *items: Kind, expects: str, of: type[list] | type[tuple] = list):
        self.items, self.expects, self.of = items, expects, of

    def read(self, value: Any, where: str) -> tuple:
        if type(value) is not self.of or len(value) != len(self.items):
            raise self.refuse(value, where)
        return tuple(kind.read(item, f"{where}[{i}]") for i, (kind, item) in enumerate(zip(self.items, value)))

    def write(self, value: tuple) -> list | tuple:
        return self.of(kind.write(item) for kind, item in zip(self.items, value))


class MapOf(Kind):
    """A map of ``key`` to ``value`` (at most ``max_items``), held as a dict."""

    def __init__(self, key: Kind, value: Kind, max_items: int = MAX_ITEMS):
        self.key, self.value, self.max_items = key, value, max_items
        self.expects = f"a map of at most {max_items} items"

    def read(self, value: Any, where: str) -> dict:
        if type(value) is not dict or len(value) > self.max_items:
            raise self.refuse(value, where)
        read_key, read_value, at = self.key.read, self.value.read, self.at
        return {read_key(k, f"{where} key {shown(k, 40)}"): read_value(v, at(where, k)) for k, v in value.items()}

    def at(self, where: str, key: Any) -> str:
        """Where the value of ``key`` is, as its errors say (``key`` is read first: a valid key)."""
        return f"{where}[{shown(key, 40)}]"

    def write(self, value: dict) -> dict:
        write_key, write_value = self.key.write, self.value.write
        return {write_key(k): write_value(v) for k, v in value.items()}


class Document(Kind):
    """A map with string keys whose values its receiver validates as a whole (a run's IR:
    ir.IR, and its plan: plan.Plan.from_data); read as it came, never called."""

    expects = "a map with string keys"

    def read(self, value: Any, where: str) -> dict:
        if type(value) is not dict or not all(type(k) is str for k in value):
            raise self.refuse(value, where)
        return value


class Plain(Kind):
    """Free-form plain data (a step record's detail): nil, booleans, integers, finite floats,
    strings, bytes, lists, and maps with string keys, at most ``depth`` levels deep."""

    def __init__(self, depth: int = 16):
        self.depth = depth
        self.expects = f"plain data (maps with string keys, no extension types, finite floats, {depth} levels)"

    def read(self, value: Any, where: str) -> Any:
        self._check(value, where, self.depth)
        return value

    def _check(self, value: Any, where: str, depth: int) -> None:
        kind = type(value)
        if kind in (type(None), bool, int):
            return
        if kind is float:
            if not math.isfinite(value):
                raise self.refuse(value, where)
            return
        if kind in (str, bytes):
            if len(value) > MAX_TEXT_CHARS:
                raise self.refuse(value, where)
            return
        if depth == 0 or kind not in (list, dict) or len(value) > MAX_ITEMS:
            raise self.refuse(value, where)
        if kind is list:
            for i, item in enumerate(value):
                self._check(item, f"{where}[{i}]", depth - 1)
            return
        for k, item in value.items():
            if type(k) is not str:
                raise self.refuse(value, where)
            self._check(item, f"{where}[{shown(k, 40)}]", depth - 1)


class HexKey(Kind):
    """A process's key (origin.KEY_BYTES random bytes), as the hex text it travels as."""

    def __init__(self, size: int):
        self.size = size
        self.expects = f"{2 * size} hexadecimal digits (a key of {size} bytes)"

    def read(self, value: Any, where: str) -> bytes:
        if type(value) is not str or len(value) != 2 * self.size or not all(c in "0123456789abcdef" for c in value):
            raise self.refuse(value, where)
        return bytes.fromhex(value)

    def write(self, value: bytes) -> str:
        return value.hex()


class Nested(Kind):
    """A map that is a record of its own (a node's line in a deployment's status)."""

    def __init__(self, record: type[Record]):
        self.record = record
        self.expects = f"a map of {record.__name__}'s fields"

    def read(self, value: Any, where: str) -> Record:
        return self.record.from_fields(value, where)

    def write(self, value: Record) -> dict:
        return value.to_fields()


def field(kind: Kind, *, optional: bool = False, default: Any = dataclasses.MISSING,
          default_factory: Any = dataclasses.MISSING) -> Any:
    """A record's field that travels as ``kind``; ``optional``: its message may leave it out
    (:data:`ABSENT` then); ``default`` (or ``default_factory``): it may, and the record then
    holds that."""
    if default is not dataclasses.MISSING or default_factory is not dataclasses.MISSING:
        return dataclasses.field(default=default, default_factory=default_factory,
                                 metadata={"kind": kind, "optional": True})
    return dataclasses.field(default=ABSENT if optional else dataclasses.MISSING,
                             metadata={"kind": kind, "optional": optional})


class Record:
    """A message of the protocol: a frozen dataclass whose fields travel as a map (see the
    module docstring). Subclasses name their op or state (``NAME``) and, in a section module,
    the channel that carries them (``CHANNEL``), which encodes and decodes them."""

    NAME: ClassVar[str] = ""
    #: the channel that encodes and decodes this record (set by the one that claims it)
    CHANNEL: ClassVar[Any]
    #: fields an older sender put in this message that must now be refused with their own reason
    REFUSED: ClassVar[dict[str, str]] = {}
    _schema: ClassVar[tuple[tuple[str, Kind, bool], ...]]
    _defaults: ClassVar[dict[str, Any]]

    @classmethod
    def schema(cls) -> tuple[tuple[str, Kind, bool], ...]:
        """``(name, kind, optional)`` of each field that travels in the map, in order."""
        if "_schema" not in cls.__dict__:
            cls._schema = tuple((f.name, f.metadata["kind"], f.metadata["optional"])
                                for f in dataclasses.fields(cls) if "kind" in f.metadata)
        return cls._schema

    def encode(self) -> bytes:
        """This message's bytes."""
        return self.CHANNEL.encode(self)

    @classmethod
    def decode(cls, data: Any) -> Record:
        """The message ``data`` as this record (exact); WireError for anything else, another
        message of its channel too."""
        record = cls.CHANNEL.decode(data)
        if type(record) is not cls:
            raise WireError(f"a '{record.NAME}' message where '{cls.NAME}' was expected")
        return record

    @classmethod
    def defaults(cls) -> dict[str, Any]:
        """The default of each field that has one (ABSENT is none): its message leaves it out."""
        if "_defaults" not in cls.__dict__:
            found = {}
            for f in dataclasses.fields(cls):
                if f.default_factory is not dataclasses.MISSING:
                    found[f.name] = f.default_factory()
                elif f.default is not dataclasses.MISSING and f.default is not ABSENT:
                    found[f.name] = f.default
            cls._defaults = found
        return cls._defaults

    def to_fields(self) -> dict:
        """The message's map: each field present and not at its default, in the record's order."""
        defaults = self.defaults()
        return {name: kind.write(value) for name, kind, _ in self.schema()
                if (value := getattr(self, name)) is not ABSENT and not (name in defaults and value == defaults[name])}

    @classmethod
    def from_fields(cls, fields: Any, where: str, **envelope: Any) -> Record:
        """The record of a decoded map (exact: every field read, none missing, none more);
        ``envelope``: fields that travel outside the map (a status's node)."""
        if type(fields) is not dict:
            raise WireError(f"{where} must carry a map of its fields, got {got(fields)}")
        values = dict(envelope)
        for name, kind, optional in cls.schema():
            if name in fields:
                values[name] = kind.read(fields[name], f"{where}: field '{name}'")
            elif not optional:
                raise WireError(f"{where} lacks its field '{name}'")
        extra = [k for k in fields if k not in values or k in envelope]
        if extra:
            reason = next((cls.REFUSED[k] for k in extra if k in cls.REFUSED), None)
            raise WireError(f"{where}: {reason}" if reason else
                            f"{where} has a field it does not take: {shown(extra[0], 40)} "
                            f"(it takes {', '.join(n for n, _, _ in cls.schema()) or 'none'})")
        return cls(**values)


def _exact_map(pairs: list) -> dict:
    """A decoded msgpack map that names no key twice (a message that did would mean two things)."""
    found = dict(pairs)
    if len(found) != len(pairs):
        raise ValueError("a map names a key twice")
    return found


def pack(fields: list) -> bytes:
    """A message's bytes: a msgpack array, as wire.WireEncoder packs it (tuples as arrays: the
    project codec's packb would make them its extension type 2, which no plain reader knows)."""
    return msgpack.packb(fields, use_bin_type=True)


def unpack(data: Any, count: int, what: str, max_bytes: int, exact_maps: bool = True) -> list:
    """The fields of a message: a msgpack array of ``count`` whose first is WIRE_VERSION.
    ``exact_maps``: refuse a map that names a key twice (which costs a call per map)."""
    if not isinstance(data, (bytes, bytearray, memoryview)):
        raise WireError(f"{what} must be bytes, got {type(data).__name__}")
    if len(data) > max_bytes:
        raise WireError(f"{what} of {len(data)} bytes, past {max_bytes}: refused")
    try:
        fields = msgpack.unpackb(data, raw=False, strict_map_key=False, object_pairs_hook=_exact_map if exact_maps
                                 else None)
    except Exception as e:  # msgpack's own errors on garbage: ExtraData, ValueError, UnicodeDecodeError, ...
        raise WireError(f"{what} is not valid msgpack ({type(e).__name__}: {e})"[:300]) from None
    if type(fields) is not list or len(fields) != count:
        raise WireError(f"{what} must be a msgpack array of {count}, got {got(fields)}")
    if type(fields[0]) is not int or fields[0] != WIRE_VERSION:
        raise WireError(f"{what} of wire format {shown(fields[0], 20)}; this process speaks {WIRE_VERSION}")
    return fields


class Channel:
    """Where a family of records travels as ``[2, name, {fields}]`` (the control envelope):
    one of ``records`` per message, told apart by its op."""

    def __init__(self, what: str, records: tuple[type[Record], ...], max_bytes: int = MAX_MESSAGE_BYTES):
        self.what, self.max_bytes = what, max_bytes
        self.records = {record.NAME: record for record in records}
        for record in records:
            record.CHANNEL = self

    def encode(self, record: Record) -> bytes:
        if self.records.get(record.NAME) is not type(record):
            raise TypeError(f"{type(record).__name__} does not travel on {self.what}")
        return pack([WIRE_VERSION, str(record.NAME), record.to_fields()])

    def decode(self, data: Any, who: str | None = None) -> Record:
        """The record of a message; WireError for anything else. ``who``: the receiver, as an
        unknown op's error names it (``worker 'w' knows no op ...``)."""
        _, name, fields = unpack(data, 3, f"a message on {self.what}", self.max_bytes)
        record = self.records.get(name) if type(name) is str else None
        if record is None:
            raise WireError(f"{who or self.what} knows no op {shown(name, 40)} (it knows {', '.join(self.records)})")
        return record.from_fields(fields, f"a '{name}' message on {self.what}")
