"""Every status, state and op of the log and the control protocol is spelled once, as its enum's
member (issue 37): no module of ``retriever/``, ``agents/`` or ``benchmarks/`` spells one as a
string where the enum's field is meant. The values are what the log and the wire carry, so a
string that drifts from them compares unequal without a word, where a misspelled member fails
on import.

The rule, over each module's AST. A *field name* is an identifier one of whose words (split at
``_``, singular or plural) is a field of :data:`FIELDS`: ``status``, ``s.status``, ``statuses``,
``end["status"]``, ``end.get("status")``, ``book.state[n]``, or a record class's ``NAME`` (the op
or state a record carries). A string equal to a value of an enum is flagged where it stands for
that enum's field: alone, in a literal tuple, list or set, or as a branch of ``a if c else b``,

- compared with a field name (``==``, ``!=``, ``in``, ``is``; tuples against tuples by position),
  or matched against one (``match status: case "ok"``);
- assigned to a field name (tuples by position), or its default (``def f(status="finished")``);
- a keyword argument named by a field (``f(status="ok")``), or the default of a field's ``get``
  (``end.get("status", "finished")``);
- a dict's value under a field's key (``{"status": "finished"}``), or a key of a dict whose every
  key (two or more) is a value of one enum: a table keyed by that enum;
- for step records, whose status goes by position: an argument of a call that records a step
  (:data:`RECORDING`), a field of a step record's tuple (7 fields or more, not all constants),
  the first of a tick's outcome returned as ``(status, detail)``.

A value spelled where another field is meant (``on_error == "restart"``, the counter
``"late"``, a detail's ``"error"`` key) is not flagged: the name beside the string says which
field it fills, which is why the rule reads names and not values alone. The tests build records
by hand and are not read.
"""

from __future__ import annotations

import ast
from enum import StrEnum
from pathlib import Path

from retriever.backends.zenoh.protocol import DaemonEvent, DaemonOp, DeploymentOp, NodeState, Op, State, Stream
from retriever.log import RunEnd
from retriever.trace import StepStatus

ROOT = Path(__file__).resolve().parents[1]
#: what the check reads: the package, the agents and the benchmarks
SCANNED = ("retriever", "agents", "benchmarks")
#: each enum, by the fields whose values it holds (command.SpawnMode is not here: its values are
#: command-line words, which the fuzzer's hostile command lines spell as such)
FIELDS: dict[type[StrEnum], tuple[str, ...]] = {
    StepStatus: ("status",), RunEnd: ("status",),
    Op: ("op", "NAME"), DeploymentOp: ("op", "NAME"), DaemonOp: ("op", "NAME"), DaemonEvent: ("event", "NAME"),
    State: ("state", "NAME"), NodeState: ("state",),
    Stream: ("stream",),
}
VALUES = {enum: {member.value for member in enum} for enum in FIELDS}
#: calls that take a step record's fields positionally (a status among them)
RECORDING = {"record", "finish_tick", "emit", "StepRecord", "ReportedStep"}


def _words(identifier: str) -> set[str]:
    """The fields ``identifier`` may name: itself (``NAME``), and each of its words in lower case,
    singular and plural (``step_statuses``: step, steps, status, statuses, ...)."""
    words = {identifier}
    for word in identifier.lower().split("_"):
        words |= {word, word.removesuffix("s"), word.removesuffix("es")}
    return words


def _identifier(node: ast.AST) -> str:
    """The name ``node`` reads a value by: ``x``, ``o.x``, ``d["x"]``, ``d.get("x")``; for a
    subscript or ``get`` by another key, the mapping's name (``book.state[n]``: ``state``)."""
    if isinstance(node, ast.Name):
        return node.id
    if isinstance(node, ast.Attribute):
        return node.attr
    if isinstance(node, ast.Subscript):
        key, mapping = node.slice, node.value
    elif isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute) and node.func.attr == "get" and node.args:
        key, mapping = node.args[0], node.func.value
    else:
        return ""
    return key.value if isinstance(key, ast.Constant) and isinstance(key.value, str) else _identifier(mapping)


