"""A worker process's command line, built and read here only.

    python -m retriever.backends.zenoh.worker SPEC.json NODE                 the node's first process
    python -m retriever.backends.zenoh.worker SPEC.json NODE --join T0 END   a restarted flow's new one
    python -m retriever.backends.zenoh.worker SPEC.json NODE --fresh T0 END  one whose old process died
    python -m retriever.backends.dora.node SPEC.json DORA_ID                 a dora node (backends/dora)

Every host starts a worker with :func:`worker_command`: this machine's (host.py), a worker daemon
(runs.py, which checks the mode a coordinator sends with :func:`parse_mode`), and dora's dataflow
(dataflow.py). T0 and END are nanoseconds, non-negative, as decimal digits.
"""

from __future__ import annotations

import sys
from collections.abc import Sequence
from dataclasses import dataclass

from .protocol import SpawnMode

#: the module a worker process runs
WORKER_MODULE = "retriever.backends.zenoh.worker"
#: the start modes after the node's first process: a restarted flow's, and a lost process's
JOIN, FRESH = SpawnMode.JOIN, SpawnMode.FRESH
#: the most digits of T0 or END (an int64 of nanoseconds)
MAX_DIGITS = 19


@dataclass(frozen=True)
class Mode:
    """How a worker process starts: ``None`` the node's first process; else ``JOIN`` or ``FRESH``
    into the run that started at ``t0`` and ends at ``end`` (ns)."""

    kind: str | None = None
    t0: int = 0
    end: int = 0

    def args(self) -> list[str]:
        """The mode as command-line arguments (and as a spawn request carries it: remote.py)."""
        return [] if self.kind is None else [self.kind, str(self.t0), str(self.end)]


FIRST = Mode()


def mode_args(t0_end: tuple[int, int] | None, fresh: bool = False) -> list[str]:
    """The arguments of a worker joining the run ``t0_end`` (None: its node's first process)."""
    return FIRST.args() if t0_end is None else Mode(FRESH if fresh else JOIN, *map(int, t0_end)).args()


def parse_mode(args: object) -> Mode:
    """The mode from its arguments (a list of text); ValueError for anything else."""
    if args == []:
        return FIRST
    if not (type(args) is list and len(args) == 3 and args[0] in (JOIN, FRESH)
            and all(type(x) is str and x.isascii() and x.isdigit() and len(x) <= MAX_DIGITS
                    for x in args[1:])):  # ASCII: "²" is a digit to isdigit, not to int
        raise ValueError(f"mode {args!r:.60} is not [] nor [{JOIN}|{FRESH}, T0, END] (ns, non-negative)")
    return Mode(args[0], int(args[1]), int(args[2]))


def worker_command(spec_path: str, node: str, mode: Sequence[str] = (), module: str = WORKER_MODULE,
                   python: str | None = None) -> list[str]:
    """The command that starts a worker process for ``node`` of the run whose spec is at
    ``spec_path``: ``python`` (this interpreter unless given) runs ``module`` with them."""
    return [python or sys.executable, "-m", module, str(spec_path), node, *parse_mode(list(mode)).args()]
