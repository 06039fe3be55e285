"""Clocks say when a flow runs: on a fixed schedule, on events, or both.

Bind one to a flow with ``flow @ clock``. Every flow owns exactly one clock, so its ``step`` runs
sequentially, one tick at a time.
"""

from __future__ import annotations

from fractions import Fraction

from .errors import ClockError
from .time import MAX_HZ, NS_PER_S, exact_rational, is_finite_number, rate_problem, seconds_problem, seconds_to_ns


def _check_rate(owner: str, hz: object, offset: object) -> tuple[Fraction, int]:
    problem = rate_problem("hz", hz)
    if problem is not None:
        hint = ("time counts integer nanoseconds: use hz <= 1e9" if is_finite_number(hz) and hz > MAX_HZ
                else "for an event-driven flow use Trigger(\"port\") instead of a rate")
        raise ClockError(f"{owner}(hz={hz!r}): {problem}\n    hint: {hint}")
    problem = seconds_problem("offset", offset)
    if problem is not None:
        raise ClockError(f"{owner}(offset={offset!r}): {problem}")
    return exact_rational(hz), seconds_to_ns(offset)


def _check_ports(owner: str, ports: tuple) -> tuple[str, ...]:
    for p in ports:
        if not isinstance(p, str) or not p:
            raise ClockError(f"{owner}: trigger ports must be non-empty port names (str), got {p!r}")
    return tuple(dict.fromkeys(ports))


class Clock:
    """Base class of clocks. A clock is a value: equal clocks mean equal schedules."""

    __slots__ = ()

    hz: Fraction | None = None
    trigger_ports: tuple[str, ...] = ()
    triggered: bool = False

    def to_ir(self) -> dict:
        raise NotImplementedError

    def triggers_on(self, port: str) -> bool:
        """Whether an event arriving on input ``port`` makes a tick (no ports named: any)."""
        return self.triggered and (not self.trigger_ports or port in self.trigger_ports)

    def may_tick_at(self, tag: tuple[int, int], end_ns: int | None = None) -> bool:
        """Whether a tick of this clock can have ``tag`` (ns since T0, microstep), in a run that
        ends at ``end_ns``: a rate's ticks are its tick times, at microstep 0, before the end; a
        triggered clock ticks at whatever tag an event brings. A step record at another tag
        was not made by this clock (the coordinator and the replay refuse it)."""
        if self.triggered or self.hz is None:
            return True
        t, microstep = tag
        return (microstep == 0 and t >= 0 and (end_ns is None or t < end_ns)
                and self.tick_time(self.first_tick_at_or_after(t)) == t)

    def __eq__(self, other: object) -> bool:
        return type(self) is type(other) and self.to_ir() == other.to_ir()

    def __hash__(self) -> int:
        return hash(repr(self))


class _Periodic(Clock):
    __slots__ = ("hz_value", "offset", "_rate", "offset_ns", "_step_num", "_step_den")

    def _init_rate(self, owner: str, hz: float, offset: float) -> None:
        self._rate, self.offset_ns = _check_rate(owner, hz, offset)
        self.hz_value = hz
        self.offset = offset
        # t_k = offset + floor(k * 1e9 * q / p) for hz = p/q; plain ints, since Fraction attributes are slow
        self._step_num = NS_PER_S * self._rate.denominator
        self._step_den = self._rate.numerator

    @property
    def hz(self) -> Fraction:  # type: ignore[override]
        """The rate as an exact rational."""
        return self._rate

    @property
    def schedule(self) -> tuple[int, int, int]:
        """``(offset_ns, num, den)`` with ``tick_time(k) == offset_ns + k * num // den``: clocks with
        equal schedules tick at the same times (the inproc backend runs their nodes as one group)."""
        return self.offset_ns, self._step_num, self._step_den

    def tick_time(self, k: int, t0: int = 0) -> int:
        """Time in ns of tick ``k``: ``t0 + offset + floor(k * 1e9 / hz)``, exact, no drift."""
        return t0 + self.offset_ns + (k * self._step_num) // self._step_den

    def first_tick_at_or_after(self, t: int, t0: int = 0) -> int:
        """The smallest ``k`` whose tick time is ``>= t``."""
        rel = t - t0 - self.offset_ns
        if rel <= 0:
            return 0
        # smallest k with floor(k*1e9*q/p) >= rel  <=>  k*1e9*q >= rel*p  (p = _step_den, 1e9*q = _step_num)
        return -(-(rel * self._step_den) // self._step_num)


class Rate(_Periodic):
    """Tick at ``T0 + offset + floor(k * 1e9 / hz)`` ns for k = 0, 1, 2, …, microstep 0."""

    __slots__ = ()

    def __init__(self, hz: float, offset: float = 0.0):
        self._init_rate("Rate", hz, offset)

    def to_ir(self) -> dict:
        return {"Rate": {"hz": self.hz_value, "offset": self.offset}}

    def __repr__(self) -> str:
        return f"Rate(hz={self.hz_value!r}" + (f", offset={self.offset!r})" if self.offset else ")")


class Trigger(Clock):
    """Tick at the tag of each event arriving on the named input ports (no ports: on any input).

    Several triggering events at one tag make one tick.
    """

    __slots__ = ("trigger_ports",)
    triggered = True

    def __init__(self, *ports: str):
        self.trigger_ports = _check_ports("Trigger", ports)

    def to_ir(self) -> dict:
        return {"Trigger": {"ports": list(self.trigger_ports)}}

    def __repr__(self) -> str:
        return f"Trigger({', '.join(map(repr, self.trigger_ports))})"


class Hybrid(_Periodic):
    """Tick on a rate *and* on events at the trigger ports; a coinciding pair is one tick."""

    __slots__ = ("trigger_ports",)
    triggered = True

    def __init__(self, hz: float, trigger: list[str] | tuple[str, ...] | str = (), offset: float = 0.0):
        self._init_rate("Hybrid", hz, offset)
        ports = (trigger,) if isinstance(trigger, str) else tuple(trigger)
        self.trigger_ports = _check_ports("Hybrid", ports)

    def to_ir(self) -> dict:
        return {"Hybrid": {"hz": self.hz_value, "offset": self.offset, "trigger": list(self.trigger_ports)}}

    def __repr__(self) -> str:
        return f"Hybrid(hz={self.hz_value!r}, trigger={list(self.trigger_ports)!r})"


def clock_from_ir(doc: object) -> Clock:
    """Rebuild a clock from its IR form, e.g. ``{"Rate": {"hz": 30}}``. Raises ValueError/ClockError."""
    if not isinstance(doc, dict) or len(doc) != 1:
        raise ValueError(f"a clock must be an object with one key (Rate, Trigger or Hybrid), got {doc!r}")
    (kind, params), = doc.items()
    if not isinstance(params, dict):
        raise ValueError(f"clock {kind}: parameters must be an object, got {params!r}")
    if kind == "Rate":
        return Rate(params.get("hz"), offset=params.get("offset", 0.0))
    if kind == "Trigger":
        return Trigger(*params.get("ports", []))
    if kind == "Hybrid":
        return Hybrid(params.get("hz"), trigger=params.get("trigger", []), offset=params.get("offset", 0.0))
    raise ValueError(f"unknown clock kind {kind!r}; expected Rate, Trigger or Hybrid")
