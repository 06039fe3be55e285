"""Retriever's value codec: msgpack plus a few extension types, never pickle.

Used for trace digests today, and for the MCAP log and the Zenoh wire. Round-trips exactly:

- ``None``, bool, int (any size), float (bit-exact), str, bytes, list, dict (any msgpack keys);
- tuples (kept as tuples), numpy arrays of any non-object dtype and shape, numpy scalars;
- registered value types (``@io`` dataclasses), as ``["module:QualName", {field: value}]``.

Anything else raises :class:`CodecError` naming the type and the path to it inside the value.

Decoding never imports or calls anything it was not given by this process: a dataclass is rebuilt
only as a class that this process registered (``@io`` calls :func:`register_value_type`), found by
its registered path. Bytes from the network, a log or an IR file are hostile: a path that is not
registered here (``os:system``) is a :class:`CodecError`, or, for tools that only show values
(``retriever log cat``), an inert :class:`UnregisteredValue`.

Between processes (the Zenoh wire) arrays may travel *out of band*: :class:`OutOfBandEncoder`
packs each array as ``ExtType(6, [descr, shape, index])`` and hands its bytes back as the
``index``-th buffer, uncopied; :func:`unpackb_out_of_band` rebuilds it as a read-only view of that
buffer. The sender then copies each array once (into the message) and the receiver not at all.
"""

from __future__ import annotations

import dataclasses
import functools
import math
import re
import threading
from collections.abc import Callable
from typing import Any, Iterable, NamedTuple

import msgpack
import numpy as np

from .errors import CodecError, UnregisteredTypeError

#: (numpy's module has a ``__getattr__``, so CPython 3.11 reads ``np.X`` the slow way at each use:
#: these run per message, sent or received)
_NDARRAY, _frombuffer = np.ndarray, np.frombuffer

EXT_NDARRAY = 1
EXT_TUPLE = 2
EXT_BIGINT = 3
EXT_DATACLASS = 4
EXT_NPSCALAR = 5
EXT_NDARRAY_OOB = 6  # [descr, shape, buffer index]: the bytes travel beside the msgpack

_INT64_MIN, _UINT64_MAX = -(1 << 63), (1 << 64) - 1

#: extension values (tuples, dataclasses) nested deeper than this do not decode. Each level is a
#: nested msgpack decode, which takes tens of KiB of C stack (msgpack's unpack context lives
#: there): unbounded, a message of a few hundred bytes nesting tuples would overflow a thread's
#: stack (Zenoh's threads have 2 MiB) and kill the process. benchmarks/fuzz.py sends such messages.
MAX_EXT_DEPTH = 16


def type_path(cls: type) -> str:
    """``module:QualName`` of a class, the form used in IR ``type`` fields and the codec."""
    return f"{cls.__module__}:{cls.__qualname__}"


#: classes this process registered as value types, by the path their values carry
_value_types: dict[str, type] = {}

#: a class defined in the main script lives in ``__main__`` in the process that ran the script,
#: and in ``__mp_main__`` in a worker that imported it (as multiprocessing does): one path for both
_MODULE_ALIASES = {"__mp_main__": "__main__"}


def value_type_path(cls: type) -> str:
    """The path a value of ``cls`` carries, the same in every process of a run."""
    module = _MODULE_ALIASES.get(cls.__module__, cls.__module__)
    return f"{module}:{cls.__qualname__}"


def register_value_type(cls: type) -> type:
    """Let values of the dataclass ``cls`` be encoded, and decoded back into ``cls`` in this
    process. ``@io`` does this; the last class registered under a path wins (a re-run cell)."""
    if not (isinstance(cls, type) and dataclasses.is_dataclass(cls)):
        raise TypeError(f"only dataclasses can be value types, not {cls!r}")
    cls.__retriever_value_type__ = True
    _value_types[value_type_path(cls)] = cls
    return cls


def is_value_type(cls: type) -> bool:
    return cls.__dict__.get("__retriever_value_type__", False) is True


