"""``Burst``: several events on one output port from one step.

A step makes at most one event per output port, which caps a flow's rate at its tick rate. A
producer of many small values (a 1 kHz IMU read in batches, a tokenizer's tokens, a point
stream) returns them as a burst instead::

    def step(self):
        return {"imu": Burst(self.device.read_all())}     # n samples -> n events

Each value is an event of its own (its own seq, its own id in step records and in the log) and
they all carry the step's output tag, in order: a consumer's ``Queue()`` takes them all, oldest
first; ``Latest()`` sees the last, ``Exact()`` the first; a ``Trigger`` consumer ticks once for the burst, as for any
events at one tag. An empty burst is no event, as ``None`` is. The real-time backends send a
burst as one message, which is what lets one flow move hundreds of thousands of small values a
second (``benchmarks/throughput.py``).
"""

from __future__ import annotations

from collections.abc import Iterable
from typing import Any

import numpy as np


#: the most values a burst holds (a step with more makes an array its value, or splits them over
#: ticks): it bounds what one message may make a receiver build, and the seqs a lost process may
#: have used unreported (RESTART_SEQ_GAP in backends/zenoh/node/frontiers.py)
MAX_BURST = 1 << 16

_NOT_VALUES = (str, bytes, bytearray, memoryview, dict, set, frozenset)


class Burst:
    """Values that a step emits on one port as consecutive events at its output tag.

    ``Burst(array)``: the array's rows (views of it, as iterating it gives; of a 1-D array, numpy
    scalars). Rows of one dtype and shape, given so or as a list, travel as one array."""

    __slots__ = ("values", "rows")

    def __init__(self, values: Iterable[Any] = ()):
        if isinstance(values, _NOT_VALUES) or not isinstance(values, Iterable):
            what = type(values).__name__
            raise TypeError(f"Burst takes the values of its events (a list, a tuple, an array, an iterator), got {what}"
                            + (": wrap it in a list for one event" if isinstance(values, (str, bytes)) else ""))
        rows = values if type(values) is np.ndarray and travels_as_rows(values) else None
        values = tuple(values)
        if len(values) > MAX_BURST:
            raise ValueError(f"Burst of {len(values)} values: at most {MAX_BURST} in one step; emit an array "
                             "as one event, or split the values over ticks")
        if rows is None:
            for i, value in enumerate(values):
                if value is None:
                    raise TypeError(f"Burst: value {i} is None; None means 'no event', leave it out of the burst")
                if type(value) is Burst:
                    raise TypeError(f"Burst: value {i} is a Burst; a burst holds values, not bursts")
        self.values: tuple = values
        self.rows: np.ndarray | None = rows  # the array whose rows the values are, if given so

    @classmethod
    def unchecked(cls, values: tuple) -> Burst:
        """A burst of ``values`` as they are, not checked again: decoded ones, or blanks (the
        node loop's, for a burst it hands over or reports without its values)."""
        burst = cls.__new__(cls)
        burst.values, burst.rows = values, None
        return burst

    def stacked(self) -> np.ndarray | None:
        """The values as the rows of one array, when they are arrays (of one or more dimensions,
        not empty) of one dtype and shape, or the rows of the array given; else None."""
        if self.rows is not None:
            return self.rows
        values = self.values
        first = values[0] if values else None
        if type(first) is not np.ndarray or not first.ndim or not first.size:
            return None
        dtype, shape = first.dtype, first.shape
        for value in values:
            if type(value) is not np.ndarray or value.dtype != dtype or value.shape != shape:
                return None
        stacked = np.stack(values)
        return stacked if stacked.dtype == dtype else None  # (numpy makes a byte order native, for one)

    def __len__(self) -> int:
        return len(self.values)

    def __iter__(self):
        return iter(self.values)

    def __eq__(self, other: object) -> bool:
        """Bursts of equal values, in order, are equal (numpy arrays and scalars by dtype, shape
        and content, NaN equal to NaN; lists, tuples and dicts item by item): what a test of a
        step's outputs compares. Not hashable (it may hold arrays)."""
        if type(other) is not Burst:
            return NotImplemented
        return len(self.values) == len(other.values) and all(map(_same, self.values, other.values))

    __hash__ = None  # type: ignore[assignment]

    def __repr__(self) -> str:
        shown = ", ".join(repr(v) for v in self.values[:3])
        return f"Burst(<{len(self.values)} values: {shown}{', ...' if len(self.values) > 3 else ''}>)"


def _same(a: Any, b: Any) -> bool:
    """Equality of two events' values: numpy arrays and scalars by dtype, shape and content (NaN
    equal to NaN), never equal to a value of another kind; lists, tuples and dicts item by item;
    the rest by ``==``, and a comparison that raises or gives no truth value is inequality."""
    if a is b:
        return True
    if isinstance(a, (np.ndarray, np.generic)) or isinstance(b, (np.ndarray, np.generic)):
        return _same_numpy(a, b)
    if type(a) in (list, tuple) or type(b) in (list, tuple):
        return type(a) is type(b) and len(a) == len(b) and all(map(_same, a, b))
    if type(a) is dict or type(b) is dict:
        return type(a) is type(b) and a.keys() == b.keys() and all(_same(v, b[k]) for k, v in a.items())
    try:
        return bool(a == b)
    except Exception:  # (a value whose == gives an array, or raises)
        return False


def _same_numpy(a: Any, b: Any) -> bool:
    if type(a) is not type(b) or a.dtype != b.dtype or np.shape(a) != np.shape(b):
        return False
    if a.dtype.hasobject:
        return _same(np.asarray(a).tolist(), np.asarray(b).tolist())
    try:
        return bool(np.array_equal(a, b, equal_nan=a.dtype.kind in "fc"))
    except Exception:  # (a dtype with no ==: structured with odd fields, void)
        return False


def travels_as_rows(array: np.ndarray) -> bool:
    """Whether a burst of ``array``'s rows travels as the array (the sender asks) or an array
    received is such a burst (the receiver asks): rows that each hold bytes (no message of a few
    bytes makes a million empty rows), of a 1-D array numpy scalars of a plain dtype."""
    return 0 < len(array) <= array.nbytes and (array.ndim >= 2 or (
        array.ndim == 1 and array.dtype.fields is None and not array.dtype.hasobject))

