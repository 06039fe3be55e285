"""What a run's workers are told of it: the run's directory, and the import path of its flows."""

from __future__ import annotations

import os
import sys
from pathlib import Path

from ....errors import BackendError
from ....graph import Graph
from ..folders import RUN_FOLDER, private_folder


def run_dir() -> Path:
    """The run's directory: the spec and big events on their way to the
    coordinator. In shared memory when the host has it (no disk I/O for those events)."""
    shm = Path("/dev/shm")
    base = str(shm) if shm.is_dir() and os.access(shm, os.W_OK | os.X_OK) else None
    return private_folder(RUN_FOLDER, base)  # named by pid: a SIGKILLed run's is reaped by the next


def python_path() -> list[str]:
    """The import path the flows came from, for the workers (absolute directories only)."""
    out = []
    for entry in sys.path:
        path = os.path.abspath(entry or ".")
        if os.path.isdir(path) and path not in out:
            out.append(path)
    return out


def main_file(graph: Graph) -> str | None:
    """The ``__main__`` script, when some flow class is defined in it."""
    if not any(type(n.flow).__module__ == "__main__" for n in graph.nodes.values()):
        return None
    path = getattr(sys.modules.get("__main__"), "__file__", None)
    if path is None:
        raise BackendError("a flow class is defined in an interactive __main__, which worker processes cannot "
                           "import\n    hint: move the flow classes to a module or a script file")
    return os.path.abspath(path)
