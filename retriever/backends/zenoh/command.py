"""A worker process's command line, built and read here only.

    python -m retriever.backends.zenoh.worker SPEC.json NODE                 the node's first process
    python -m retriever.backends.zenoh.worker SPEC.json NODE --join T0 END   a restarted flow's new one
    python -m retriever.backends.zenoh.worker SPEC.json NODE --fresh T0 END  one whose old process died
    python -m retriever.backends.zenoh.worker.group SPEC.json NAME [MODE]    the process of a group of flows
    python -m retriever.backends.dora.node SPEC.json DORA_ID                 a dora node (backends/dora)

Every host starts a worker with :func:`worker_command`: this machine's (host.py), a worker daemon
(daemon/runs.py), and dora's dataflow (dataflow.py). Every such process reads its own with
:func:`parse_command` (worker/__init__.py, worker/group.py, dora/node.py), and a worker daemon checks the
mode a coordinator's spawn request carries with :func:`parse_mode` (protocol/daemon.py), before
it is ever a command line. T0 and END are nanoseconds, non-negative, as decimal digits.
"""

from __future__ import annotations

import sys
from collections.abc import Sequence
from dataclasses import dataclass
from enum import StrEnum
from pathlib import Path

#: the module a worker process runs; a group's (several flows in one process: configure(process=));
#: a dora node's (dora starts it: backends/dora/node.py)
WORKER_MODULE = "retriever.backends.zenoh.worker"
GROUP_MODULE = "retriever.backends.zenoh.worker.group"
DORA_NODE_MODULE = "retriever.backends.dora.node"
#: what each module's command line names after the spec, and whether a start mode may follow
NAMED = {WORKER_MODULE: ("NODE", True), GROUP_MODULE: ("NAME", True), DORA_NODE_MODULE: ("DORA_ID", False)}
#: the most digits of T0 or END (an int64 of nanoseconds)
MAX_DIGITS = 19


class SpawnMode(StrEnum):
    """How a worker process joins its run after its node's first process (on the command line,
    and in a daemon's spawn request: protocol/daemon.py)."""

    JOIN = "--join"  # a restarted flow's process, taking over from the old one
    FRESH = "--fresh"  # a flow whose process died, started afresh


JOIN, FRESH = SpawnMode.JOIN, SpawnMode.FRESH


@dataclass(frozen=True)
class StartMode:
    """How a worker process starts: ``kind`` None, its node's first process; else ``JOIN`` or
    ``FRESH`` into the run that started at ``t0`` and ends at ``end`` (ns)."""

    kind: SpawnMode | None = None
    t0: int = 0
    end: int = 0

    def args(self) -> list[str]:
        """The mode as command-line arguments (and as a spawn request carries it: remote.py)."""
        return [] if self.kind is None else [self.kind, str(self.t0), str(self.end)]


FIRST = StartMode()


@dataclass(frozen=True)
class Command:
    """A worker process's command line, read: the run's spec, what the process serves (a node,
    a group's name, a dora id), and how it starts."""

    spec_path: Path
    name: str
    mode: StartMode = FIRST


def mode_args(t0_end: tuple[int, int] | None, fresh: bool = False) -> list[str]:
    """The arguments of a worker joining the run ``t0_end`` (None: its node's first process)."""
    return FIRST.args() if t0_end is None else StartMode(FRESH if fresh else JOIN, *map(int, t0_end)).args()


def parse_mode(args: object) -> StartMode:
    """The mode from its arguments (a list of text); ValueError for anything else."""
    if args == []:
        return FIRST
    if not (type(args) is list and len(args) == 3 and args[0] in (JOIN, FRESH)
            and all(type(x) is str and x.isascii() and x.isdigit() and len(x) <= MAX_DIGITS
                    for x in args[1:])):  # ASCII: "²" is a digit to isdigit, not to int
        raise ValueError(f"mode {args!r:.60} is not [] nor [{JOIN}|{FRESH}, T0, END] (ns, non-negative)")
    return StartMode(SpawnMode(args[0]), int(args[1]), int(args[2]))


def usage(module: str) -> str:
    """The command line ``module`` takes, as its usage line says it."""
    name, takes_mode = NAMED[module]
    return f"python -m {module} SPEC.json {name}" + (f" [{JOIN}|{FRESH} T0 END]" if takes_mode else "")


def parse_command(argv: Sequence[str], module: str = WORKER_MODULE) -> Command:
    """The command line of a process of ``module`` (``argv``: after ``python -m module``), as
    :func:`worker_command` built it. ValueError for any other: the usage line, and what is wrong."""
    name, takes_mode = NAMED[module]
    args = list(argv)
    try:
        if len(args) < 2:
            raise ValueError(f"no {name}" if args else "no SPEC.json")
        if not takes_mode and len(args) > 2:
            raise ValueError(f"unexpected argument(s) {args[2:]!r:.60}")
        mode = parse_mode(args[2:]) if takes_mode else FIRST
    except ValueError as e:
        raise ValueError(f"usage: {usage(module)}: {e}") from None
    return Command(Path(args[0]), args[1], mode)


def worker_command(spec_path: str, node: str, mode: Sequence[str] = (), module: str = WORKER_MODULE,
                   python: str | None = None) -> list[str]:
    """The command that starts a worker process for ``node`` of the run whose spec is at
    ``spec_path``: ``python`` (this interpreter unless given) runs ``module`` with them."""
    return [python or sys.executable, "-m", module, str(spec_path), node, *parse_mode(list(mode)).args()]
