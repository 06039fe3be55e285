"""The stack of pipelines entered with ``with Pipeline(...)``; flows join the innermost."""

from __future__ import annotations

from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from .pipeline import Pipeline

_active: list["Pipeline"] = []


def current_pipeline() -> "Pipeline | None":
    return _active[-1] if _active else None


def push(pipe: "Pipeline") -> None:
    _active.append(pipe)


def pop(pipe: "Pipeline") -> None:
    if _active and _active[-1] is pipe:
        _active.pop()
    elif pipe in _active:
        _active.remove(pipe)
