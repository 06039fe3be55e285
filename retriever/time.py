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
#: the latest time, and the longest duration, a run can hold: tags, logs and the wire carry
#: times as int64 nanoseconds (2**63 - 1 ns is about 292 years)
MAX_TIME_NS = 2**63 - 1
MAX_SECONDS = MAX_TIME_NS / NS_PER_S
#: the fastest rate: a tick period of at least 1 ns, so that ticks are distinct integer nanoseconds
MAX_HZ = NS_PER_S

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
    if isinstance(x, bool) or not isinstance(x, (int, float, Fraction)):
        return False
    return isinstance(x, int) or math.isfinite(x)  # an int is finite, and may be too big for a float


def seconds_problem(name: str, value: object) -> str | None:
    """Why ``value`` is not a usable number of seconds for ``name`` (None when it is): it must be
    finite, >= 0, and at most :data:`MAX_SECONDS`."""
    if not is_finite_number(value) or value < 0:
        return f"{name} must be a finite number of seconds >= 0, got {value!r:.40}"
    if value > MAX_SECONDS:
        return (f"{name} must be at most {MAX_SECONDS:.4g} s (about 292 years: times are int64 nanoseconds), "
                f"got {value!r:.40}")
    return None


def max_microsteps_problem(value: object) -> str | None:
    """Why ``value`` is not a usable ``max_microsteps`` (None when it is): an integer from 1 to
    ``MAX_TIME_NS`` (microsteps are int64 too)."""
    if not isinstance(value, int) or isinstance(value, bool) or not 1 <= value <= MAX_TIME_NS:
        return (f"max_microsteps must be an integer from 1 to 2**63 - 1 (how many microsteps one instant may "
                f"run before the run stops with a Zeno-loop error), got {value!r}")
    return None


def rate_problem(name: str, hz: object) -> str | None:
    """Why ``hz`` is not a usable rate (None when it is): finite, with a period between 1 ns
    (``hz <= MAX_HZ``) and :data:`MAX_SECONDS`."""
    if not is_finite_number(hz) or hz <= 0:
        return f"{name} must be a finite number > 0, got {hz!r}"
    if hz > MAX_HZ:
        return (f"{name} must be at most {MAX_HZ:.0e} (a tick period of at least 1 ns: ticks are integer "
                f"nanoseconds), got {hz!r}")
    if exact_rational(hz) * MAX_TIME_NS < NS_PER_S:
        return f"{name} must be at least {1 / MAX_SECONDS:.4g} (a tick period of at most about 292 years), got {hz!r}"
    return None


def format_tag(tag: Tag) -> str:
    """Human form of a tag: ``t=0.100000000s m=1``."""
    t, m = tag
    sign = "-" if t < 0 else ""
    s, ns = divmod(abs(t), NS_PER_S)
    return f"t={sign}{s}.{ns:09d}s m={m}"
