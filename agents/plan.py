"""Plan chunks: the planner's skill programs, parsed, checked and spliced (paper Appendix E-c..e, E-i).

A program is a list of lines in the paper's format::

    OpenDrawer(TL-H) -> InspectDrawer(TL)
    IF at(spice, TL) = yes THEN Pick(spice) -> Season(food) -> CloseDrawer(TL-H) -> Done() ELSE CloseDrawer(TL-H)

A line is a chain of skills joined by ``->``, or one ``IF <predicate> = yes|no THEN <chain> [ELSE
<chain>]``. Skills come from the task's closed vocabulary (a planner that names anything else is
refused, as the paper's prompt rules demand); ``Done()`` ends the task. The bag task's programs
read ``OpenBag(bag) -> InspectBag(bag)``, ``IF in(target, bag) = yes THEN Pick(target) ->
Extract(target) -> Done() ELSE Done()``. Parsing never evaluates anything:
a plan is text from a model, so it is data until checked.
"""

from __future__ import annotations

import re
from dataclasses import dataclass

DRAWERS = ("TL", "TR", "BL", "BR")
HANDLES = tuple(f"{d}-H" for d in DRAWERS)
TASKS = ("drawers", "bag")

# each task's closed skill vocabulary (skill -> the arguments it accepts) and predicates
# (name -> the values of its two arguments)
VOCABULARIES: dict[str, dict[str, tuple[str, ...]]] = {
    "drawers": {
        "OpenDrawer": HANDLES,
        "InspectDrawer": DRAWERS,
        "CloseDrawer": HANDLES,
        "Pick": ("spice",),
        "Season": ("food",),
        "PlaceBack": ("spice",),
        "Done": ("",),
    },
    "bag": {
        "OpenBag": ("bag",),
        "InspectBag": ("bag",),
        "Pick": ("target",),
        "Extract": ("target",),
        "Done": ("",),
    },
}
PREDICATES: dict[str, dict[str, tuple[tuple[str, ...], tuple[str, ...]]]] = {
    "drawers": {"at": (("spice",), DRAWERS)},
    "bag": {"in": (("target",), ("bag",))},
}
MAX_LINES = 32
MAX_LINE = 400


class PlanError(ValueError):
    """A plan that is not a program of the closed vocabulary."""


@dataclass(frozen=True)
class Skill:
    name: str
    arg: str

    def __str__(self) -> str:
        return f"{self.name}({self.arg})"


@dataclass(frozen=True)
class Branch:
    predicate: str                  # "at(spice, TL)"
    value: str                      # "yes" | "no": the THEN side is taken when the belief says this
    then: tuple
    otherwise: tuple

    def __str__(self) -> str:
        text = f"IF {self.predicate} = {self.value} THEN {_chain(self.then)}"
        return text + (f" ELSE {_chain(self.otherwise)}" if self.otherwise else "")


Node = Skill | Branch
_SKILL = re.compile(r"^\s*([A-Za-z]+)\(\s*([A-Za-z0-9_\-]*)\s*\)\s*$")
_BRANCH = re.compile(r"^\s*IF\s+(.+?)\s*=\s*(yes|no)\s+THEN\s+(.+?)(?:\s+ELSE\s+(.+))?\s*$")
_PREDICATE = re.compile(r"^\s*([a-z_]+)\(\s*([A-Za-z0-9_\-]+)\s*,\s*([A-Za-z0-9_\-]+)\s*\)\s*$")


def _chain(skills: tuple) -> str:
    return " -> ".join(str(s) for s in skills)


def _task(task: str) -> str:
    if task not in TASKS:
        raise PlanError(f"unknown task {task!r}: the tasks are {', '.join(TASKS)}")
    return task