class UnregisteredValue(NamedTuple):
    """A dataclass value whose class this process has not registered, kept inert: what
    ``retriever log cat`` shows instead of calling anything."""

    path: str
    fields: dict

    def __repr__(self) -> str:
        return f"<{self.path}>(" + ", ".join(f"{k}={v!r}" for k, v in self.fields.items()) + ")"


def dataclass_fields(value: Any) -> dict[str, Any] | None:
    """A dataclass value's fields by name, the same whether this process registered its type
    (a dataclass) or decoded it without (an :class:`UnregisteredValue`); None for anything else."""
    if isinstance(value, UnregisteredValue):
        return value.fields
    if hasattr(value, "__dataclass_fields__") and not isinstance(value, type):
        return {name: getattr(value, name) for name in value.__dataclass_fields__}
    return None


_pack_plain = msgpack.Packer(use_bin_type=True).pack  # no `default`, so it never re-enters Python
_UINT8 = np.dtype(np.uint8)
#: msgpack's positive fixints, 0 to 127, by value: each one byte, the value itself
_FIXINTS = tuple(bytes((i,)) for i in range(128))
#: packs what packb packs without its `default` (no tuple, array, dataclass, int past 64 bits), or raises
_pack_strict = msgpack.Packer(use_bin_type=True, strict_types=True).pack


_array_heads: dict[tuple, bytes] = {}  # (dtype, shape) -> the msgpack bytes of "[descr, shape, " below


def _array_head(arr: np.ndarray) -> bytes:
    """The msgpack bytes of ``[descr, shape, `` (an array of 3 whose last item follows), cached:
    this is the hot path of logging and the wire, where the same few dtypes and shapes repeat."""
    key = (arr.dtype, arr.shape)
    head = _array_heads.get(key)
    if head is None:
        dtype = arr.dtype
        if dtype.hasobject:
            raise CodecError(f"numpy arrays of dtype object cannot be encoded (dtype {dtype})")
        # Structured dtypes need their full description; plain ones travel as their short string.
        descr = np.lib.format.dtype_to_descr(dtype) if dtype.fields else dtype.str
        head = b"\x93" + _pack_plain(descr) + _pack_plain(list(arr.shape))
        if len(_array_heads) < 4096:
            _array_heads[key] = head
    return head


_dtypes: dict[str, np.dtype] = {}  # descr string -> dtype, for the decoders' hot path


#: a plain dtype as ``dtype.str`` spells it (``<f8``, ``|u1``, ``<U3``, ``<M8[ns]``). Only these
#: reach numpy: its dtype parser takes far more (comma lists, ``(2,)f8`` shapes, which it reads with
#: ``ast.literal_eval``), and a decoder has no business compiling text from a message
_TYPESTR = re.compile(r"[<>|=]?[A-Za-z?]\d{0,9}(\[\d{0,9}[A-Za-z]{1,2}\])?")


def _array_dtype(descr: Any) -> np.dtype:
    if type(descr) is str:
        dtype = _dtypes.get(descr)
        if dtype is None:
            if not _TYPESTR.fullmatch(descr):
                raise CodecError(f"an array's dtype {descr!r:.40} is not a numpy type string such as '<f8'")
            dtype = np.dtype(descr)
            if len(_dtypes) < 1024:
                _dtypes[descr] = dtype
        return dtype
    if not _structured_descr(descr):
        raise CodecError(f"an array's dtype {descr!r:.60} is not a numpy type string or [[name, type(, shape)], ...]")
    return np.lib.format.descr_to_dtype(descr)


def _structured_descr(descr: Any) -> bool:
    """Whether ``descr`` is a structured dtype's description as ``dtype_to_descr`` makes it."""
    return type(descr) is list and all(
        type(f) is list and len(f) in (2, 3) and type(f[0]) is str
        and (_TYPESTR.fullmatch(f[1]) if type(f[1]) is str else _structured_descr(f[1]))
        and (len(f) == 2 or (type(f[2]) is list and all(type(n) is int for n in f[2])))
        for f in descr)


