"""The stack of pipelines entered with ``with Pipeline(...)``; flows join the innermost."""

from __future__ import annotations

from typing import Any, Protocol


class OpenPipeline(Protocol):
    """What a flow asks of the pipeline it is declared in (``Pipeline`` is one; it sits layers above)."""

    def add(self, flow: Any) -> Any: ...

    def connect(self, src: Any, dst: Any, **options: Any) -> Any: ...


_active: list[OpenPipeline] = []


def current_pipeline() -> OpenPipeline | None:
    return _active[-1] if _active else None


def push(pipe: OpenPipeline) -> None:
    _active.append(pipe)


def pop(pipe: OpenPipeline) -> None:
    if _active and _active[-1] is pipe:
        _active.pop()
    elif pipe in _active:
        _active.remove(pipe)
