"""Placement: which worker runs each node of an IR, for ``retriever deploy`` (docs/deploy.md).

A *worker* here is a worker daemon (``retriever worker --name NAME``, backends/zenoh/daemon/), as
the placement file and ``retriever workers`` name it; not the process that serves one node on
it (backends/zenoh/worker/), which the daemon starts once the node is placed.

A placement file pins nodes to workers by name, or asks for workers with labels::

    [nodes]
    camera = "arm-pc"                                    # on the worker named arm-pc
    policy = { labels = ["gpu"] }                        # on a worker that has every one of these labels
    planner = { worker = "gpu-box", labels = ["gpu"] }   # on gpu-box, which must have these labels
    detector = { process = "perception" }                # in one process with the other flows of that name
    # nodes not listed go to any worker, spread by load

A *process* name groups flows into one worker process, as ``configure(process=NAME)`` does (the
file's name wins over the flow's; the coordinator makes the groups of both, coordinator/spec.py,
and hands them to :func:`place` and :func:`move`): a group is placed as one unit, on one worker,
which must meet every member's constraint; members pinned to different workers are refused,
naming them.

:func:`load_placement` reads and validates a file; :func:`place` maps an IR's nodes onto the
workers that are up, :func:`move` the nodes of a lost worker onto those still up: both by one rule
(:func:`assign`, which keeps each group of flows together), whose result one check validates
(:func:`check_assignment`). Each reports every problem at once, in one :class:`PlacementError`,
before anything starts. Pure: the only I/O is :func:`load_placement` reading its file.
"""

from __future__ import annotations

import difflib
import re
import shlex
import tomllib
from collections import Counter
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path

from .errors import PlacementError, Problem
from .ir import NODE_ID

#: how a hint tells the user to start a worker daemon (issue 18); labels are added as ``--labels A,B``
WORKER_COMMAND = "retriever-worker --name NAME"
#: a message lists at most this many names: an IR, a placement or the workers up may be large
LISTED_NAMES = 20
#: a name in a message is cut after this many characters (of its repr)
SHOWN_CHARS = 60
#: the keys of a node's table
ENTRY_KEYS = ("worker", "labels", "process")
#: the hint of a document that is no placement at all
EXAMPLE_HINT = ('a placement is a [nodes] table: camera = "arm-pc" pins a node, policy = { labels = ["gpu"] } '
                'asks for labels (see deploy/placement.example.toml)')
#: what TOML calls the values a placement document may hold in the wrong place
_TOML_KINDS = {dict: "a table", list: "an array", int: "an integer", float: "a float", bool: "a boolean"}
_ENTRY_FORMS = ('a worker name ("arm-pc") or a table ({ labels = ["gpu"] } or { process = "NAME" }, optionally '
                 'with worker = "NAME")')


@dataclass(frozen=True)
class Constraint:
    """Where one node may run: on the worker named ``worker`` if set, which must have every label in ``labels``."""

    worker: str | None = None
    labels: frozenset[str] = frozenset()


@dataclass(frozen=True)
class Placement:
    """A validated placement: a constraint per listed node (by node id); other nodes are placed by load."""

    nodes: Mapping[str, Constraint]
    source: str = "<memory>"
    #: the process name given to a node (``process = "NAME"``): the nodes of one name share a process
    processes: Mapping[str, str] = field(default_factory=dict)


#: the constraint of a node a placement does not list: any worker up
ANYWHERE = Constraint()


@dataclass(frozen=True)
class LiveDaemon:
    """A worker daemon that is up, as placement weighs it: its name (unique among the workers up), its
    labels, how many nodes it already runs (its load), and the host it runs on, if known. (What a
    daemon says of itself when asked is daemon/listing.py's DaemonInfo; deploy/book.py's placement_target
    makes this of it.)"""

    name: str
    labels: frozenset[str] = frozenset()
    nodes: int = 0
    host: str | None = None


# ---------------------------------------------------------------------------------------------
# Reading a placement file
# ---------------------------------------------------------------------------------------------
def load_placement(path: str | Path) -> Placement:
    """A placement from its TOML file. Anything wrong (unreadable, not TOML, not a placement) raises
    one PlacementError naming the file, with tomllib's line and column for a syntax error."""
    source = str(path)
    try:
        text = Path(path).read_text(encoding="utf-8")
    except OSError as e:
        raise PlacementError(source, [Problem(f"cannot read the file: {e.strerror or e}")]) from None
    except UnicodeDecodeError:
        raise PlacementError(source, [Problem("not a text file (expected UTF-8 TOML)")]) from None
    try:
        doc = tomllib.loads(text)
    except tomllib.TOMLDecodeError as e:
        raise PlacementError(source, [Problem(f"not valid TOML: {e}", EXAMPLE_HINT)]) from None
    except RecursionError:
        raise PlacementError(source, [Problem("not a placement: it nests arrays or tables deeper than Python's "
                                              "recursion limit", EXAMPLE_HINT)]) from None
    return parse_placement(doc, source)