def _array_payload(arr: np.ndarray) -> bytes:
    """msgpack ``[descr, shape, raw bytes]``."""
    head = _array_head(arr)
    raw = arr.tobytes()
    return head + _bin_head(len(raw)) + raw


def _bin_head(n: int) -> bytes:
    """What precedes ``n`` bytes in msgpack (bin 8/16/32)."""
    if n < 0x100:
        return bytes((0xC4, n))
    if n < 0x10000:
        return b"\xc5" + n.to_bytes(2, "big")
    return b"\xc6" + n.to_bytes(4, "big")


#: (dtype, shape) -> array_encoding_head of an array of that dtype and shape
_encoding_heads: dict[tuple, bytes] = {}


def array_encoding_head(arr: np.ndarray) -> bytes:
    """What ``Encoder.pack(arr)`` puts before the array's raw bytes (in C order, ``arr.tobytes()``),
    cached by dtype and shape, which decide it: the log writer makes an array's record from it
    in one ``struct.pack``, and a big array's encoding can be assembled in a buffer numpy copies
    the array into, which lets other threads run meanwhile (``tobytes`` and joining bytes hold
    the GIL for the whole copy)."""
    key = (arr.dtype, arr.shape)
    found = _encoding_heads.get(key)
    if found is None:
        head, n = _array_head(arr), arr.nbytes
        size = _bin_head(n)
        found = _ext_head(EXT_NDARRAY, len(head) + len(size) + n) + head + size
        if len(_encoding_heads) < 4096:
            _encoding_heads[key] = found
    return found


def _default(obj: Any) -> Any:
    if type(obj) is tuple:  # (an event id, a tag: the commonest, in traces and step records)
        ext = _plain_tuple(obj, _depth.level)
        if ext is not None:
            return ext
    if isinstance(obj, np.ndarray):
        return msgpack.ExtType(EXT_NDARRAY, _array_payload(obj))
    return _extension(obj, packb)


#: what a tuple's items may be for :func:`_plain_tuple` (with tuples, lists and arrays)
_PLAIN_ITEMS = frozenset({int, str, float, bool, bytes, type(None)})


def _plain_tuple(obj: tuple, level: int) -> msgpack.ExtType | None:
    """The extension :func:`_extension` makes of a tuple nested ``level`` deep, for a tuple of
    plain values, arrays, and tuples and lists of them (an event id, a tag, a trace's record),
    made with one packer call rather than one a level (what it packs is what packb would); None
    for any other tuple, or one nested too deep: then :func:`_extension` makes it."""
    if level >= MAX_EXT_DEPTH:
        return None
    items = list(obj)
    if not _plain_items(items, level, True):
        return None
    try:
        return _ext_type((EXT_TUPLE, _pack_strict(items)))
    except (OverflowError, ValueError):  # an int past 64 bits (packb widens it), a str too long
        return None


def _plain_items(items: list, level: int, lists: bool) -> bool:
    """Make the tuples and arrays in ``items`` (and, with ``lists``, in lists in it: a list one
    level only) their extensions, in place; False if something else is in it."""
    for i, item in enumerate(items):
        kind = type(item)
        if kind in _PLAIN_ITEMS:
            continue
        if kind is tuple:
            item = _plain_tuple(item, level + 1)
            if item is None:
                return False
            items[i] = item
        elif kind is np.ndarray and not item.dtype.hasobject:  # as _default makes it
            items[i] = _ext_type((EXT_NDARRAY, _array_payload(item)))
        elif kind is list and lists:
            item = list(item)
            if not _plain_items(item, level, False):
                return False
            items[i] = item
        else:
            return False
    return True


#: an ExtType of (code, bytes) made without its checks (both are the codec's own)
_ext_type = functools.partial(tuple.__new__, msgpack.ExtType)


class _Depth(threading.local):
    level = 0


_depth = _Depth()


