"""Deterministic stand-ins for the flows the seed documents wire together.

The seed documents (``../shared/seeds``) show pipeline *wiring* but leave the flows' internals
out. These stand-ins fill them in just enough for the wiring to run as written and for the loop
to do something: the monitor issues skills from a plan chunk, the skill policy reports progress
and emits 32-row numpy action chunks, an inspection updates the belief, the belief triggers a
replan, and the planner proposes the next bounded-horizon chunk. The spice-search task runs to
the project page's representative trace:

    OpenDrawer(TL) InspectDrawer(TL) CloseDrawer(TL) OpenDrawer(TR) InspectDrawer(TR)
    Pick(spice) Season(food) CloseDrawer(TR)

Everything is a pure function of the flows' inputs and state: no wall time, no randomness, no
``hash()`` (it is salted per process); constructor arguments are JSON values, so every flow can
be rebuilt from the IR alone (``tests.seed_flows:ClassName`` + params).

Three families, one per seed listing:

- project page, "Full pipeline with port mappings" (typed ``@io`` flows): ``WristCameraFlow``,
  ``HeadCameraFlow``, ``GoalFlow``, ``BeliefMemoryFlow``, ``VLMPlanFlow``, ``ExecMonitorFlow``,
  ``VLASkillFlow``, ``ControllerFlow``, ``TeleopFlow``;
- paper Appendix D-H, Listing 1 (untyped flows: one ``step`` parameter per port, dict outputs):
  ``NamedCameraFlow``, ``GoalFlow``, ``BeliefFlow``, ``PlannerFlow``, ``ExecutionMonitorFlow``,
  ``PolicyFlow``, ``RobotControllerFlow`` (+ the ``VLM`` handle);
- paper Appendix D-D (typed, ports matched by name/type since that listing has no maps):
  ``CameraSource``, ``VLMPPlanFlow`` (sic), and the page's ``BeliefMemoryFlow``,
  ``ExecMonitorFlow``, ``VLASkillFlow``, ``ControllerFlow``, ``TeleopFlow``.
"""

from dataclasses import asdict, dataclass
from typing import Optional
import zlib

import numpy as np

from retriever import Flow, io

TASK = "find the spice and season the food"
DRAWERS = ("TL", "TR")
SPICE_DRAWER = "TR"  # the world: the spice is in the top-right drawer
SKILL_TICKS = 2  # policy ticks a skill takes to reach progress 1.0
CHUNK_STEPS = 32  # Listing 1: ActionChunking(control_hz=200, chunk_steps=32)
DOF = 14  # bimanual: 2 x (6 joints + gripper)

#: the project page's representative spice-search trace
EXPECTED_SKILLS = [
    "OpenDrawer(TL)", "InspectDrawer(TL)", "CloseDrawer(TL)", "OpenDrawer(TR)", "InspectDrawer(TR)",
    "Pick(spice)", "Season(food)", "CloseDrawer(TR)",
]


# ---------------------------------------------------------------------------------------------
# Shared, deterministic helpers (the paper's hash_obs, merge_three_valued, splice_keep_current)
# ---------------------------------------------------------------------------------------------
def _crc(*parts) -> int:
    h = 0
    for p in parts:
        data = p.tobytes() if isinstance(p, np.ndarray) else repr(p).encode()
        h = zlib.crc32(data, h)
    return h


def hash_obs(*parts) -> int:
    """A stable id of an observation (crc32; Python's hash() is salted per process)."""
    return _crc(*parts)


def parse_belief(text) -> dict:
    """``"in(spice,TL)=no; in(spice,TR)=unknown"`` → ``{"TL": "no", "TR": "unknown"}``."""
    belief = {d: "unknown" for d in DRAWERS}
    if not isinstance(text, str):
        return belief
    for item in text.split(";"):
        key, _, value = item.strip().partition("=")
        if key.startswith("in(spice,") and key.endswith(")") and value in ("yes", "no", "unknown"):
            belief[key[len("in(spice,"):-1]] = value
    return belief


