"""An emitted value is immutable (docs/semantics.md): the arrays of an event's value are made
read-only when the step that made them returns.

In one process an event's value goes to its consumers by reference, and the log writer encodes
it after the step: a consumer that changed its input in place (``inp.frame *= 2``), or a producer
that wrote into a buffer it had emitted, would change what every other consumer sees and what the
log holds, and the run would no longer replay. Marking the arrays read-only (numpy's
``writeable`` flag, no copy) turns such a write into numpy's ``ValueError: assignment destination
is read-only`` at the line that makes it, on every backend alike: between processes the arrays
arrive read-only already, and a replay's values, decoded from the log, are read-only too.

What is not caught: a write through another array that shares the memory (an emitted view of a
buffer the flow keeps writing, an array a C library fills), and changes to lists, dicts and
dataclass fields themselves; those are the flow's to avoid (copy first).

A value that contains itself (a list appended to itself) cannot be walked, nor encoded: the
codec's CodecError (``codec.nested_too_deeply``), not a RecursionError from deep in the runtime.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np

from ..codec import nested_too_deeply
from .burst import Burst

#: values with nothing inside to protect (immutable Python values)
_IMMUTABLE = frozenset({int, float, str, bytes, bool, complex, type(None)})
#: (numpy's module has a ``__getattr__``, so CPython 3.11 reads ``np.ndarray`` the slow way at each
#: use: this runs per event emitted)
_NDARRAY = np.ndarray
#: a dataclass's instance fields by class (not its ClassVar entries, which its class holds for every instance)
_FIELDS: dict[type, tuple[str, ...]] = {}


def make_read_only(value: Any) -> None:
    """Mark every numpy array in ``value`` read-only, in place: the value itself, the items of
    lists and tuples, the values of dicts, the fields of dataclass values, and a Burst's values
    (and the array whose rows they are). CodecError if ``value`` nests too deeply to walk (it
    contains itself)."""
    kind = type(value)
    if kind is _NDARRAY:  # (the commonest, and a number, without the walk's call: per event)
        value.flags.writeable = False
        return
    if kind in _IMMUTABLE:
        return
    if kind is dict or kind is list or kind is tuple:  # (of arrays and plain values only: no call either)
        for item in (value.values() if kind is dict else value):
            if type(item) is _NDARRAY:
                item.flags.writeable = False
            elif type(item) not in _IMMUTABLE:
                break  # something to walk: the walk takes it all (an array marked twice is marked)
        else:
            return
    try:
        _walk(value)
    except RecursionError:
        raise nested_too_deeply(value) from None


def _walk(value: Any) -> None:
    """:func:`make_read_only`, recursively."""
    kind = type(value)
    if kind is _NDARRAY:
        value.flags.writeable = False
    elif kind in _IMMUTABLE:
        return
    elif kind is list or kind is tuple:
        for item in value:  # (an array or a plain item without a call)
            if type(item) is _NDARRAY:
                item.flags.writeable = False
            elif type(item) not in _IMMUTABLE:
                _walk(item)
    elif kind is dict:
        for item in value.values():
            if type(item) is _NDARRAY:
                item.flags.writeable = False
            elif type(item) not in _IMMUTABLE:
                _walk(item)
    elif kind is Burst:
        if value.rows is not None:
            value.rows.flags.writeable = False
        for item in value.values:
            _walk(item)
    elif isinstance(value, _NDARRAY):  # a subclass of ndarray
        value.flags.writeable = False
    else:
        fields = _FIELDS.get(kind)
        if fields is None and hasattr(kind, "__dataclass_fields__") and not isinstance(value, type):
            fields = _FIELDS[kind] = tuple(field.name for field in dataclasses.fields(kind))
        if fields is not None:
            for name in fields:
                _walk(getattr(value, name, None))
        elif isinstance(value, (list, tuple)):  # a NamedTuple, a list subclass
            for item in value:
                _walk(item)
        elif isinstance(value, dict):
            for item in value.values():
                _walk(item)