def _nested(pack_nested: Callable[[Any], bytes], inner: Any) -> bytes:
    """Pack what a tuple or dataclass holds, one level deeper: never past what decodes."""
    if _depth.level >= MAX_EXT_DEPTH:
        raise CodecError(f"a value nests tuples or dataclasses deeper than {MAX_EXT_DEPTH} levels, which this "
                         f"codec does not decode\n    hint: nest tuples and @io dataclasses at most {MAX_EXT_DEPTH} deep")
    _depth.level += 1
    try:
        return pack_nested(inner)
    finally:
        _depth.level -= 1


def _extension(obj: Any, pack_nested: Callable[[Any], bytes]) -> msgpack.ExtType:
    """The extension type of anything but an ndarray; ``pack_nested`` encodes the values inside
    tuples and dataclasses (with the caller's array encoding)."""
    if isinstance(obj, np.generic):
        return msgpack.ExtType(EXT_NPSCALAR, _array_payload(np.asarray(obj)))
    if isinstance(obj, tuple):
        return msgpack.ExtType(EXT_TUPLE, _nested(pack_nested, list(obj)))
    if isinstance(obj, int):  # beyond 64 bits
        return msgpack.ExtType(EXT_BIGINT, str(obj).encode())
    if is_value_type(type(obj)):
        fields = {name: getattr(obj, name) for name in _field_names(type(obj))}
        return msgpack.ExtType(EXT_DATACLASS, _nested(pack_nested, [value_type_path(type(obj)), fields]))
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        raise CodecError(
            f"cannot encode a {type(obj).__module__}.{type(obj).__qualname__}: a dataclass that is not a "
            "registered value type, which no process could decode\n"
            "    hint: decorate the class with @io (from retriever import io)")
    raise CodecError(
        f"cannot encode a value of type {type(obj).__module__}.{type(obj).__qualname__}\n"
        "    hint: use numbers, str, bytes, lists, dicts, numpy arrays or @io dataclasses"
    )


def _ext_hook(code: int, data: bytes, *, keep_unregistered: bool = False, buffers: list | None = None,
              depth: int = 0) -> Any:
    try:
        if code == EXT_NDARRAY_OOB:  # (the wire's arrays, one call sooner: this runs per array received)
            return _out_of_band_array(data, buffers)
        return _ext_value(code, data, keep_unregistered, buffers, depth)
    except CodecError:
        raise
    except Exception as e:  # what numpy, int() or msgpack raise on a damaged or forged value
        raise CodecError(f"a malformed value of msgpack extension type {code} ({type(e).__name__}: {e})"[:300]) from None


def _ext_value(code: int, data: bytes, keep_unregistered: bool, buffers: list | None, depth: int) -> Any:
    if code == EXT_NDARRAY or code == EXT_NPSCALAR:
        descr, shape, raw = msgpack.unpackb(data, raw=False)
        arr = np.frombuffer(raw, dtype=_array_dtype(descr)).reshape(shape).copy()
        return arr[()] if code == EXT_NPSCALAR else arr
    if code == EXT_NDARRAY_OOB:
        return _out_of_band_array(data, buffers)
    if code == EXT_TUPLE:
        return tuple(_unpack(data, keep_unregistered, buffers, depth + 1))
    if code == EXT_BIGINT:
        return int(data.decode())
    if code == EXT_DATACLASS:
        return _dataclass(*_dataclass_parts(_unpack(data, keep_unregistered, buffers, depth + 1)), keep_unregistered)
    raise CodecError(f"unknown msgpack extension type {code}")


def _dataclass_parts(decoded: Any) -> tuple[str, dict]:
    if (type(decoded) is not list or len(decoded) != 2 or type(decoded[0]) is not str
            or type(decoded[1]) is not dict or not all(type(k) is str for k in decoded[1])):
        raise CodecError("a dataclass value must be [\"module:QualName\", {field: value}]")
    return decoded[0], decoded[1]