class _Scan(ast.NodeVisitor):
    """Collects ``(line, value, members)`` for each enum value spelled as a string in a module."""

    def __init__(self) -> None:
        self.found: list[tuple[int, str, list[StrEnum]]] = []

    # -- what is flagged: a literal where one of ``fields`` is meant ----------------------------
    def spelled(self, node: ast.AST | None, fields: set[str], only: type[StrEnum] | None = None) -> None:
        if isinstance(node, ast.Constant) and isinstance(node.value, str):
            members = [enum(node.value) for enum, named in FIELDS.items()
                       if only in (None, enum) and fields & set(named) and node.value in VALUES[enum]]
            if members:
                self.found.append((node.lineno, node.value, members))
        elif isinstance(node, (ast.Tuple, ast.List, ast.Set)):
            for item in node.elts:
                self.spelled(item, fields, only)
        elif isinstance(node, ast.IfExp):
            self.spelled(node.body, fields, only)
            self.spelled(node.orelse, fields, only)

    def paired(self, named: ast.AST, value: ast.AST | None) -> None:
        """``value`` where ``named`` is: tuples element by element, else the whole of ``value``."""
        if (isinstance(named, (ast.Tuple, ast.List)) and isinstance(value, (ast.Tuple, ast.List))
                and len(named.elts) == len(value.elts)):
            for n, v in zip(named.elts, value.elts):
                self.paired(n, v)
        else:
            self.spelled(value, _words(_identifier(named)))

    # -- where a field is meant -----------------------------------------------------------------
    def visit_Compare(self, node: ast.Compare) -> None:
        sides = [node.left, *node.comparators]
        for a in sides:
            for b in sides:
                if a is not b:
                    self.paired(a, b)
        self.generic_visit(node)

    def visit_Assign(self, node: ast.Assign) -> None:
        for target in node.targets:
            self.paired(target, node.value)
        self.generic_visit(node)

    def visit_AnnAssign(self, node: ast.AnnAssign) -> None:
        self.paired(node.target, node.value)
        self.generic_visit(node)

    def visit_arguments(self, node: ast.arguments) -> None:
        positional = [*node.posonlyargs, *node.args]
        for arg, default in [*zip(positional[len(positional) - len(node.defaults):], node.defaults),
                             *zip(node.kwonlyargs, node.kw_defaults)]:
            self.spelled(default, _words(arg.arg))
        self.generic_visit(node)

    def visit_keyword(self, node: ast.keyword) -> None:
        if node.arg is not None:
            self.spelled(node.value, _words(node.arg))
        self.generic_visit(node)

    def visit_Dict(self, node: ast.Dict) -> None:
        for key, value in zip(node.keys, node.values):
            if isinstance(key, ast.Constant) and isinstance(key.value, str):
                self.spelled(value, _words(key.value))
        keys = [k.value if isinstance(k, ast.Constant) else None for k in node.keys]
        for enum, fields in FIELDS.items():
            if len(keys) >= 2 and all(k in VALUES[enum] for k in keys):
                for key in node.keys:
                    self.spelled(key, set(fields), only=enum)
        self.generic_visit(node)

    # -- a step record's status, by position ----------------------------------------------------
    def visit_Match(self, node: ast.Match) -> None:
        """``match status: case "ok": ...``: each value a case matches the subject's field against."""
        fields = _words(_identifier(node.subject))
        patterns = [case.pattern for case in node.cases]
        while patterns:
            pattern = patterns.pop()
            if isinstance(pattern, ast.MatchValue):
                self.spelled(pattern.value, fields)
            elif isinstance(pattern, ast.MatchOr):
                patterns += pattern.patterns
        self.generic_visit(node)

    def visit_Call(self, node: ast.Call) -> None:
        callee = node.func.attr if isinstance(node.func, ast.Attribute) else getattr(node.func, "id", "")
        if (callee == "get" and len(node.args) >= 2 and isinstance(node.args[0], ast.Constant)
                and isinstance(node.args[0].value, str)):  # end.get("status", "finished"): the default
            self.spelled(node.args[1], _words(node.args[0].value))
        if callee in RECORDING:
            for arg in node.args:
                self.spelled(arg, {"status"}, only=StepStatus)
        self.generic_visit(node)

    def visit_Tuple(self, node: ast.Tuple) -> None:
        if len(node.elts) >= 7 and not all(isinstance(item, ast.Constant) for item in node.elts):
            for item in node.elts:
                if isinstance(item, ast.Constant):
                    self.spelled(item, {"status"}, only=StepStatus)
        self.generic_visit(node)

    def visit_Return(self, node: ast.Return) -> None:
        if isinstance(node.value, ast.Tuple) and len(node.value.elts) == 2:
            self.spelled(node.value.elts[0], {"status"}, only=StepStatus)
        self.generic_visit(node)