def parse_placement(doc: object, source: str = "<memory>") -> Placement:
    """A placement from a parsed document (a TOML file's tables). Validates all of it and raises one
    PlacementError listing every problem; only a ``[nodes]`` table of node = worker or table is accepted."""
    if not isinstance(doc, dict):
        raise PlacementError(source, [Problem(f"expected a document with a [nodes] table, got {_show(doc)}")])
    problems = [Problem(f"unknown top-level key {_show(key)}", "a placement has only a [nodes] table")
                for key in doc if key != "nodes"]
    table = doc.get("nodes", {})
    if not isinstance(table, dict):
        problems.append(Problem(f"[nodes]: expected a table of node = worker, got {_show(table)}", EXAMPLE_HINT))
        table = {}
    nodes, processes = {}, {}
    for node, value in table.items():
        entry = _entry(node, value, problems)
        if entry is not None:
            constraint, process = entry
            if constraint != ANYWHERE:
                nodes[node] = constraint
            if process is not None:
                processes[node] = process
    if problems:
        raise PlacementError(source, problems)
    return Placement(nodes, source, processes)


def _entry(node: object, value: object, problems: list[Problem]) -> tuple[Constraint, str | None] | None:
    """One ``[nodes]`` entry as its Constraint and process name, or None after adding its problems."""
    if not isinstance(node, str):
        problems.append(Problem(f"[nodes] has a key that is {_show(node)}; a node name is a string"))
        return None
    where = f"[nodes] {_show(node)}"
    if isinstance(value, str):
        if value:
            return Constraint(worker=value), None
        problems.append(Problem(f"{where}: the worker name is empty", "name a worker that is up, or remove the line"))
        return None
    if not isinstance(value, dict):
        problems.append(Problem(f"{where}: expected {_ENTRY_FORMS}, got {_show(value)}"))
        return None
    before = len(problems)
    problems += [Problem(f"{where}: unknown key {_show(key)}", 'a node\'s table has only worker = "NAME", '
                         'labels = ["LABEL", ...] and process = "NAME"') for key in value if key not in ENTRY_KEYS]
    if not any(key in value for key in ENTRY_KEYS):
        problems.append(Problem(f"{where}: says none of worker, labels and process", f"write {_ENTRY_FORMS}"))
    worker = value.get("worker")
    if "worker" in value and not (isinstance(worker, str) and worker):
        problems.append(Problem(f"{where}: worker: expected a worker name (a non-empty string), got {_show(worker)}"))
    labels = _labels(where, value["labels"], problems) if "labels" in value else frozenset()
    process = _process(where, value["process"], problems) if "process" in value else None
    return (Constraint(worker, labels), process) if len(problems) == before else None


def _process(where: str, name: object, problems: list[Problem]) -> str | None:
    """A node's ``process``: a name as configure(process=) takes it (problem added otherwise)."""
    if isinstance(name, str) and re.fullmatch(NODE_ID, name):
        return name
    problems.append(Problem(f"{where}: process: expected a process name (letters, digits, _ and -, not starting "
                            f"with a digit or -), got {_show(name)}",
                            'write process = "perception": the flows of one name share a process'))
    return None


def _labels(where: str, labels: object, problems: list[Problem]) -> frozenset[str]:
    """A node's ``labels``: a non-empty list of non-empty strings (problems added otherwise)."""
    if isinstance(labels, str):
        problems.append(Problem(f"{where}: labels: expected a list, got the string {_show(labels)}",
                                f"write labels = [{_show(labels)}]"))
    elif not isinstance(labels, list) or not labels:
        problems.append(Problem(f"{where}: labels: expected a non-empty list of labels, got {_show(labels)}",
                                'write labels = ["gpu"], or leave labels out'))
    else:
        bad = next((i for i, label in enumerate(labels) if not (isinstance(label, str) and label)), None)
        if bad is None:
            return frozenset(labels)
        problems.append(Problem(f"{where}: labels[{bad}]: expected a label (a non-empty string), "
                                f"got {_show(labels[bad])}"))
    return frozenset()