def _dataclass(path: str, fields: dict, keep_unregistered: bool) -> Any:
    """Rebuild a registered value type; nothing is imported, and only a registered class called."""
    cls = _value_types.get(path)
    if cls is None:
        if keep_unregistered:
            return UnregisteredValue(path, fields)
        raise UnregisteredTypeError(f"cannot decode a value of type {path[:200]!r}: no value type of that name is registered "
                         "in this process, and decoding never imports or calls anything else\n"
                         "    hint: import the module that defines it (its @io class registers itself) before "
                         "decoding")
    known = _init_fields(cls)
    if not known.issuperset(fields):
        unknown = sorted(set(fields) - known)
        raise CodecError(f"cannot decode a {path}: it has no field(s) {', '.join(unknown)[:200]}")
    try:
        return cls(**fields)
    except Exception as e:
        raise CodecError(f"cannot decode a {path}: its constructor raised {type(e).__name__}: {e}") from None


@functools.lru_cache(maxsize=1024)
def _field_names(cls: type) -> tuple[str, ...]:
    """A value type's fields, in order: what its encoding holds (a class's fields never change)."""
    return tuple(f.name for f in dataclasses.fields(cls))


@functools.lru_cache(maxsize=1024)
def _init_fields(cls: type) -> frozenset[str]:
    """The fields a value type's constructor takes: what a decoded one may hold."""
    return frozenset(f.name for f in dataclasses.fields(cls) if f.init)


def _out_of_band_array(data: bytes, buffers: list | None) -> np.ndarray:
    """A read-only array over its buffer: no copy."""
    descr, shape, index = msgpack.unpackb(data, raw=False)
    if buffers is None or type(index) is not int or not 0 <= index < len(buffers):
        raise CodecError(f"an out-of-band array refers to buffer {index!r:.20}, which the message does not carry")
    dtype = _dtypes.get(descr) if type(descr) is str else None  # (a dtype seen before: no call)
    if dtype is None:
        dtype = _array_dtype(descr)
    buf = buffers[index]
    if type(shape) is not list or len(buf) != dtype.itemsize * math.prod(shape):
        raise CodecError(f"an out-of-band array of shape {shape!r:.40} and dtype {dtype} does not fit its "
                         f"buffer of {len(buf)} bytes")
    array = np.frombuffer(buf, dtype=dtype).reshape(shape)
    if type(data) is bytes and len(_out_of_band_heads) < 1024:
        # (1-D: frombuffer's shape already, no reshape)
        _out_of_band_heads[data] = (index, len(buf), dtype, None if len(shape) == 1 else tuple(shape))
    return array


#: an out-of-band array's extension data (``[descr, shape, index]``, packed) -> (index, its
#: buffer's size, dtype, shape or None if 1-D), as :func:`_out_of_band_array` last decoded those
#: bytes and found them fit their buffer: the same bytes with a buffer of that size decode the
#: same way, no check failing (the wire's arrays of a few dtypes and shapes, without msgpack,
#: the dtype and size checks and the hook's calls: :func:`unpackb_out_of_band`)
_out_of_band_heads: dict[bytes, tuple[int, int, np.dtype, tuple | None]] = {}


def packb(value: Any) -> bytes:
    """Encode a value to bytes. Raises CodecError naming the type and where it sits in the value."""
    try:
        return _pack_with(value, _default)
    except CodecError as e:
        raise _located(e, value) from None
    except (RecursionError, ValueError) as e:
        raise _too_deep(e, value) from None


#: what msgpack's packer raises for a value nested deeper than its limit (511 levels)
_MSGPACK_TOO_DEEP = "recursion limit exceeded"


def _too_deep(error: RecursionError | ValueError, value: Any) -> BaseException:
    """The CodecError of a value too deeply nested to encode (:func:`nested_too_deeply`): what
    msgpack's ValueError or Python's RecursionError, through nested values' packers, mean;
    another ValueError as it was."""
    if isinstance(error, ValueError) and _MSGPACK_TOO_DEEP not in str(error):
        return error
    return nested_too_deeply(value)


def nested_too_deeply(value: Any) -> CodecError:
    """The error of a value nested too deeply to encode (or to walk: flow/read_only.py), most
    often one that contains itself (a list appended to itself, a dataclass whose field refers
    back to it); not located in the value (_path_to_unencodable would recurse as deep)."""
    return CodecError(f"cannot encode a {type(value).__name__} nested too deeply (it may contain "
                      "itself: a list or dict holding itself, a dataclass referring back to it)\n    hint: "
                      "emit values that are trees, not graphs: copy out what a consumer needs")