def format_belief(belief: dict) -> str:
    return "; ".join(f"in(spice,{d})={belief.get(d, 'unknown')}" for d in DRAWERS)


def merge_three_valued(prev, new_obs: dict):
    """3-valued update: unknown never overwrites yes/no; yes/no overwrite (may flip)."""
    as_text = isinstance(prev, str)
    belief = parse_belief(prev) if as_text else dict(prev)
    for d, v in new_obs.items():
        if v != "unknown":
            belief[d] = v
    return format_belief(belief) if as_text else belief


def plan_for(belief: dict, completed) -> list[str]:
    """A bounded-horizon conditional plan chunk: it ends at an inspection whose outcome is unknown."""
    seq: list[str] = []
    for d in DRAWERS:
        state = belief.get(d, "unknown")
        seq += [f"OpenDrawer({d})", f"InspectDrawer({d})"]
        if state == "unknown":
            break  # the branch depends on what the inspection finds: replan then
        if state == "yes":
            seq += ["Pick(spice)", "Season(food)", f"CloseDrawer({d})"]
            break
        seq.append(f"CloseDrawer({d})")
    done = set(completed)
    return [s for s in seq if s not in done]


def splice_keep_current(active, pending, current, completed=()) -> list[str]:
    """Safe-point apply: follow the proposal after the current skill, never redoing finished ones."""
    pending = list(pending)
    if current in pending:
        pending = pending[pending.index(current) + 1:]
    done = set(completed)
    return [s for s in pending if s not in done and s != current]


def drawer_of(skill: str) -> str:
    return skill[skill.index("(") + 1:-1]


class VLM(str):
    """Stand-in VLM handle. It is its model name (a str), so it survives the IR as a parameter."""

    def observe(self, inspection) -> dict:
        d = inspection["drawer"]
        return {d: "yes" if d == SPICE_DRAWER else "no"}

    def plan(self, belief: dict, completed) -> list[str]:
        return plan_for(belief, completed)