# ---------------------------------------------------------------------------------------------
# Placing nodes on workers
# ---------------------------------------------------------------------------------------------
#: groups of flows that share a process: name -> its nodes (the run spec's ``groups``)
Groups = Mapping[str, Sequence[str]]


def place(node_ids: Iterable[str], placement: Placement | None, workers: Sequence[LiveDaemon],
          groups: Groups | None = None) -> dict[str, str]:
    """Each node's worker, for a deployment's start: node id -> worker name, in the order of ``node_ids``;
    ``groups``: the flows that share a process, each group on one worker.

    The placement and the workers up are checked first: a placement that cannot be met raises one
    PlacementError listing every problem, and nothing is placed. Then :func:`assign` decides, and
    :func:`check_assignment` checks what it decided (as for a move: :func:`move`).
    """
    nodes = list(dict.fromkeys(node_ids))
    rules = dict(placement.nodes) if placement is not None else {}
    source = placement.source if placement is not None else None
    named = [*rules, *(n for n in (placement.processes if placement is not None else {}) if n not in rules)]
    problems = (_unknown_nodes(named, nodes) + _worker_problems(rules, workers, source, bool(nodes))
                + _group_problems(nodes, groups, rules, workers))
    if problems:
        raise PlacementError(source, problems)
    chosen = assign(nodes, rules, workers, groups)
    check_assignment(chosen, rules, workers, source, groups)
    return chosen


def move(node_ids: Iterable[str], placement: Placement | None, workers: Sequence[LiveDaemon],
         groups: Groups | None = None) -> dict[str, str] | None:
    """Where the nodes of a lost worker start afresh: node id -> worker name among ``workers`` (those
    still up, each with the nodes it runs as its load), by the rule of the first placement
    (:func:`assign`: a group's members together); None when some node has nowhere to go."""
    nodes = list(dict.fromkeys(node_ids))
    rules = dict(placement.nodes) if placement is not None else {}
    chosen = assign(nodes, rules, workers, groups)
    if any(name is None for name in chosen.values()):
        return None
    check_assignment(chosen, rules, workers, placement.source if placement is not None else None, groups)
    return chosen


def assign(nodes: Sequence[str], rules: Mapping[str, Constraint], workers: Sequence[LiveDaemon],
           groups: Groups | None = None) -> dict[str, str | None]:
    """The one placement rule, for a start and for a move: node id -> worker name, or None where no
    worker up meets the node's constraint.

    A unit is a node, or the nodes of ``nodes`` in one group (which share a process): it goes to
    one worker, which must meet the constraint of each of its nodes. A pinned unit goes to its
    worker; a unit with labels to the least-loaded worker that has them all; any other unit to
    the least-loaded worker. A worker's load is the nodes it already runs plus those assigned so
    far; ties go to the first name. Pins go first, then the other units, fewest eligible workers
    first (so a unit with labels goes before one any worker may run), ties by node id. Pure and
    deterministic: which worker a node gets depends on neither the order of ``nodes`` nor that
    of ``workers``.
    """
    units = _units(nodes, groups)
    joined = {unit: _joined(unit, rules) for unit in units}
    eligible = {unit: _eligible(joined[unit], workers) if joined[unit] is not None else [] for unit in units}
    load = {w.name: w.nodes for w in workers}
    chosen: dict[str, str | None] = {}
    pinned = {unit: joined[unit] is None or joined[unit].worker is not None for unit in units}
    for unit in sorted(units, key=lambda u: (not pinned[u], len(eligible[u]), u[0])):
        name = min(eligible[unit], key=lambda w: (load[w], w), default=None)
        chosen.update(dict.fromkeys(unit, name))
        if name is not None:
            load[name] += len(unit)
    return {node: chosen[node] for node in nodes}


def check_assignment(chosen: Mapping[str, str], rules: Mapping[str, Constraint], workers: Sequence[LiveDaemon],
                     source: str | None = None, groups: Groups | None = None) -> None:
    """The one check of what :func:`assign` decided: every node on a worker that is up and meets its
    constraint, every group on one worker. A failure is a bug of the rule, raised as one
    PlacementError naming each node."""
    bug = "this is a bug in Retriever's placement: please report it"
    problems = [Problem(f"node {_show(node)} was assigned to worker {_show(name)}, which is not up or does not "
                        "meet its constraint", bug)
                for node, name in chosen.items() if name not in _eligible(rules.get(node, ANYWHERE), workers)]
    problems += [Problem(f"the nodes {_names(unit)}, which share a process, were assigned to workers "
                         f"{_names(sorted({chosen[n] for n in unit}))}", bug)
                 for unit in _units(list(chosen), groups) if len({chosen[n] for n in unit}) > 1]
    if problems:
        raise PlacementError(source, problems)


