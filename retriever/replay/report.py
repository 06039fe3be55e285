"""What a replay finds: per node, what it re-executed and how it compared; each step whose replay
differs from the log (a :class:`Divergence`); and where two values differ, in words."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ..time import format_tag
from ..trace import Trace

MAX_DIVERGENCES_KEPT = 20


@dataclass
class Divergence:
    """One step whose replay differs from the log."""

    node: str
    tag: tuple[int, int]
    what: str  # "value", "inputs", "status", "outputs", "error", "tick" (a record at no tick of its clock)
    port: str | None
    logged: Any
    replayed: Any

    def __str__(self) -> str:
        where = f"{self.node}.{self.port}" if self.port else self.node
        text = (f"{where} at tick {format_tag(self.tag)}: {self.what} differs\n"
                f"      logged:   {_short(self.logged)}\n"
                f"      replayed: {_short(self.replayed)}")
        if self.what == "value":
            text += "".join(f"\n      {line}" for line in explain_difference(self.logged, self.replayed))
        return text


@dataclass
class NodeReplay:
    steps: int = 0  # logged steps of this node
    replayed: int = 0  # of those, re-executed (non-sources)
    identical: int = 0
    divergent: int = 0
    cut: int = 0  # re-executed, not compared: a log cut short lost their outputs (recovered, salvaged)
    lost: int = 0  # re-executed, not compared: their outputs died unpublished with their process (a fault)
    from_log: bool = False  # not re-executed: a source, or a flow configured with replay="log"


@dataclass
class ReplayReport:
    nodes: dict[str, NodeReplay] = field(default_factory=dict)
    divergences: list[Divergence] = field(default_factory=list)  # the first MAX_DIVERGENCES_KEPT
    divergent_steps: int = 0
    code_changes: list[str] = field(default_factory=list)  # flow modules whose file differs from the run's
    #: with ``replay(..., keep_trace=True)``: the run as replayed: every step record as logged (the
    #: replay checks the ids it names), the outputs of each re-executed step as the replay computed
    #: them, the others' from the log
    trace: Trace | None = field(default=None, repr=False)

    @property
    def identical(self) -> bool:
        return self.divergent_steps == 0

    @property
    def steps_replayed(self) -> int:
        return sum(n.replayed for n in self.nodes.values())


def _short(value: Any, limit: int = 300) -> str:
    # every float as the shortest text that reads back to it: two values that differ never look alike
    with np.printoptions(floatmode="unique"):
        text = repr(value)
    return text if len(text) <= limit else text[:limit] + f"... ({len(text)} chars)"


def explain_difference(logged: Any, replayed: Any) -> list[str]:
    """Where two differing values differ, in words: the path to the first differing part (a
    dataclass field, dict key or list item), and for arrays their shapes and dtypes, how many
    elements differ and the largest difference (absolute and relative), values in full."""
    found = _first_difference(logged, replayed, "")
    if found is None:  # equal as values, different as bytes: e.g. 1 vs 1.0, or a list vs a tuple
        return [f"as values they are equal; their encodings differ ({type(logged).__name__} vs "
                f"{type(replayed).__name__})"]
    path, a, b = found
    at = f"at {path}: " if path else ""
    if isinstance(a, np.ndarray) and isinstance(b, np.ndarray):
        first, *rest = _array_difference(a, b)
        return [at + first, *rest]
    if type(a) is not type(b):
        return [f"{at}logged a {type(a).__name__}, replayed a {type(b).__name__}"]
    lines = [f"{at}logged {_short(a)}, replayed {_short(b)}"] if path else []
    if isinstance(a, (float, np.floating)) and np.isfinite(a) and np.isfinite(b):
        lines.append(f"difference: absolute {abs(float(b) - float(a))!r}{_relative(float(a), float(b))}")
    return lines


def _first_difference(a: Any, b: Any, path: str) -> tuple[str, Any, Any] | None:
    if type(a) is not type(b):
        return (path, a, b)
    if isinstance(a, np.ndarray):
        same = a.shape == b.shape and a.dtype == b.dtype and np.array_equal(a, b, equal_nan=a.dtype.kind in "fc")
        return None if same else (path, a, b)
    if dataclasses.is_dataclass(a):
        fields = [f.name for f in dataclasses.fields(a)]
        return next((d for name in fields
                     if (d := _first_difference(getattr(a, name), getattr(b, name), f"{path}.{name}"))), None)
    if isinstance(a, dict):
        for key in list(a) + [k for k in b if k not in a]:
            if key not in a or key not in b:
                return (f"{path}[{key!r}]", a.get(key, "<absent>"), b.get(key, "<absent>"))
            if (d := _first_difference(a[key], b[key], f"{path}[{key!r}]")) is not None:
                return d
        return None
    if isinstance(a, (list, tuple)):
        if len(a) != len(b):
            return (path, a, b)
        return next((d for i, (x, y) in enumerate(zip(a, b)) if (d := _first_difference(x, y, f"{path}[{i}]"))), None)
    if isinstance(a, float) and a != a and b != b:  # NaN: the same value to the log
        return None
    return None if a == b else (path, a, b)


def _array_difference(a: np.ndarray, b: np.ndarray) -> list[str]:
    if a.shape != b.shape or a.dtype != b.dtype:
        return [f"logged {a.dtype} {a.shape}, replayed {b.dtype} {b.shape}"]
    differs = a != b
    if a.dtype.kind in "fc":
        differs &= ~(np.isnan(a) & np.isnan(b))
    count = int(np.count_nonzero(differs))
    head = f"{a.dtype} {a.shape}: {count} of {a.size} element{'s' if a.size != 1 else ''} differ"
    if a.dtype.kind not in "iufc":
        first = tuple(int(i) for i in np.argwhere(differs)[0])
        return [f"{head}; the first at {list(first)}: logged {a[first]!r}, replayed {b[first]!r}"]
    with np.errstate(invalid="ignore", over="ignore"):
        gap = np.where(differs, np.abs(b.astype(np.complex128 if a.dtype.kind == "c" else np.float64)
                                       - a.astype(np.complex128 if a.dtype.kind == "c" else np.float64)), 0)
    gap = np.where(np.isnan(gap), np.inf, gap)  # a NaN on one side only is the largest difference
    where = tuple(int(i) for i in np.unravel_index(int(np.argmax(gap)), a.shape))
    x, y = a[where].item(), b[where].item()
    return [head, f"largest difference at {list(where)}: logged {x!r}, replayed {y!r} "
                  f"(absolute {abs(y - x)!r}{_relative(x, y)})"]


def _relative(logged: Any, replayed: Any) -> str:
    return f", relative {abs(replayed - logged) / abs(logged)!r}" if logged else ""