# ---------------------------------------------------------------------------------------------
# The logic inside the monitor and the skill policy, shared by the typed and untyped flows
# ---------------------------------------------------------------------------------------------
class _MonitorCore:
    """Plan chunking inside the monitor: commit proposals at safe points, one skill at a time.

    ``tick`` takes the latest values on its ports (``Latest`` re-delivers old values, so it
    recognises new ones by their ids) and returns the outputs of this tick:
    ``current_skill``, ``inspection``, ``plan_request``, ``context``.

    ``heartbeat``: on a tick that brings nothing new (it was triggered by ``task``), re-issue the
    current skill, so a policy clocked by ``Trigger("prompt")`` keeps stepping. A tick caused by
    the policy's own feedback never re-issues, so monitor ⇄ policy settles within each instant.
    """

    def __init__(self, heartbeat: bool):
        self.heartbeat = heartbeat
        self.active_chunk: list[str] = []
        self.pending_chunk: list[str] | None = None
        self.current_skill: str | None = None
        self.issue = 0
        self.completed: list[str] = []
        self.belief_text: str | None = None
        self._belief_at_request: str | None = None
        self._last_result = None
        self._last_feedback = None
        self._requested_for = None
        self._requests = 0
        self._inspections = 0

    def tick(self, planner_result, feedback, belief_text) -> dict:
        out: dict = {}
        news = False
        issue_before = self.issue
        if planner_result is not None and planner_result["id"] != self._last_result:
            self._last_result = planner_result["id"]
            self.on_planner_result(planner_result)
            news = True
        if belief_text is not None and belief_text != self.belief_text:
            self.belief_text = belief_text
            news = True
        if feedback is not None and feedback["seq"] != self._last_feedback:
            self._last_feedback = feedback["seq"]
            news = True
            finished = self.on_policy_feedback(feedback)
            if finished is not None and finished.startswith("InspectDrawer("):
                self._inspections += 1
                out["inspection"] = {"ts": self._inspections, "drawer": drawer_of(finished)}
        if self.current_skill is None:  # idle is a safe point too
            self._commit_pending_chunk_if_any()
            self._next_skill()
        issued = self.issue != issue_before
        if self.current_skill is not None and (issued or (self.heartbeat and not news)):
            out["current_skill"] = {"skill": self.current_skill, "n": self.issue}
        idle = self.current_skill is None and not self.active_chunk
        belief_changed = self.belief_text != self._belief_at_request
        key = (len(self.completed), self.belief_text)
        if (idle or belief_changed) and key != self._requested_for:
            self._requested_for = key
            self._belief_at_request = self.belief_text
            self._requests += 1
            out["plan_request"] = self._requests
            out["context"] = {"belief": self.belief_text, "completed": list(self.completed),
                              "current": self.current_skill,
                              "reason": "belief_updated" if belief_changed else "plan_exhausted"}
        return out

    def on_planner_result(self, planner_result) -> None:
        # Receive an asynchronous proposal; do not apply it immediately.
        self.pending_chunk = list(planner_result["plan_chunk"])

    def on_policy_feedback(self, feedback) -> str | None:
        if feedback["n"] != self.issue or self.current_skill is None:
            return None  # feedback about an earlier command
        safe_point = bool(feedback.get("skill_done") or feedback.get("skill_failed"))
        if not safe_point:
            return None
        finished = self.current_skill
        self.completed.append(finished)
        self.current_skill = None
        self._commit_pending_chunk_if_any()
        self._next_skill()
        return finished

    def _commit_pending_chunk_if_any(self) -> None:
        if not self.pending_chunk:
            self.pending_chunk = None
            return
        self.active_chunk = splice_keep_current(self.active_chunk, self.pending_chunk,
                                                self.current_skill, self.completed)
        self.pending_chunk = None

    def _next_skill(self) -> bool:
        if self.current_skill is not None or not self.active_chunk:
            return False
        self.current_skill = self.active_chunk.pop(0)
        self.issue += 1
        return True


class _SkillCore:
    """A skill policy: progress per tick on one command, an action chunk every tick."""

    def __init__(self, chunk_steps: int, dof: int, ticks_per_skill: int = SKILL_TICKS):
        self.chunk_steps, self.dof, self.ticks_per_skill = chunk_steps, dof, ticks_per_skill
        self.command = None
        self.ticks = 0
        self.seq = 0

    def tick(self, prompt) -> tuple[dict, np.ndarray, dict | None]:
        key = (prompt["skill"], prompt["n"])
        if key != self.command:
            self.command, self.ticks = key, 0
        self.ticks += 1
        self.seq += 1
        progress = min(1.0, self.ticks / self.ticks_per_skill)
        skill = prompt["skill"]
        feedback = {"seq": self.seq, "skill": skill, "n": prompt["n"], "skill_progress": progress,
                    "skill_done": progress >= 1.0, "skill_failed": False}
        inspection = None
        if self.ticks == self.ticks_per_skill and skill.startswith("InspectDrawer("):
            d = drawer_of(skill)
            inspection = {"drawer": d, "has_target": d == SPICE_DRAWER}
        base = (zlib.crc32(skill.encode()) % 1000) / 1000.0
        ramp = np.linspace(0.0, 1.0, self.chunk_steps)[:, None]
        chunk = base + progress * ramp * np.linspace(0.5, 1.5, self.dof)[None, :]
        return feedback, chunk, inspection


def _frame(k: int, salt: int) -> np.ndarray:
    return ((np.arange(16, dtype=np.int64).reshape(4, 4) * 7 + k * 3 + salt) % 256).astype(np.uint8)


# =============================================================================================
# Project page: "Full pipeline with port mappings" (typed flows) — also Appendix D-D
# =============================================================================================
@dataclass
class SkillCommand:
    skill: str
    n: int


@dataclass
class Progress:
    seq: int
    skill: str
    n: int
    skill_progress: float
    skill_done: bool
    skill_failed: bool