def _units(nodes: Sequence[str], groups: Groups | None) -> list[tuple[str, ...]]:
    """``nodes`` as the units placement moves: each group's members among them (sorted), and
    each other node alone."""
    units, grouped = [], set()
    for members in (groups or {}).values():
        unit = tuple(sorted(set(members) & set(nodes)))
        if unit:
            units.append(unit)
            grouped.update(unit)
    return units + [(node,) for node in nodes if node not in grouped]


def _joined(unit: tuple[str, ...], rules: Mapping[str, Constraint]) -> Constraint | None:
    """Where every node of ``unit`` may run at once, or None when their pins differ."""
    constraints = [rules.get(node, ANYWHERE) for node in unit]
    pins = {c.worker for c in constraints if c.worker is not None}
    if len(pins) > 1:
        return None
    return Constraint(next(iter(pins), None), frozenset().union(*(c.labels for c in constraints)))


def _group_problems(nodes: Sequence[str], groups: Groups | None, rules: Mapping[str, Constraint],
                    workers: Sequence[LiveDaemon]) -> list[Problem]:
    """A problem for each group whose members no one worker may run together, though each alone
    could run somewhere (what one member cannot meet alone is that member's problem)."""
    fix = ("a group's flows run in one process, on one worker: pin them to one worker (or none), or give "
           "the ones that must run elsewhere another process name (configure(process=), or process = \"NAME\" "
           "in [nodes]); a flow with no process name runs in a process of its own")
    problems = []
    for name, members in sorted((groups or {}).items()):
        unit = tuple(sorted(set(members) & set(nodes)))
        if len(unit) < 2:
            continue
        pins = {n: rules[n].worker for n in unit if n in rules and rules[n].worker is not None}
        if len(set(pins.values())) > 1:
            where = ", ".join(f"{_show(n)} on {_show(w)}" for n, w in sorted(pins.items()))
            problems.append(Problem(f"process {_show(name)}: its flows {_names(unit)} share one process, on one "
                                    f"worker, and are pinned to different workers ({where})", fix))
        elif all(_eligible(rules.get(n, ANYWHERE), workers) for n in unit) and not _eligible(_joined(unit, rules),
                                                                                             workers):
            problems.append(Problem(f"process {_show(name)}: its flows {_names(unit)} share one process, on one "
                                    f"worker, and no worker up meets all their constraints together "
                                    f"({_constraints_of(unit, rules)})", fix))
    return problems


def _constraints_of(unit: tuple[str, ...], rules: Mapping[str, Constraint]) -> str:
    """What each node of ``unit`` that has a constraint asks for, for a message."""
    asks = []
    for node in unit:
        c = rules.get(node, ANYWHERE)
        wants = ([f"worker {_show(c.worker)}"] if c.worker else []) + \
            ([f"label(s) {_names(sorted(c.labels))}"] if c.labels else [])
        if wants:
            asks.append(f"{_show(node)} wants {' and '.join(wants)}")
    return _cut(asks, "; ")


def _eligible(constraint: Constraint, workers: Sequence[LiveDaemon]) -> list[str]:
    """The names of the workers up that may run a node under ``constraint``."""
    return [w.name for w in workers if constraint.worker in (None, w.name) and constraint.labels <= w.labels]


def _unknown_nodes(rules: Iterable[str], nodes: list[str]) -> list[Problem]:
    """A problem for each node the placement names (``rules``) that the IR does not have."""
    problems, known = [], set(nodes)
    for name in rules:
        if name not in known:
            close = difflib.get_close_matches(name, nodes, n=1)
            hint = f"did you mean {_show(close[0])}?" if close else "use the IR's node ids, or remove the line"
            has = f"its nodes: {_names(nodes)}" if nodes else "it has no nodes"
            problems.append(Problem(f"[nodes] {_show(name)}: the IR has no such node ({has})", hint))
    return problems