class _IdlePackers(threading.local):
    """This thread's idle packers for :func:`packb`.

    Nested values (tuples, dataclasses) re-enter :func:`_pack_with` from a packer's ``default``,
    and a msgpack packer is not re-entrant, so each level takes its own packer from here and puts
    it back when done: a value nested d deep uses d packers, all reused by the next value. A fresh
    packer per call instead allocates msgpack's buffer each time, and nested, that allocation sits
    on top of the heap, so glibc gives it back and takes it again (two ``brk`` calls per tuple).
    """

    def __init__(self) -> None:
        self.packers: list = []


_idle = _IdlePackers()


def _pack_with(value: Any, default: Callable[[Any], Any], idle: list | None = None) -> bytes:
    """Pack with a packer from ``idle`` (this thread's pool for :func:`_default` if None)."""
    if idle is None:
        idle = _idle.packers
    packer = idle.pop() if idle else msgpack.Packer(default=default, use_bin_type=True, strict_types=True)
    try:
        data = packer.pack(value)
    except OverflowError:  # a packer that raised is dropped: its buffer may hold part of the value
        return msgpack.packb(_widen(value), default=default, use_bin_type=True, strict_types=True)
    idle.append(packer)
    return data


def _located(error: CodecError, value: Any) -> CodecError:
    try:
        path = _path_to_unencodable(value)
    except RecursionError:  # a value that contains itself (_too_deep's error, from a nested packer)
        return error
    if not path:
        return error
    first, _, rest = str(error).partition("\n")
    return CodecError(f"{first} at value{path}" + (f"\n{rest}" if rest else ""))


_FIXEXT = {1: 0xD4, 2: 0xD5, 4: 0xD6, 8: 0xD7, 16: 0xD8}


def _ext_head(code: int, n: int) -> bytes:
    """What precedes an ``ExtType(code, payload)``'s payload of ``n`` bytes in msgpack (exactly
    msgpack's: fixext 1/2/4/8/16, else ext 8/16/32)."""
    fixed = _FIXEXT.get(n)
    if fixed is not None:
        return bytes((fixed, code))
    if n < 0x100:
        return bytes((0xC7, n, code))
    if n < 0x10000:
        return b"\xc8" + n.to_bytes(2, "big") + bytes((code,))
    return b"\xc9" + n.to_bytes(4, "big") + bytes((code,))


class Encoder:
    """:func:`packb` with a reusable packer, for hot loops (the log writer, the wire).

    Not thread-safe: give each thread its own. Nested values (tuples, arrays, dataclasses) still
    go through :func:`packb`, so the shared packer is never re-entered.
    """

    __slots__ = ("_pack",)

    def __init__(self) -> None:
        self._pack = msgpack.Packer(default=_default, use_bin_type=True, strict_types=True).pack

    def pack(self, value: Any) -> bytes:
        if type(value) is _NDARRAY:  # the commonest payload: skip msgpack's `default` round trip
            head = _encoding_heads.get((value.dtype, value.shape))  # (a dtype and shape seen before: no call)
            return (head or array_encoding_head(value)) + value.tobytes()
        try:
            return self._pack(value)
        except OverflowError:
            return packb(value)
        except CodecError as e:
            raise _located(e, value) from None


def _path_to_unencodable(value: Any, path: str = "") -> str | None:
    """Where in a nested value the first thing the codec cannot encode sits, e.g. ``['a'][1]``."""
    if value is None or isinstance(value, (bool, int, float, str, bytes, np.ndarray, np.generic)):
        return None
    if isinstance(value, (list, tuple)):
        items = enumerate(value)
    elif isinstance(value, dict):
        items = value.items()
    elif dataclasses.is_dataclass(value) and not isinstance(value, type):
        found = (_path_to_unencodable(getattr(value, f.name), f"{path}.{f.name}") for f in dataclasses.fields(value))
        return next((p for p in found if p is not None), None)
    else:
        return path
    found = (_path_to_unencodable(v, f"{path}[{k!r}]") for k, v in items)
    return next((p for p in found if p is not None), None)