def spelled_literals(source: str, path: str = "<string>") -> list[str]:
    """Each enum value ``source`` spells as a string where its field is meant, as
    ``path:line: "value" -> Member`` (with every member it may be)."""
    scan = _Scan()
    scan.visit(ast.parse(source, path))
    found: dict[tuple[int, str], list[str]] = {}
    for line, value, members in scan.found:
        named = found.setdefault((line, value), [])
        for member in (f"{type(m).__name__}.{m.name} ({type(m).__module__})" for m in members):
            if member not in named:
                named.append(member)
    return [f"{path}:{line}: {value!r} -> use {' or '.join(named)}" for (line, value), named in sorted(found.items())]


def test_no_status_state_or_op_is_spelled_as_a_string():
    files = sorted(p for top in SCANNED for p in (ROOT / top).rglob("*.py"))
    spelled = [line for path in files
               for line in spelled_literals(path.read_text(encoding="utf-8"), str(path.relative_to(ROOT)))]
    assert spelled == [], "a status, state or op spelled as a string; use its enum's member:\n" + "\n".join(spelled)


def test_the_rule_flags_each_place_a_field_is_meant():
    source = '''
if end.get("status") == "finished" or op in ("start", "stop"): pass
status, error = "interrupted", ""
def close(status="finished"): pass
write(state="ready")
end = {"status": "error"}
levels = {"ok": 1, "late": 2}
record("a", (0, 0), {}, (), "skipped", None, 0)
def outcome(): return "overrun", {}
said = end.get("status", "interrupted")
match msg.op:
    case "grant" | "have": pass
'''
    assert spelled_literals(source) == [
        "<string>:2: 'finished' -> use RunEnd.FINISHED (retriever.log.format)",
        "<string>:2: 'start' -> use Op.START (retriever.backends.zenoh.protocol.to_worker)",
        "<string>:2: 'stop' -> use Op.STOP (retriever.backends.zenoh.protocol.to_worker) or DeploymentOp.STOP "
        "(retriever.backends.zenoh.protocol.deployment)",
        "<string>:3: 'interrupted' -> use RunEnd.INTERRUPTED (retriever.log.format)",
        "<string>:4: 'finished' -> use RunEnd.FINISHED (retriever.log.format)",
        "<string>:5: 'ready' -> use State.READY (retriever.backends.zenoh.protocol.to_coordinator) or NodeState.READY "
        "(retriever.backends.zenoh.protocol.deployment)",
        "<string>:6: 'error' -> use StepStatus.ERROR (retriever.trace) or RunEnd.ERROR (retriever.log.format)",
        "<string>:7: 'late' -> use StepStatus.LATE (retriever.trace)",
        "<string>:7: 'ok' -> use StepStatus.OK (retriever.trace)",
        "<string>:8: 'skipped' -> use StepStatus.SKIPPED (retriever.trace)",
        "<string>:9: 'overrun' -> use StepStatus.OVERRUN (retriever.trace)",
        "<string>:10: 'interrupted' -> use RunEnd.INTERRUPTED (retriever.log.format)",
        "<string>:12: 'grant' -> use Op.GRANT (retriever.backends.zenoh.protocol.to_worker)",
        "<string>:12: 'have' -> use Op.HAVE (retriever.backends.zenoh.protocol.to_worker)",
    ]


def test_a_value_where_another_field_is_meant_is_not_flagged():
    source = '''
if settings.on_error == "restart" or what == "start": pass
COUNTERS = {"late": "events that came late", "restart_skipped": "ticks skipped"}
detail = {"error": text, "on_error": "stop"}
status, error = StepStatus.OK, "error"
'''
    assert spelled_literals(source) == []
