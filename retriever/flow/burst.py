"""``Burst``: several events on one output port from one step.

A step makes at most one event per output port, which caps a flow's rate at its tick rate. A
producer of many small values (a 1 kHz IMU read in batches, a tokenizer's tokens, a point
stream) returns them as a burst instead::

    def step(self):
        return {"imu": Burst(self.device.read_all())}     # n samples -> n events

Each value is an event of its own (its own seq, its own id in step records and in the log) and
they all carry the step's output tag, in order: a consumer's ``Queue()`` takes them all, oldest
first; ``Latest()`` sees the last; a ``Trigger`` consumer ticks once for the burst, as for any
events at one tag. An empty burst is no event, as ``None`` is. The real-time backends send a
burst as one message, which is what lets one flow move hundreds of thousands of small values a
second (``benchmarks/throughput.py``).
"""

from __future__ import annotations

from collections.abc import Iterable
from typing import Any

import numpy as np


class Burst:
    """Values that a step emits on one port as consecutive events at its output tag.

    ``Burst(array)`` of an array of two or more dimensions: its rows (views of it, as iterating
    it gives). Rows of one dtype and shape, given so or as a list, travel as one array."""

    __slots__ = ("values", "rows")

    def __init__(self, values: Iterable[Any] = ()):
        rows = values if type(values) is np.ndarray and values.ndim >= 2 else None
        values = tuple(values)
        if rows is None:
            for i, value in enumerate(values):
                if value is None:
                    raise TypeError(f"Burst: value {i} is None; None means 'no event', leave it out of the burst")
                if type(value) is Burst:
                    raise TypeError(f"Burst: value {i} is a Burst; a burst holds values, not bursts")
        self.values: tuple = values
        self.rows: np.ndarray | None = rows  # the array whose rows the values are, if given so

    @classmethod
    def _of(cls, values: tuple) -> Burst:
        """A burst of ``values`` as they are (decoded or blank ones: not checked again)."""
        burst = cls.__new__(cls)
        burst.values, burst.rows = values, None
        return burst

    def stacked(self) -> np.ndarray | None:
        """The values as the rows of one array, when they are arrays (of one or more dimensions)
        of one dtype and shape; else None."""
        if self.rows is not None:
            return self.rows
        values = self.values
        first = values[0] if values else None
        if type(first) is not np.ndarray or not first.ndim:
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

    def __repr__(self) -> str:
        shown = ", ".join(repr(v) for v in self.values[:3])
        return f"Burst([{shown}{', ...' if len(self.values) > 3 else ''}])  # {len(self.values)} values"