def _widen(value: Any) -> Any:
    # msgpack raises OverflowError instead of calling `default` for ints beyond 64 bits. Tuples and
    # dataclasses need no case here: `_default` encodes them through packb, which widens again.
    if type(value) is int and not (_INT64_MIN <= value <= _UINT64_MAX):
        return msgpack.ExtType(EXT_BIGINT, str(value).encode())
    if type(value) is list:
        return [_widen(v) for v in value]
    if type(value) is dict:
        return {_widen(k): _widen(v) for k, v in value.items()}
    return value


def unpackb(data: bytes, *, keep_unregistered: bool = False) -> Any:
    """Decode bytes made by :func:`packb`. A dataclass comes back as its registered value type;
    one not registered here raises CodecError, or with ``keep_unregistered=True`` (tools that only
    show values) comes back as an :class:`UnregisteredValue`."""
    if type(data) is bytes:
        known = _array_decodings.get(len(data))
        if known is not None and data.startswith(known[0]):  # an array as one decoded before: its data differs
            head, dtype, shape = known
            return np.frombuffer(data, dtype, offset=len(head)).reshape(shape).copy()
        value = _unpack(data, keep_unregistered, None)
        if type(value) is np.ndarray and value.dtype.itemsize and len(_array_decodings) < 1024:
            _array_decodings[len(data)] = (data[:len(data) - value.nbytes], value.dtype, value.shape)
        return value
    return _unpack(data, keep_unregistered, None)


def unpackb_read_only(data: bytes) -> Any:
    """:func:`unpackb`, but an array that decodes surely (:func:`decodes_surely`) comes back as a
    read-only view of ``data``, not a copy: a value decoded to be emitted again (which makes it
    read-only anyway), e.g. a replayed source's."""
    if type(data) is bytes:
        known = _array_decodings.get(len(data))
        if known is not None and data.startswith(known[0]):
            head, dtype, shape = known
            return np.frombuffer(data, dtype, offset=len(head)).reshape(shape)
    return unpackb(data)


def decodes_surely(data: bytes) -> bool:
    """Whether :func:`unpackb` decodes ``data`` surely, told without decoding it: an array's
    encoding that begins as one of the same length that it decoded before (``_array_decodings``).
    False says nothing: decode it to know. A decoder may put off decoding what decodes surely."""
    if type(data) is not bytes:
        return False
    known = _array_decodings.get(len(data))
    return known is not None and data.startswith(known[0])


def all_decode_surely(datas: Iterable[bytes]) -> bool:
    """Whether :func:`decodes_surely` says yes of every one of ``datas``, told in one loop (not a
    call each): a batch of logged values where nearly every one does."""
    known_heads = _array_decodings.get
    for data in datas:
        if type(data) is not bytes:
            return False
        known = known_heads(len(data))
        if known is None or not data.startswith(known[0]):
            return False
    return True


#: the length of an array's encoding -> (the bytes before its raw bytes, its dtype, its shape), as
#: unpackb last decoded one that long. Bytes of that length that begin with the same bytes encode
#: an array of that dtype and shape whatever the rest (the raw bytes of the same count), which
#: decodes as that one did, no check failing: the decoding of the log's and the wire's arrays of a
#: few dtypes and shapes, without msgpack and the extension hook
_array_decodings: dict[int, tuple[bytes, np.dtype, tuple]] = {}