def parse_skill(text: str, task: str = "drawers") -> Skill:
    """``"Pick(spice)"`` → ``Skill("Pick", "spice")``, from the task's vocabulary only."""
    vocabulary = VOCABULARIES[_task(task)]
    m = _SKILL.match(text) if isinstance(text, str) else None
    if m is None:
        raise PlanError(f"{str(text).strip()!r} is not a skill call such as {next(iter(vocabulary))}("
                        f"{next(iter(vocabulary.values()))[0]})")
    name, arg = m.groups()
    if name not in vocabulary:
        raise PlanError(f"unknown skill {name!r}; the {task} vocabulary is {', '.join(vocabulary)}")
    if arg not in vocabulary[name]:
        allowed = ", ".join(repr(a) for a in vocabulary[name])
        raise PlanError(f"{name}({arg}): {name} takes one of {allowed}")
    return Skill(name, arg)


def parse_predicate(text: str, task: str = "drawers") -> str:
    """``"at(spice,TL)"`` in its canonical spelling ``"at(spice, TL)"``."""
    predicates = PREDICATES[_task(task)]
    m = _PREDICATE.match(text)
    if m is None or m.group(1) not in predicates:
        example = {"drawers": "at(spice, TL)", "bag": "in(target, bag)"}[task]
        raise PlanError(f"{text.strip()!r} is not a predicate such as {example}")
    name, a, b = m.groups()
    first, second = predicates[name]
    if a not in first or b not in second:
        raise PlanError(f"{name}({a}, {b}): {name} relates one of {first} to one of {second}")
    return f"{name}({a}, {b})"


def parse_chain(text: str, task: str = "drawers") -> tuple[Skill, ...]:
    return tuple(parse_skill(part, task) for part in text.split("->"))


def parse_line(line: str, task: str = "drawers") -> list[Node]:
    if not isinstance(line, str) or len(line) > MAX_LINE:
        raise PlanError(f"a plan line must be a string of at most {MAX_LINE} characters")
    m = _BRANCH.match(line)
    if m is not None:
        predicate, value, then, otherwise = m.groups()
        return [Branch(parse_predicate(predicate, task), value, parse_chain(then, task),
                       parse_chain(otherwise, task) if otherwise else ())]
    return list(parse_chain(line, task))


def parse_program(lines, task: str = "drawers") -> list[Node]:
    """The nodes of a plan chunk for ``task``, or PlanError naming the line that is wrong."""
    _task(task)
    if not isinstance(lines, (list, tuple)) or not lines or len(lines) > MAX_LINES:
        got = f"{len(lines)} lines" if isinstance(lines, (list, tuple)) else type(lines).__name__
        raise PlanError(f"a plan is a list of 1 to {MAX_LINES} lines, got {got}")
    nodes: list[Node] = []
    for i, line in enumerate(lines, 1):
        try:
            nodes.extend(parse_line(line, task))
        except PlanError as e:
            raise PlanError(f"plan line {i}: {e}") from None
    return nodes


def format_program(nodes) -> list[str]:
    """The text of a program: linear runs joined by ``->``, one branch per line."""
    lines, run = [], []
    for node in nodes:
        if isinstance(node, Branch):
            if run:
                lines.append(_chain(tuple(run)))
                run = []
            lines.append(str(node))
        else:
            run.append(node)
    if run:
        lines.append(_chain(tuple(run)))
    return lines


def leading_skills(nodes) -> list[Skill]:
    """The skills before the first branch: what will run whatever the belief says."""
    out = []
    for node in nodes:
        if isinstance(node, Branch):
            break
        out.append(node)
    return out


def splice(proposal: list[Node], anchor: Skill | None) -> list[Node]:
    """The splice rule (Appendix E-c), applied at a safe point: ``anchor`` is the skill that ran
    while the proposal was being made (it never is interrupted). If the proposal has it among its
    leading skills, what comes up to and including it is dropped (ran C, proposal A, B, C, D, E →
    D, E); otherwise the whole proposal comes next."""
    lead = leading_skills(proposal)
    if anchor is not None and anchor in lead:
        return proposal[lead.index(anchor) + 1:]
    return list(proposal)


def remaining_skills(nodes) -> int:
    """How many skills are certain to run: the leading ones, plus the shorter side of a branch."""
    count = 0
    for node in nodes:
        if isinstance(node, Branch):
            return count + min(len(node.then), len(node.otherwise))
        count += node.name != "Done"
    return count
