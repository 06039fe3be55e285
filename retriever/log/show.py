"""A logged value on one line, as ``retriever log cat`` prints it.

Arrays are what make a value long: a camera frame's repr runs to dozens of lines. Three ways to
show them: ``summary`` (the default: an array of more than :data:`ARRAY_SHOWN_WHOLE` elements as
its dtype, shape and range, or first items), ``brief`` (every array as its dtype and shape, long
reprs cut) and ``full`` (every element).
"""

from __future__ import annotations

import sys
from typing import Any

import numpy as np

from ..codec import UnregisteredValue, dataclass_fields

ARRAY_SHOWN_WHOLE = 16  # elements: a pose, a small matrix, a short action vector
BRIEF_TEXT = 80  # characters of a non-array leaf in brief mode
BRIEF_ITEMS = 8  # items of a list or tuple in brief mode


def show_value(value: Any, arrays: str = "summary") -> str:
    """``value`` on one line, its arrays shown as ``arrays`` says: ``summary``, ``brief`` or ``full``."""
    if isinstance(value, np.ndarray):
        return _array(value, arrays)
    fields = dataclass_fields(value)
    if fields is not None:
        name = f"<{value.path}>" if isinstance(value, UnregisteredValue) else type(value).__name__
        return f"{name}(" + ", ".join(f"{k}={show_value(v, arrays)}" for k, v in fields.items()) + ")"
    if isinstance(value, dict):
        return "{" + ", ".join(f"{k!r}: {show_value(v, arrays)}" for k, v in value.items()) + "}"
    if isinstance(value, (list, tuple)):
        items = value[:BRIEF_ITEMS] if arrays == "brief" else value
        inner = ", ".join(show_value(v, arrays) for v in items)
        if len(items) < len(value):
            inner += f", … {len(value)} in all"
        return f"[{inner}]" if isinstance(value, list) else f"({inner}{',' if len(value) == 1 else ''})"
    text = repr(value)
    return text[:BRIEF_TEXT - 3] + "..." if arrays == "brief" and len(text) > BRIEF_TEXT else text


def _array(value: np.ndarray, arrays: str) -> str:
    kind = f"{value.dtype}[{','.join(map(str, value.shape))}]"
    if arrays == "brief":
        return kind
    if arrays == "full":  # every element, each with the digits that tell it apart (numpy's default keeps 8)
        with np.printoptions(threshold=sys.maxsize, floatmode="unique"):
            return repr(value)
    if value.size <= ARRAY_SHOWN_WHOLE:
        with np.printoptions(floatmode="unique"):
            text = repr(value)  # numbers on one line (numpy breaks rows over lines); text as it is
        return " ".join(text.split()).replace(" ,", ",") if value.dtype.kind in "biufc" else text
    if value.dtype.kind in "iuf":
        return f"{kind} min {value.min().item()!r} max {value.max().item()!r}"
    if value.dtype.kind == "b":
        return f"{kind} {int(value.sum())} true"
    return f"{kind} first {', '.join(map(repr, value.reshape(-1)[:3].tolist()))}, …"