@dataclass
class PlanChunk:
    id: int
    plan_chunk: list[str]


@dataclass
class ReplanContext:
    request: int
    belief: Optional[str]
    completed: list[str]
    current: Optional[str]
    reason: str


@dataclass
class Inspection:
    drawer: str
    has_target: bool


@dataclass
class BeliefState:
    text: str


@dataclass
class TeleopCmd:
    command: str


@io
@dataclass
class CameraFrame:
    frame: np.ndarray


@io
@dataclass
class Goal:
    task: str


class WristCameraFlow(Flow[None, CameraFrame]):
    """4x wrist cameras, stood in for by one synthetic 4x4 image stream."""

    def __init__(self):
        self.k = 0

    def step(self, inp: None) -> CameraFrame:
        self.k += 1
        return CameraFrame(frame=_frame(self.k, 11))


class HeadCameraFlow(Flow[None, CameraFrame]):
    def __init__(self):
        self.k = 0

    def step(self, inp: None) -> CameraFrame:
        self.k += 1
        return CameraFrame(frame=_frame(self.k, 29))


class CameraSource(Flow[None, CameraFrame]):
    """Appendix D-D's ``CameraSource(id=0)``."""

    def __init__(self, id: int = 0):
        self.id = id
        self.k = 0

    def step(self, inp: None) -> CameraFrame:
        self.k += 1
        return CameraFrame(frame=_frame(self.k, 41 + self.id))


class GoalFlow(Flow[None, Goal]):
    """The task, restated at the goal's rate (page: ``GoalFlow()``; Listing 1: ``GoalFlow(task=TASK)``)."""

    def __init__(self, task: str = TASK):
        self.task = task

    def step(self, inp: None) -> Goal:
        return Goal(task=self.task)


@io
@dataclass
class BeliefIn:
    frames: np.ndarray
    inspection_done: Optional[Inspection] = None


@io
@dataclass
class BeliefOut:
    belief: Optional[BeliefState] = None
    belief_updated: Optional[bool] = None


class BeliefMemoryFlow(Flow[BeliefIn, BeliefOut]):
    """Appendix D-B's pattern: state initialised in ``reset()``; updated on ``inspection_done``."""

    def reset(self):
        self.belief = {d: "unknown" for d in DRAWERS}
        self.updates = 0

    def step(self, inp: BeliefIn) -> BeliefOut:
        event = inp.inspection_done
        if event is None:
            return BeliefOut()
        obs = {event.drawer: "yes" if event.has_target else "no"}
        self.belief = merge_three_valued(self.belief, obs)
        self.updates += 1
        return BeliefOut(belief=BeliefState(format_belief(self.belief)), belief_updated=True)


@io
@dataclass
class VLMPlanIn:
    task: str
    state: Optional[BeliefState] = None
    frame: Optional[np.ndarray] = None
    context: Optional[ReplanContext] = None
    replan_request: Optional[int] = None


@io
@dataclass
class PlanOut:
    result: Optional[PlanChunk] = None


class VLMPlanFlow(Flow[VLMPlanIn, PlanOut]):
    """The page's planner: a bounded-horizon plan chunk from belief ``state`` + execution ``context``."""

    def __init__(self, model: str):
        self.vlm = VLM(model)
        self.n = 0

    def step(self, inp: VLMPlanIn) -> PlanOut:
        belief = parse_belief(inp.state.text if inp.state is not None else None)
        completed = inp.context.completed if inp.context is not None else []
        self.n += 1
        return PlanOut(result=PlanChunk(id=self.n, plan_chunk=self.vlm.plan(belief, completed)))


@io
@dataclass
class VLMPPlanIn:
    belief: Optional[BeliefState] = None
    belief_updated: Optional[bool] = None
    task: str = TASK


