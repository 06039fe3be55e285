"""Superdense time: integer nanoseconds plus a microstep.

A **tag** is a plain tuple ``(t, m)``: ``t`` in integer nanoseconds, ``m`` the microstep. Tuples
order lexicographically, which is exactly the superdense order, and cost nothing to compare.
Floats never decide order: seconds become nanoseconds once, by ``round(x * 1e9)``, and rates
become exact rationals (a float ``hz`` is taken as the decimal its ``repr`` shows).
"""

from __future__ import annotations

import math
from fractions import Fraction

NS_PER_S = 1_000_000_000

Tag = tuple[int, int]


def seconds_to_ns(seconds: float | int | Fraction) -> int:
    """Convert a duration in seconds to integer nanoseconds, ``round(x * 1e9)``."""
    if isinstance(seconds, bool):
        raise TypeError("a duration must be a number of seconds, not a bool")
    if isinstance(seconds, int):
        return seconds * NS_PER_S
    if isinstance(seconds, Fraction):
        return round(seconds * NS_PER_S)
    return round(float(seconds) * 1e9)


def exact_rational(x: float | int | Fraction) -> Fraction:
    """The rational number a user-written number denotes: ``30`` → 30, ``0.1`` → 1/10."""
    if isinstance(x, Fraction):
        return x
    if isinstance(x, int):
        return Fraction(x)
    return Fraction(repr(float(x)))


def is_finite_number(x: object) -> bool:
    return isinstance(x, (int, float, Fraction)) and not isinstance(x, bool) and math.isfinite(x)


def format_tag(tag: Tag) -> str:
    """Human form of a tag: ``t=0.100000000s m=1``."""
    t, m = tag
    sign = "-" if t < 0 else ""
    s, ns = divmod(abs(t), NS_PER_S)
    return f"t={sign}{s}.{ns:09d}s m={m}"
