"""The messages of Retriever-0 (the paper's Appendix E-l), as registered value types.

Every edge of the agent carries one of these, so a log decodes them by name and nothing else.
Times (``t``) are simulated seconds read from the world, the agent's one clock of record.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from retriever import io


@io
@dataclass
class Task:
    """The language goal: what to find, and what to do with it."""
    text: str
    task: str = "drawers"          # "drawers" | "bag"
    target: str = "spice"
    food: str = "food"


@io
@dataclass
class Observation:
    """The world's state at one physics tick: positions for cameras, facts for skills and the monitor."""
    t: float
    qpos: np.ndarray
    robot: np.ndarray               # measured values in the order of world.ACTUATORS
    facts: dict                     # drawers, handles, bottle pose, milestones (Sim.observe() minus arrays above)


@io
@dataclass
class Frame:
    """One camera image (uint8 H×W×3) and the world time it shows."""
    camera: str
    t: float
    rgb: np.ndarray


@io
@dataclass
class Command:
    """The controller's actuator targets for the world, in the order of world.ACTUATORS."""
    u: np.ndarray


@io
@dataclass
class SkillCmd:
    """One concrete skill for the skill policy: ``OpenDrawer(TL-H)`` with an id the feedback echoes."""
    skill_id: int
    name: str
    arg: str
    source: str = "plan"            # "plan" | "teleop"

    def __str__(self) -> str:
        return f"{self.name}({self.arg})"


@io
@dataclass
class ActionChunk:
    """A chunk of actuator targets at the control rate, starting at its event's tag time
    (``ActionChunking`` reads ``actions``)."""
    skill_id: int
    actions: np.ndarray


@io
@dataclass
class Progress:
    """The skill policy's feedback: progress ``p`` in [0, 1] of the skill it was told to run."""
    skill_id: int
    t: float
    p: float
    status: str                     # "running" | "done" | "failed"


@io
@dataclass
class InspectionDone:
    """An inspection skill finished looking into ``drawer`` (world time ``t``): belief may update."""
    skill_id: int
    t: float
    drawer: str


@io
@dataclass
class Belief:
    """Three-valued predicates (``"yes" | "no" | "unknown"``), versioned: each update adds one."""
    version: int
    predicates: dict
    t: float = 0.0
    evidence: str = ""


@io
@dataclass
class PlanRequest:
    """The monitor asks the planner for a plan chunk, with the context it needs."""
    request_id: int
    reason: str
    t: float
    belief: dict
    executed: list                  # skills done so far, as "Name(arg)" strings
    current: str = ""               # the skill running now, "" when idle
    failures: list = field(default_factory=list)


@io
@dataclass
class PlanChunk:
    """A bounded-horizon skill program in the paper's text format, one line per node:
    ``OpenDrawer(TL-H)``, ``IF at(spice, TL) = yes THEN Pick(spice) -> Season(food) ELSE CloseDrawer(TL-H)``,
    ``Done()``."""
    request_id: int
    program: list
    planner: str = "scripted"


@io
@dataclass
class PlanFailure:
    """The planner gave up on a request (a model that answered no plan in all its attempts, an
    endpoint that refused or is gone): ``error`` says so in one line, naming the endpoint and the
    last answer. Sent instead of a ``PlanChunk``, by the planners that can fail."""
    request_id: int
    error: str
    planner: str = ""


@io
@dataclass
class TeleopEvent:
    """An intervention (Appendix E-n): a skill that overrides the plan from ``t_start``. The
    override runs until its skill hands off, as a plan's would; ``t_end`` is the operator's
    intended end, kept for the record (the schedule file's, or ``t_start``)."""
    t_start: float
    t_end: float
    mode: str                       # "skill_override"
    payload: str                    # a skill, "Pick(spice)"
    resume_policy: str = "next_safe_point"


@io
@dataclass
class MonitorStatus:
    """What the monitor knows at one tick: the task-progress score and how it got there."""
    t: float
    skill: str                      # the skill running, "" when idle
    skill_id: int
    p: float
    score: float                    # task progress 0..1 (Appendix E-o milestones)
    milestones: dict
    finished: bool
    replans: int
    executed: list
    waiting: str = ""               # what the monitor waits for when idle ("plan", "belief", "")
    failures: int = 0               # skills that failed so far
    last_failed: str = ""           # the last one, "Pick(spice)"
    gave_up: str = ""               # why the task was given up (a skill failed too often), if it was
    stale_feedback: int = 0         # progress reports for a skill that no longer runs, ignored
    stale_plans: int = 0            # answers to a request a newer one superseded, dropped
    bad_plans: int = 0              # answers that were no program of the vocabulary, refused