def unpackb_out_of_band(data: bytes | memoryview, buffers: list) -> Any:
    """Decode what :class:`OutOfBandEncoder` packed, given its buffers (any bytes-like objects,
    e.g. memoryviews of the received message). Arrays come back as read-only views of them."""
    # (_unpack's work at depth 0, one call sooner: this runs per message received; the hook a
    # closure, not a partial with keywords, which builds a dict per call; an array as decoded
    # before, _out_of_band_heads, without a call)
    heads = _out_of_band_heads

    def hook(code: int, ext: bytes) -> Any:
        if code == EXT_NDARRAY_OOB:
            known = heads.get(ext)
            if known is not None and known[0] < len(buffers) and len(buffers[known[0]]) == known[1]:
                array = _frombuffer(buffers[known[0]], known[2])
                return array if known[3] is None else array.reshape(known[3])
        return _ext_hook(code, ext, buffers=buffers)

    return msgpack.unpackb(data, ext_hook=hook, raw=False, strict_map_key=False)


def _unpack(data: bytes, keep_unregistered: bool, buffers: list | None, depth: int = 0) -> Any:
    if depth > MAX_EXT_DEPTH:
        raise CodecError(f"a value nests tuples or dataclasses deeper than {MAX_EXT_DEPTH} levels, which this "
                         f"codec does not decode\n    hint: nest tuples and @io dataclasses at most {MAX_EXT_DEPTH} deep")
    if buffers is None:
        hook = _ext_hook if not keep_unregistered and not depth else _hook(keep_unregistered, depth)
    else:
        hook = functools.partial(_ext_hook, keep_unregistered=keep_unregistered, buffers=buffers, depth=depth)
    return msgpack.unpackb(data, ext_hook=hook, raw=False, strict_map_key=False)


@functools.lru_cache(maxsize=2 * (MAX_EXT_DEPTH + 1))
def _hook(keep_unregistered: bool, depth: int) -> Callable:
    """The ext hook of a value nested ``depth`` deep, made once (a dataclass's fields are one level down)."""
    return functools.partial(_ext_hook, keep_unregistered=keep_unregistered, buffers=None, depth=depth)


class OutOfBandEncoder:
    """Packs a value with its arrays' bytes left out: each array becomes ``ExtType(6, [descr,
    shape, index])`` and ``buffers[index]`` is a flat uint8 view of its memory (a non-contiguous
    array is made contiguous first). The caller joins header and buffers into one message: one
    copy per array, where in-band encoding makes several. Not thread-safe: one per thread."""

    __slots__ = ("_buffers", "_idle", "_pack")

    def __init__(self) -> None:
        self._buffers: list[np.ndarray] = []
        self._idle: list = []  # packers for nested values, with this encoder's `default`
        self._pack = msgpack.Packer(default=self._default, use_bin_type=True, strict_types=True).pack

    def pack(self, value: Any) -> tuple[bytes, list[np.ndarray]]:
        """``(msgpack bytes, buffers)``; the buffers are views of the value's arrays: send them
        before the arrays change."""
        self._buffers = buffers = []
        try:
            try:
                return self._pack(value), buffers
            except OverflowError:
                self._buffers = buffers = []
                return self._nested(value), buffers
        except CodecError as e:
            raise _located(e, value) from None
        except (RecursionError, ValueError) as e:
            raise _too_deep(e, value) from None

    def _nested(self, value: Any) -> bytes:
        return _pack_with(value, self._default, self._idle)

    def _default(self, obj: Any) -> Any:
        if isinstance(obj, _NDARRAY):
            # the cached head first, without a call (_array_head raises for dtype object, which
            # is never cached): this runs per array sent
            head = _array_heads.get((obj.dtype, obj.shape)) or _array_head(obj)
            if not obj.flags.c_contiguous:
                obj = np.ascontiguousarray(obj)
            if obj.ndim == 1:  # (flat already: one of bytes is its own buffer, another one a view away)
                self._buffers.append(obj if obj.dtype is _UINT8 else obj.view(_UINT8))
            else:
                self._buffers.append(obj.reshape(-1).view(_UINT8))
            # ExtType without its constructor's checks (two Python calls): its code and bytes are ours
            # (the index packed from a table while it is a positive fixint: no packer's call)
            index = len(self._buffers) - 1
            return tuple.__new__(msgpack.ExtType, (EXT_NDARRAY_OOB, head + (_FIXINTS[index] if index < 128
                                                                             else _pack_plain(index))))
        return _extension(obj, self._nested)