def _worker_problems(rules: Mapping[str, Constraint], workers: Sequence[LiveDaemon], source: str | None,
                     has_nodes: bool) -> list[Problem]:
    """Problems with the workers up: none at all, two of one name, pins and labels they cannot meet."""
    if not workers:
        return [Problem("no worker is up", f"start one on each machine that should run nodes: {WORKER_COMMAND} "
                        "[--labels A,B], in this deployment's namespace")] if has_nodes else []
    problems = _duplicate_names(workers)
    up = {w.name: w for w in workers}
    for node, constraint in rules.items():
        if constraint.worker is None:
            problems += _missing_labels(node, constraint.labels, workers, source)
        elif constraint.worker not in up:
            problems.append(_not_up(node, constraint.worker, up))
        elif not constraint.labels <= up[constraint.worker].labels:
            problems.append(_pinned_without_labels(node, constraint, up[constraint.worker]))
    return problems


def _duplicate_names(workers: Sequence[LiveDaemon]) -> list[Problem]:
    """A problem for each name that more than one worker up has: a pin to it would be ambiguous."""
    counts = Counter(w.name for w in workers)
    return [Problem(f"{count} workers are up under the name {_show(name)} (hosts: "
                    f"{_cut(_show(w.host) if w.host else 'unknown' for w in workers if w.name == name)})",
                    "give each worker its own --name") for name, count in sorted(counts.items()) if count > 1]


def _not_up(node: str, worker: str, up: Mapping[str, LiveDaemon]) -> Problem:
    close = difflib.get_close_matches(worker, sorted(up), n=1)
    hint = (f"did you mean {_show(close[0])}? " if close else "") + \
        f"Start it ({WORKER_COMMAND.replace('NAME', _arg(worker))}), or pin {_show(node)} to a worker that is up"
    return Problem(f"[nodes] {_show(node)} is pinned to worker {_show(worker)}, which is not up "
                   f"(workers up: {_names(sorted(up))})", hint)


def _pinned_without_labels(node: str, constraint: Constraint, worker: LiveDaemon) -> Problem:
    missing = sorted(constraint.labels - worker.labels)
    return Problem(f"[nodes] {_show(node)} is pinned to worker {_show(worker.name)}, which lacks the label(s) "
                   f"{_names(missing)} that {_show(node)} needs (it has {_labels_of(worker)})",
                   f"start {_show(worker.name)} with {_label_flags(constraint.labels)}, or drop worker or labels "
                   f"from the entry of {_show(node)}")


def _missing_labels(node: str, labels: frozenset[str], workers: Sequence[LiveDaemon],
                    source: str | None) -> list[Problem]:
    if any(labels <= w.labels for w in workers):
        return []
    has = _cut((f"{_show(w.name)} has {_labels_of(w)}" for w in sorted(workers, key=lambda w: w.name)), "; ")
    return [Problem(f"[nodes] {_show(node)} needs the label(s) {_names(sorted(labels))}, and no worker up has "
                    f"all of them ({has})",
                    f"start a worker with them ({WORKER_COMMAND} {_label_flags(labels)}), or change the labels "
                    f"of {_show(node)} in {source}")]


def _labels_of(worker: LiveDaemon) -> str:
    return _names(sorted(worker.labels)) if worker.labels else "no labels"


# ---------------------------------------------------------------------------------------------
# Message helpers
# ---------------------------------------------------------------------------------------------
def _show(value: object) -> str:
    """A value for a message: a string quoted and escaped (no control character reaches a terminal)
    and cut when long; anything else by its type only (it may be huge, or nested deeply)."""
    if isinstance(value, str):
        text = repr(value)
        return text if len(text) <= SHOWN_CHARS else text[:SHOWN_CHARS] + "…"
    return _TOML_KINDS.get(type(value), f"a value of type {type(value).__name__}")


def _names(names: Iterable[str]) -> str:
    """Names for a message, each quoted by :func:`_show`, comma-separated, cut after LISTED_NAMES."""
    return _cut(_show(name) for name in names)


def _cut(texts: Iterable[str], sep: str = ", ") -> str:
    """Texts already fit for a message, joined by ``sep``, cut after LISTED_NAMES."""
    texts = list(texts)
    more = len(texts) - LISTED_NAMES
    return sep.join(texts[:LISTED_NAMES]) + (f"{sep}… ({more} more)" if more > 0 else "")


def _arg(text: str) -> str:
    """A name as a shell argument in a hint's command; a name a shell cannot take as typed is shown quoted."""
    return shlex.quote(text) if text.isprintable() and len(text) <= SHOWN_CHARS else _show(text)


def _label_flags(labels: Iterable[str]) -> str:
    """The worker command's option that gives it ``labels``."""
    return f"--labels {_arg(','.join(sorted(labels)))}"
