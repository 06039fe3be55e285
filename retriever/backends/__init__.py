"""Backends by name, and the process-wide default chosen with ``retriever.init(backend=...)``."""

from __future__ import annotations

from ..errors import BackendError
from .base import Backend, NodeStats, Session

_default = "inproc"


def _registry() -> dict[str, Backend]:
    from .dora import DoraBackend
    from .inproc import InprocBackend
    from .zenoh import ZenohBackend

    return {"dora": DoraBackend(), "inproc": InprocBackend(), "zenoh": ZenohBackend()}


def available_backends() -> list[str]:
    """Names of the backends ``pipe.run(backend=...)`` and ``retriever.init`` accept."""
    return sorted(_registry())


#: the seed paper's names of the backends (Listing 4): the local Zenoh runtime is its
#: "multiprocessing", the in-process backend its "in-process"
ALIASES = {"multiprocessing": "zenoh", "in-process": "inproc"}


def canonical(name: str) -> str:
    """A backend's own name for ``name`` (its alias resolved)."""
    return ALIASES.get(name, name)


def _lookup(name: str) -> Backend:
    registry = _registry()
    name = canonical(name)
    if name not in registry:
        raise BackendError(f"unknown backend {name!r}; available: {', '.join(sorted(registry))}\n"
                           f"    hint: use backend=\"inproc\" for deterministic virtual time")
    return registry[name]


def init(backend: str = "inproc") -> None:
    """Set the backend ``pipe.run()`` uses when none is named (the seed's ``retriever.init``)."""
    global _default
    _lookup(backend)
    _default = backend


def default_backend() -> str:
    return _default


def open_backend(name: str, graph, **options) -> Session:
    return _lookup(name).open(graph, **options)


__all__ = ["Backend", "NodeStats", "Session", "available_backends", "default_backend", "init", "open_backend"]