class VLMPPlanFlow(Flow[VLMPPlanIn, PlanOut]):
    """Appendix D-D's planner (spelled ``VLMPPlanFlow`` there), triggered by ``belief_updated``."""

    def __init__(self, model: str):
        self.vlm = VLM(model)
        self.n = 0

    def step(self, inp: VLMPPlanIn) -> PlanOut:
        belief = parse_belief(inp.belief.text if inp.belief is not None else None)
        self.n += 1
        return PlanOut(result=PlanChunk(id=self.n, plan_chunk=self.vlm.plan(belief, [])))


@io
@dataclass
class MonitorIn:
    task: Optional[str] = None
    planner_result: Optional[PlanChunk] = None
    policy_feedback: Optional[Progress] = None
    teleop_event: Optional[TeleopCmd] = None


@io
@dataclass
class MonitorOut:
    current_skill: Optional[SkillCommand] = None
    replan_trigger: Optional[ReplanContext] = None  # the page maps it to the planner's `context`
    replan_request: Optional[int] = None


class ExecMonitorFlow(Flow[MonitorIn, MonitorOut]):
    """The page's execution monitor (@ Rate(hz=10)): plan chunking inside, one skill at a time."""

    def reset(self):
        self.core = _MonitorCore(heartbeat=False)  # a Rate-clocked policy needs no heartbeat

    def step(self, inp: MonitorIn) -> MonitorOut:
        out = self.core.tick(
            asdict(inp.planner_result) if inp.planner_result is not None else None,
            asdict(inp.policy_feedback) if inp.policy_feedback is not None else None,
            None,
        )
        skill = out.get("current_skill")
        ctx = out.get("context")
        return MonitorOut(
            current_skill=SkillCommand(**skill) if skill else None,
            replan_trigger=ReplanContext(request=out["plan_request"], **ctx) if ctx else None,
            replan_request=out.get("plan_request"),
        )


@io
@dataclass
class VLAIn:
    obs_dict: np.ndarray
    prompt: SkillCommand


@io
@dataclass
class VLAOut:
    feedback: Optional[Progress] = None
    action: Optional[np.ndarray] = None
    inspection_done: Optional[Inspection] = None


class VLASkillFlow(Flow[VLAIn, VLAOut]):
    """The page's VLA skill policy: progress feedback + an 8-step action chunk (``horizon=8``)."""

    def __init__(self, model_name: str, horizon: int = 8):
        self.model_name = model_name
        self.core = _SkillCore(horizon, DOF)

    def step(self, inp: VLAIn) -> VLAOut:
        feedback, chunk, inspection = self.core.tick(asdict(inp.prompt))
        brightness = float(inp.obs_dict.mean()) / 255.0  # the observation nudges the actions
        return VLAOut(feedback=Progress(**feedback), action=chunk + 0.01 * brightness,
                      inspection_done=Inspection(**inspection) if inspection else None)


@io
@dataclass
class ControlIn:
    action: np.ndarray  # a whole chunk (Latest) or one row of it (ActionChunking)


@io
@dataclass
class JointCommand:
    q: np.ndarray


class ControllerFlow(Flow[ControlIn, JointCommand]):
    """A first-order joint servo. Given a whole chunk it walks its rows on its own clock."""

    def __init__(self, id: int = 0, gain: float = 0.2):
        self.id, self.gain = id, gain
        self.q = np.zeros(DOF)
        self._chunk_key = None
        self._row = 0

    def step(self, inp: ControlIn) -> JointCommand:
        action = np.asarray(inp.action, dtype=float)
        if action.ndim == 2:
            key = _crc(action)
            if key != self._chunk_key:
                self._chunk_key, self._row = key, 0
            action = action[min(self._row, len(action) - 1)]
            self._row += 1
        self.q = self.q + self.gain * (action - self.q)
        return JointCommand(q=self.q.copy())


@io
@dataclass
class TeleopIO:
    teleop_event: Optional[TeleopCmd] = None


class TeleopFlow(Flow[TeleopIO, TeleopIO]):
    """Operator override. No operator is at the wheel in these runs: it ticks and emits nothing."""

    def step(self, inp: TeleopIO) -> TeleopIO:
        return TeleopIO(teleop_event=inp.teleop_event)


