"""The execution monitor's logic (paper Sec. V, Appendix E-c..f, E-o), as a plain state machine.

The Monitor flow feeds it what arrived since its last tick and the world time; it answers with
at most one new skill command, at most one plan request, and its status. Nothing here knows about
clocks or transport, so every rule is tested by direct calls:

- **plan chunking**: a proposal is buffered and committed only at a safe point (the running
  skill's handoff, or at once when idle), with the splice rule of :func:`agents.plan.splice`;
  only the answer to the newest request is taken (older ones are stale).
- **branches**: ``IF p = v THEN … ELSE …`` is resolved against the newest belief when it is
  reached; while ``p`` is unknown the monitor waits, and when nothing resolves it within
  ``branch_patience`` seconds (a plan that branches on a drawer nobody inspected) it asks again.
- **progress-threshold switching**: the running skill hands off once its progress stays at or
  above ``threshold`` for ``sustain`` seconds; ``switching="timeout"`` (an ablation) hands off
  after ``timeout`` seconds whatever the progress says.
- **stale feedback**: progress for any skill id but the running one is ignored (and counted);
  progress restarts at 0 with every new skill.
- **replanning**: on the task's arrival, on every belief change, on a failed skill, a refused
  plan or a request the planner gave up on, and when fewer than ``min_horizon`` skills are left
  of a plan with no branch ahead (a branch waits on an inspection, whose belief update asks
  anyway) that does not end the task.
- **teleop**: an override skill preempts the running one, which resumes at the next safe point.
- **giving up**: a skill that failed ``max_failures`` times ends the task where it is, and so do
  ``max_planner_failures`` requests in a row that got no plan (a planner that gave up on them, or
  answered outside the vocabulary), with the planner's last word; a plan already running goes on
  in between.
- **task progress**: milestones (Appendix E-o) from belief and world facts; the score only rises.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from .plan import Branch, PlanError, Skill, parse_program, parse_skill, remaining_skills, splice

# Appendix E-o: each task's milestones, in the order they count
MILESTONES = {
    "drawers": ("inspected_target", "grasped", "seasoned", "drawers_closed"),
    "bag": ("bag_opened", "target_localized", "grasped", "extracted"),
}


@dataclass
class MonitorConfig:
    threshold: float = 0.9          # progress at which a skill may hand off
    sustain: float = 0.5            # seconds it must stay there
    switching: str = "progress"     # "progress" | "timeout" (the − skill progress ablation)
    timeout: float = 4.0            # seconds per skill under switching="timeout"
    min_horizon: int = 2            # fewer certain skills left than this: ask for more
    chunking: bool = True           # False (an ablation): ask only when idle, and wait for the answer
    max_failures: int = 3           # a skill that failed this often: give the task up (no endless retries)
    max_planner_failures: int = 2   # requests in a row that got no plan: give the task up (a planner has
    #                                 already asked its model again itself before it gives up on one)
    branch_patience: float = 3.0    # idle on an unknown branch this long: the plan cannot go on, ask again


@dataclass
class Decision:
    """What one monitor tick decided: a skill to start, a plan to ask for (each optional)."""
    command: Skill | None = None
    command_id: int = 0
    command_source: str = "plan"
    request: str | None = None      # the reason, when a plan request goes out
    request_id: int = 0


@dataclass
class ExecutionMonitor:
    config: MonitorConfig = field(default_factory=MonitorConfig)
    task_kind: str = "drawers"                      # which vocabulary and milestones: "drawers" | "bag"
    # the plan
    active: list = field(default_factory=list)      # nodes after the running skill
    pending: list | None = None                     # a committed-at-next-safe-point proposal
    # the running skill
    current: Skill | None = None
    current_id: int = 0
    current_source: str = "plan"
    started_at: float = 0.0
    progress: float = 0.0
    above_since: float | None = None
    interrupted: Skill | None = None                # a plan skill a teleop override preempted
    # knowledge
    task: str = ""
    belief: dict = field(default_factory=dict)
    belief_version: int = -1
    executed: list = field(default_factory=list)    # skills handed off, as Skill
    failures: list = field(default_factory=list)
    # bookkeeping
    next_id: int = 1
    request_id: int = 0
    answered_id: int = 0
    must_replan: str = ""                          # a failed skill or a refused plan: ask again
    executed_at_request: int = 0
    replans: int = 0
    skill_failures: int = 0
    last_failed: str = ""
    stale_feedback: int = 0
    stale_plans: int = 0
    bad_plans: int = 0
    refused_in_row: int = 0                         # requests in a row answered with no plan
    finished: bool = False
    gave_up: str = ""                               # why the task was given up, when it was
    milestones: dict = field(default_factory=dict)
    score: float = 0.0
    best_at: float = 0.0
    waiting: str = ""
    waiting_since: float = 0.0

    def __post_init__(self) -> None:
        if self.task_kind not in MILESTONES:
            raise ValueError(f"unknown task {self.task_kind!r}: the tasks are {', '.join(MILESTONES)}")
        self.milestones = dict.fromkeys(MILESTONES[self.task_kind], False)

    # -- inputs ---------------------------------------------------------------------------
    def on_task(self, text: str) -> None:
        self.task = text

    def on_belief(self, version: int, predicates: dict) -> bool:
        """Take a newer belief; True when it changed (a reason to replan)."""
        if version <= self.belief_version:
            return False
        changed = predicates != self.belief
        self.belief_version, self.belief = version, dict(predicates)
        return changed

    def on_plan(self, request_id: int, program: list) -> str:
        """Buffer a proposal: "taken", "stale" (not the newest request's answer) or "invalid"."""
        if request_id != self.request_id:
            self.stale_plans += 1
            return "stale"
        self.answered_id = request_id
        try:
            nodes = parse_program(program, self.task_kind)
        except PlanError as e:
            self._no_plan(request_id, str(e), "invalid_plan")
            return "invalid"
        self.pending, self.refused_in_row = nodes, 0
        return "taken"

    def on_planner_failure(self, request_id: int, error: str) -> str:
        """The planner gave up on a request: "stale" (not the newest request) or "failed"."""
        if request_id != self.request_id:
            self.stale_plans += 1
            return "stale"
        self.answered_id = request_id
        self._no_plan(request_id, error, "planner_failed")
        return "failed"

    def _no_plan(self, request_id: int, why: str, reason: str) -> None:
        """A request that got no plan: said in the next request's failures and asked again, up to
        ``max_planner_failures`` in a row; then the task is given up (the plan running goes on till then)."""
        self.bad_plans += 1
        self.refused_in_row += 1
        self.failures.append(f"plan {request_id}: {why}")
        if self.refused_in_row >= self.config.max_planner_failures:
            self.finished = True
            self.gave_up = f"no plan for {self.refused_in_row} requests in a row: {why}"
        else:
            self.must_replan = reason

    def on_progress(self, skill_id: int, p: float, status: str, now: float) -> None:
        if skill_id != self.current_id or self.current is None:
            self.stale_feedback += 1
            return
        self.progress = float(p)
        if status == "failed":
            self._fail(now)
            return
        if self.progress >= self.config.threshold:
            if self.above_since is None:
                self.above_since = now
        else:
            self.above_since = None

    def on_teleop(self, skill_text: str, now: float) -> Decision:
        """A teleop override: preempt the running skill (resumed at the next safe point)."""
        skill = parse_skill(skill_text, self.task_kind)
        if self.current is not None and self.current_source == "plan":
            self.interrupted = self.current
        return self._start(skill, now, source="teleop")

    def observe_world(self, facts: dict, now: float) -> None:
        """Milestones the world and the belief show (Appendix E-o); each counts once, in task order."""
        m = self.milestones
        if self.task_kind == "drawers":
            if any(v == "yes" for k, v in self.belief.items() if k.startswith("at(")):
                m["inspected_target"] = True
            if facts.get("grasped"):
                m["grasped"] = True
            if facts.get("seasoned") and m["grasped"]:
                m["seasoned"] = True
            if facts.get("drawers_closed") and m["seasoned"]:
                m["drawers_closed"] = True
        else:
            if facts.get("bag_opened"):
                m["bag_opened"] = True
            if self.belief.get("in(target, bag)") == "yes" and m["bag_opened"]:
                m["target_localized"] = True
            if facts.get("grasped"):
                m["grasped"] = True
            if facts.get("extracted") and m["grasped"]:
                m["extracted"] = True
        score = sum(m.values()) / len(m)
        if score > self.score:
            self.score, self.best_at = score, now

    # -- one tick -------------------------------------------------------------------------
    def tick(self, now: float, belief_changed: bool = False) -> Decision:
        """Hand off, commit, branch and ask, in that order; at most one new skill per tick."""
        decision = Decision()
        if self.finished or not self.task:
            return decision
        if self.current is not None and self._handoff_due(now):
            self._hand_off()
        if self.current is None:
            if self.pending is not None:
                self._commit()
            if self.interrupted is not None:
                self.active.insert(0, self.interrupted)
                self.interrupted = None
            decision = self._next(now)
            if self.finished:
                return decision
        reason = self._replan_reason(belief_changed, now)
        if reason is not None:
            self.request_id += 1
            self.replans += self.request_id > 1
            self.executed_at_request = len(self.executed)
            decision.request, decision.request_id = reason, self.request_id
        return decision

    def _handoff_due(self, now: float) -> bool:
        if self.config.switching == "timeout":
            return now - self.started_at >= self.config.timeout
        return self.above_since is not None and now - self.above_since >= self.config.sustain

    def _hand_off(self) -> None:
        self.executed.append(self.current)
        self.current, self.above_since, self.progress = None, None, 0.0

    def _commit(self) -> None:
        """At a safe point (no skill running): the anchor of the splice is the last skill that
        finished since the plan was asked for (the planner saw it running, or not at all)."""
        done = self.executed[self.executed_at_request:]
        self.active = splice(self.pending, done[-1] if done else None)
        self.pending, self.waiting = None, ""  # a new plan: any wait on its branches starts now

    def _next(self, now: float) -> Decision:
        while self.active:
            node = self.active[0]
            if isinstance(node, Branch):
                value = self.belief.get(node.predicate, "unknown")
                if value == "unknown":
                    if self.waiting != "belief":
                        self.waiting, self.waiting_since = "belief", now
                    return Decision()
                taken = node.then if value == node.value else node.otherwise
                self.active[:1] = list(taken)
                continue
            self.active.pop(0)
            if node.name == "Done":
                self.finished, self.waiting = True, ""
                return Decision()
            return self._start(node, now)
        self.waiting = "plan"
        return Decision()

    def _start(self, skill: Skill, now: float, source: str = "plan") -> Decision:
        self.current, self.current_id, self.current_source = skill, self.next_id, source
        self.next_id += 1
        self.started_at, self.progress, self.above_since, self.waiting = now, 0.0, None, ""
        return Decision(command=skill, command_id=self.current_id, command_source=source)

    def _fail(self, now: float) -> None:
        self.failures.append(f"{self.current} failed at t={now:.2f}")
        self.skill_failures, self.last_failed = self.skill_failures + 1, str(self.current)
        if sum(f.startswith(f"{self.current} failed") for f in self.failures) >= self.config.max_failures:
            self.finished, self.gave_up = True, f"{self.current} failed {self.config.max_failures} times"
        self.current, self.above_since, self.progress = None, None, 0.0
        # the plan, and a proposal not yet committed, assumed it would succeed: wait for a new one
        self.active, self.pending, self.interrupted = [], None, None
        self.must_replan = "failed"

    def _replan_reason(self, belief_changed: bool, now: float) -> str | None:
        if self.request_id == 0:
            return "task"
        if self.must_replan:
            reason, self.must_replan = self.must_replan, ""
            return reason
        if belief_changed:
            return "belief_updated"
        if self.request_id > self.answered_id or self.pending is not None:
            return None
        stuck = self.current is None and self.waiting == "belief"
        if stuck and now - self.waiting_since >= self.config.branch_patience:
            self.waiting_since = now  # once per patience: the answer may branch on it again
            return "branch_unresolved"
        if plan_ends(self.active):
            return None
        if not self.config.chunking and (self.current is not None or self.active):
            return None             # one skill at a time: ask only when it has nothing left
        if any(isinstance(node, Branch) for node in self.active):
            return None             # a branch waits on an inspection, whose belief update asks anyway
        if remaining_skills(self.active) < self.config.min_horizon:
            return "horizon"
        return None


def plan_ends(nodes) -> bool:
    """True when the program reaches ``Done()`` whichever way its branches go."""
    for i, node in enumerate(nodes):
        if isinstance(node, Branch):
            rest = list(nodes[i + 1:])
            return plan_ends(list(node.then) + rest) and plan_ends(list(node.otherwise) + rest)
        if node.name == "Done":
            return True
    return False