# =============================================================================================
# Paper Appendix D-H, Listing 1 (untyped flows: one step parameter per input port, dict outputs)
# =============================================================================================
class NamedCameraFlow(Flow):
    """``NamedCameraFlow("right_wrist")``: a named synthetic camera."""

    def __init__(self, name: str):
        self.camera = name
        self.salt = zlib.crc32(name.encode()) % 97
        self.k = 0

    def step(self):
        self.k += 1
        return {"frame": _frame(self.k, self.salt)}


class BeliefFlow(Flow):
    """Maintain latest belief_text using (images, previous belief) -> updated belief."""

    def __init__(self, vlm):
        self.vlm = VLM(vlm)
        self.belief_text = "(init belief)"
        self._in_flight_obs_id = None

    def step(self, frames_right, frames_left, inspection_trigger_ts):
        # Drop if a request is already in flight for the same observation.
        obs_id = hash_obs(frames_right, frames_left, inspection_trigger_ts)
        if self._in_flight_obs_id == obs_id:
            return {}
        self._in_flight_obs_id = obs_id
        new_obs = self.vlm.observe(inspection_trigger_ts)
        self.belief_text = merge_three_valued(self.belief_text, new_obs)
        self._in_flight_obs_id = None
        return {"belief_text": self.belief_text, "belief_updated": True}


class PlannerFlow(Flow):
    """Propose a bounded-horizon plan chunk (3--5 skills, ~10s horizon)."""

    def __init__(self, vlm):
        self.vlm = VLM(vlm)
        self.n = 0

    def step(self, task, belief_text=None, context=None, plan_request_ts=None):
        # Listing 1's step(task, belief_text, context) plus the Hybrid's trigger port
        # plan_request_ts, which the wiring feeds and the clock names. Listing 1 wires no
        # belief → planner edge: the belief comes with the monitor's context.
        if context is not None and context.get("belief") is not None:
            belief_text = context["belief"]
        completed = context["completed"] if context is not None else []
        self.n += 1
        plan = self.vlm.plan(parse_belief(belief_text), completed)
        return {"result": {"plan_chunk": plan, "id": self.n, "task": task}}


class ExecutionMonitorFlow(Flow):
    """Execute one SkillCmd at a time; plan chunking is handled *inside* this Flow."""

    def __init__(self):
        self.core = _MonitorCore(heartbeat=True)

    def step(self, frame=None, planner_result=None, policy_feedback=None, task=None, belief_text=None):
        out = self.core.tick(planner_result, policy_feedback, belief_text)
        result = {}
        if "current_skill" in out:
            result["current_skill"] = out["current_skill"]
        if "inspection" in out:
            result["inspection_trigger_ts"] = out["inspection"]
        if "plan_request" in out:
            result["plan_request_ts"] = out["plan_request"]
            result["context"] = out["context"]
        return result


class PolicyFlow(Flow):
    """The skill policy of Listing 1 (``PolicyFlow(...)``): feedback + a 32-row action chunk."""

    def __init__(self, model: str = "pi05", chunk_steps: int = CHUNK_STEPS):
        self.model = model
        self.core = _SkillCore(chunk_steps, DOF)

    def step(self, prompt, obs_dict=None, deploy_stats=None):
        feedback, chunk, _inspection = self.core.tick(prompt)
        return {"feedback": feedback, "action_chunk": chunk}


class RobotControllerFlow(Flow):
    """The 200 Hz controller of Listing 1: tracks the action row ActionChunking hands it."""

    def __init__(self, dof: int = DOF, gain: float = 0.2):
        self.gain = gain
        self.q = np.zeros(dof)
        self.ticks = 0

    def step(self, action, reset=None):
        if reset is not None:
            self.q = np.zeros_like(self.q)
        self.q = self.q + self.gain * (np.asarray(action, dtype=float) - self.q)
        self.ticks += 1
        return {}  # commands go to the robot; nothing downstream in the graph
