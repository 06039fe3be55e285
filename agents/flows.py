"""The flows of Retriever-0 (paper Appendix E-a, D-H): world, cameras, belief, planner, monitor,
skill policy, controller, goal and teleop.

Each keeps ``__init__`` cheap (it stores JSON arguments: on ``zenoh`` every worker imports this
module and the IR rebuilds each flow from them) and acquires what is heavy in ``setup()``, in the
process that steps it: a MuJoCo model, a renderer, a planner client. Times in messages are the
world's simulated seconds.
"""

from __future__ import annotations

import json
import os
import stat
import sys
from pathlib import Path

import numpy as np

from retriever import Flow
from retriever.learn import TorchPolicy

from .messages import (
    ActionChunk, Belief, Command, Frame, InspectionDone, MonitorStatus, Observation, PlanChunk, PlanFailure,
    PlanRequest, Progress, SkillCmd, Task, TeleopEvent,
)
from .monitor import ExecutionMonitor, MonitorConfig
from .robot import NU

ARRAY_FACTS = ("qpos", "qvel", "robot")


def _sim(seed: int, drawer: str | None, task: str = "drawers"):
    """The task's world for ``seed`` (MuJoCo loads in the flow's own process only)."""
    if task == "bag":
        from .bag_world import BagLayout, BagSim
        return BagSim(BagLayout.from_seed(seed))
    from .world import Layout, Sim
    return Sim(Layout.from_seed(seed, drawer))


#: each task's language goal, and what it is about (the Task's target and food; the bag has no food)
GOALS = {
    "drawers": {"text": "Find the spice in the drawers and season the food.", "target": "spice", "food": "food"},
    "bag": {"text": "Take the target out of the bag and set it on the tray's spot.", "target": "target", "food": ""},
}


class Goal(Flow):
    """The language goal of ``task``: said once, at the first tick (``text``: other words for it)."""

    def __init__(self, text: str | None = None, task: str = "drawers"):
        self.text, self.task, self.said = text, task, False

    def step(self):
        if self.said:
            return {}
        self.said = True
        goal = GOALS[self.task]
        return {"task": Task(text=self.text or goal["text"], task=self.task, target=goal["target"], food=goal["food"])}


class World(Flow):
    """The MuJoCo world: applies the controller's newest command and advances physics by one
    tick (``tick`` seconds); its observation is the state every other flow reads. With
    ``sensors``, it also publishes what a learned skill policy sees (``state`` and ``scene``,
    :mod:`agents.skill_features`); ``start="pick"`` begins where a Pick begins in the task
    (:func:`agents.skills.pick_start`)."""

    def __init__(self, seed: int = 0, drawer: str | None = None, tick: float = 0.005, slip_prob: float = 0.0,
                 task: str = "drawers", sensors: bool = False, start: str = ""):
        self.seed, self.drawer, self.tick, self.slip_prob, self.task = seed, drawer, tick, slip_prob, task
        self.sensors, self.start = sensors, start
        self.slip_at: float | None = None

    def setup(self):
        from .skill_features import sensors
        self.sim, self.read_sensors = self._start(), sensors

    def _start(self):
        sim = _sim(self.seed, self.drawer, self.task)
        if self.start == "pick":
            from .skills import pick_start
            openings, command = pick_start(sim.layout)
            sim.set_openings(openings)
            sim.set_robot(command)
        elif self.start:
            raise ValueError(f"World(start={self.start!r}): expected '' (the task's start) or 'pick'")
        return sim

    def teardown(self):
        self.sim.close()
        del self.sim

    def reset(self):
        """A fresh episode: the same layout, physics back to its start."""
        if hasattr(self, "sim"):
            self.sim.close()
            self.sim = self._start()
        self.slip_at = None

    def step(self, command: Command | None = None):
        sim = self.sim
        if command is not None:
            sim.command(command.u)
        sim.advance(self.tick)
        facts = sim.observe()
        self._maybe_slip(facts)
        seen = {}
        if self.sensors:
            seen["state"], seen["scene"] = self.read_sensors(facts)
        arrays = {k: np.asarray(facts.pop(k), dtype=np.float64) for k in ARRAY_FACTS if k in facts}
        return {"obs": Observation(t=round(float(facts.pop("t")), 9), qpos=arrays["qpos"], robot=arrays["robot"],
                                   facts=facts), **seen}

    def _maybe_slip(self, facts: dict) -> None:
        """Failure injection: with probability ``slip_prob`` per episode (decided by the seed), the
        first grasp slips a moment after the bottle is lifted."""
        if self.slip_prob <= 0 or self.slip_at == -1.0:
            return
        if self.slip_at is None and facts.get("grasped"):
            rng = np.random.default_rng([self.seed, 7])
            self.slip_at = facts["t"] + 1.0 if rng.random() < self.slip_prob else -1.0
        if self.slip_at not in (None, -1.0) and facts["t"] >= self.slip_at:
            self.sim.slip()
            self.slip_at = -1.0


class Camera(Flow):
    """A camera: rebuilds the scene from the world's newest positions and renders it on the CPU."""

    def __init__(self, camera: str = "head", height: int = 96, width: int = 128, seed: int = 0,
                 drawer: str | None = None, task: str = "drawers"):
        self.camera, self.height, self.width, self.seed, self.drawer = camera, height, width, seed, drawer
        self.task = task

    def setup(self):
        self.sim = _sim(self.seed, self.drawer, self.task)
        self.sim.render(self.camera, self.height, self.width)     # the renderer's 0.2 s start-up, before T0

    def teardown(self):
        self.sim.close()
        del self.sim

    def step(self, obs: Observation):
        self.sim.load_qpos(obs.qpos)
        return {"frame": Frame(camera=self.camera, t=obs.t, rgb=self.sim.render(self.camera, self.height, self.width))}


class BeliefUpdater(Flow):
    """Belief/memory (F2): on each ``inspection_done``, colour segmentation of the head camera's
    newest frame (real pixels, standing in for the belief VLM) answers ``at(spice, drawer)`` (or,
    in the bag task, ``in(target, bag)``); a three-valued merge keeps what is known (unknown never
    overwrites yes/no)."""

    def __init__(self, seed: int = 0, drawer: str | None = None, task: str = "drawers"):
        self.seed, self.drawer, self.task = seed, drawer, task
        self.version, self.predicates = 0, {}

    def setup(self):
        self.sim = _sim(self.seed, self.drawer, self.task)   # the camera's geometry, for projecting drawers
        if self.task == "bag":
            from .bag_perception import inspect_bag
            self.look = lambda rgb, inspection, obs: ("in(target, bag)", inspect_bag(rgb, self.sim))
        else:
            from .perception import inspect
            self.look = lambda rgb, inspection, obs: (
                f"at(spice, {inspection.drawer})", inspect(rgb, inspection.drawer, obs.facts["drawers"], self.sim))

    def teardown(self):
        self.sim.close()
        del self.sim

    def step(self, inspection: InspectionDone, frame: Frame, obs: Observation):
        predicate, verdict = self.look(frame.rgb, inspection, obs)
        new = {predicate: verdict}
        merged = merge_three_valued(self.predicates, new)
        if merged == self.predicates and self.version > 0:
            return {}
        self.predicates, self.version = merged, self.version + 1
        return {"belief": Belief(version=self.version, predicates=dict(merged), t=obs.t,
                                 evidence=f"{inspection.drawer}: {verdict} (frame t={frame.t:.2f})")}


def merge_three_valued(old: dict, new: dict) -> dict:
    """``unknown`` never overwrites ``yes``/``no``; ``yes``/``no`` overwrite (the world may change)."""
    merged = dict(old)
    for key, value in new.items():
        if value != "unknown" or key not in merged:
            merged[key] = value
    return merged


class PlannerFlow(Flow):
    """The planner (F3, a VLM stand-in by default): answers each plan request with a plan chunk,
    or, when the planner gives up on it, with a ``failure`` naming why. A VLM planner also sees
    the head camera's newest ``frame``. Its declared latency is the seconds it is given to think."""

    def __init__(self, planner: str = "scripted", task: str = "drawers"):
        self.planner_spec, self.task = planner, task

    def setup(self):
        from .planner import make_planner
        self.planner = make_planner(self.planner_spec, self.task)

    def step(self, request: PlanRequest, task: Task | None = None, frame: Frame | None = None):
        from .planner import PlannerError
        context = {"executed": request.executed, "current": request.current, "failures": request.failures,
                   "reason": request.reason}
        image = frame.rgb if frame is not None else None
        try:
            program = self.planner.propose(task.text if task else "", request.belief, context, image=image)
        except PlannerError as e:
            print(f"planner: {e}", file=sys.stderr, flush=True)
            return {"failure": PlanFailure(request_id=request.request_id, error=e.problem, planner=self.planner.name)}
        return {"plan": PlanChunk(request_id=request.request_id, program=program, planner=self.planner.name)}


class Monitor(Flow):
    """The execution monitor (F4): plan chunking, branches, progress-threshold switching, stale
    feedback, replanning and teleop (rules in :mod:`agents.monitor`). ``end_after`` seconds after
    the plan says ``Done()`` it ends the whole run (``sys.exit(0)`` in a step)."""

    def __init__(self, threshold: float = 0.9, sustain: float = 0.5, switching: str = "progress",
                 timeout: float = 4.0, min_horizon: int = 2, chunking: bool = True,
                 end_after: float | None = 1.0, verbose: bool = False, task: str = "drawers"):
        self.settings = dict(threshold=threshold, sustain=sustain, switching=switching, timeout=timeout,
                             min_horizon=min_horizon, chunking=chunking)
        self.end_after, self.verbose, self.task = end_after, verbose, task
        self.logic = ExecutionMonitor(MonitorConfig(**self.settings), task)
        self.finished_at: float | None = None
        self.said, self.failures_said = "", 0

    def step(self, obs: Observation, task: Task | None = None, belief: Belief | None = None,
             progress: list | None = None, plan: list | None = None, teleop: list | None = None,
             plan_failure: list | None = None):
        m, now = self.logic, obs.t
        if task is not None and not m.task:
            m.on_task(task.text)
        changed = belief is not None and m.on_belief(belief.version, belief.predicates)
        for chunk in plan or ():
            m.on_plan(chunk.request_id, chunk.program)
        for failure in plan_failure or ():
            m.on_planner_failure(failure.request_id, failure.error)
        out: dict = {}
        for event in teleop or ():
            out["skill"] = self._command(m.on_teleop(event.payload, now))
        for feedback in progress or ():
            m.on_progress(feedback.skill_id, feedback.p, feedback.status, now)
        m.observe_world(obs.facts, now)
        decision = m.tick(now, changed)
        if decision.command is not None:
            out["skill"] = self._command(decision)
        if decision.request is not None:
            predicates = dict(m.belief)
            held = "holding(target)" if self.task == "bag" else "holding(spice)"
            predicates[held] = "yes" if obs.facts.get("grasped") else "no"
            out["request"] = PlanRequest(request_id=decision.request_id, reason=decision.request, t=now,
                                         belief=predicates, executed=[str(s) for s in m.executed],
                                         current=str(m.current) if m.current else "", failures=list(m.failures))
        out["status"] = MonitorStatus(t=now, skill=str(m.current) if m.current else "", skill_id=m.current_id,
                                      p=m.progress, score=m.score, milestones=dict(m.milestones),
                                      finished=m.finished, replans=m.replans, executed=[str(s) for s in m.executed],
                                      waiting=m.waiting, failures=m.skill_failures, last_failed=m.last_failed,
                                      gave_up=m.gave_up, stale_feedback=m.stale_feedback,
                                      stale_plans=m.stale_plans, bad_plans=m.bad_plans)
        self._say(out["status"], out.get("skill"), decision.request)
        if m.finished and self.end_after is not None:
            self.finished_at = now if self.finished_at is None else self.finished_at
            if now - self.finished_at >= self.end_after:
                sys.exit(0)
        return out

    @staticmethod
    def _command(decision) -> SkillCmd:
        return SkillCmd(skill_id=decision.command_id, name=decision.command.name, arg=decision.command.arg,
                        source=decision.command_source)

    def _say(self, status: MonitorStatus, started: SkillCmd | None, request: str | None) -> None:
        """With ``verbose``, one line whenever the skill, the score or the wait changes, and one
        for each failed skill, teleop takeover, plan request and giving up."""
        if not self.verbose:
            return
        t = f"t={status.t:6.2f}s "
        if status.failures > self.failures_said:
            self.failures_said = status.failures
            print(f"{t} ✗ {status.last_failed} failed ({status.failures} so far)", flush=True)
        if started is not None and started.source == "teleop":
            print(f"{t} ⇢ teleop takes over: {started.name}({started.arg})", flush=True)
        if request is not None and request != "task":
            print(f"{t} ? asks the planner again ({request.replace('_', ' ')})", flush=True)
        if status.gave_up:      # said once: the ticks until the run ends have nothing new to say
            if not self.said.startswith("gave up"):
                self.said = "gave up"
                print(f"{t} gave up: {status.gave_up}", flush=True)
            return
        line = f"{status.skill or '(' + (status.waiting or 'idle') + ')'} score {status.score:.0%}"
        if line != self.said:
            self.said = line
            known = " ".join(f"{k[k.index(',') + 2:-1]}:{v}" for k, v in sorted(self.logic.belief.items())
                             if k.startswith(("at(", "in(")))
            print(f"{t} {line:<34} belief {known or '-'}", flush=True)


class SkillPolicy(Flow):
    """The skill policy (F5, a VLA stand-in): runs the monitor's current skill with a scripted,
    state-feedback controller and emits an action chunk, its progress, and ``inspection_done``
    when an inspection has looked. For the skill named ``actor`` another flow's policy sends the
    chunks (:class:`SkillActor`): this one still runs the scripted skill on the world's
    observation, for its progress, success and failure only."""

    def __init__(self, horizon: float = 0.75, control_hz: float = 200.0, task: str = "drawers", actor: str = ""):
        self.horizon, self.control_hz, self.task, self.actor = horizon, control_hz, task, actor
        self.running_id, self.controller, self.inspected = 0, None, False

    def setup(self):
        # the skills' import (MuJoCo's constants) before the first tick, not in it
        if self.task == "bag":
            from .bag_skills import make_bag_skill as make_skill
        else:
            from .skills import make_skill
        self.make_skill = make_skill

    def step(self, skill: SkillCmd, obs: Observation, frame: Frame | None = None):
        if skill.skill_id != self.running_id:
            self.running_id, self.inspected = skill.skill_id, False
            self.controller = self.make_skill(skill.name, skill.arg)
        facts = dict(obs.facts, t=obs.t, qpos=obs.qpos, robot=obs.robot)
        out = self.controller.act(facts, round(self.horizon * self.control_hz), self.control_hz)
        result = {"progress": Progress(skill_id=skill.skill_id, t=obs.t, p=float(out.progress), status=out.status)}
        if skill.name != self.actor:
            result["chunk"] = ActionChunk(skill_id=skill.skill_id, actions=np.asarray(out.actions, dtype=np.float64))
        if skill.name in ("InspectDrawer", "InspectBag") and out.status == "done" and not self.inspected:
            self.inspected = True
            result["inspection"] = InspectionDone(skill_id=skill.skill_id, t=obs.t, drawer=skill.arg)
        return result


class SkillActor(Flow):
    """The scripted policy of one skill (``skill``, "Pick"), in its own flow: while the monitor's
    command is that skill, it turns what the robot senses (``state``, ``scene``, the ``wrist``
    frame: :mod:`agents.skill_features`) into the action chunk for the controller, with the
    scripted skill fed only those inputs (:class:`agents.skill_policies.ScriptedSkill`); otherwise
    it emits nothing (:class:`SkillPolicy` sends the other skills' chunks). Its step records hold
    exactly a policy's inputs and its action: what a dataset of the skill is made of
    (:class:`LearnedSkill` is the learned policy in the same slot)."""

    def __init__(self, skill: str = "Pick", horizon: float = 0.75, control_hz: float = 200.0,
                 policy_hz: float = 2.0, wrist_size: list | None = None):
        self.skill, self.horizon, self.control_hz = skill, horizon, control_hz
        self.policy_hz, self.wrist_size = policy_hz, tuple(wrist_size or (64, 64))
        self.running_id, self.ticks = 0, 0

    def setup(self):
        from .skill_policies import ScriptedSkill
        self.policy = ScriptedSkill()

    def teardown(self):
        del self.policy

    def step(self, skill: SkillCmd, state: np.ndarray, scene: np.ndarray, wrist: Frame | None = None):
        from .skill_policies import SkillObservation
        if skill.name != self.skill:
            return {}
        if skill.skill_id != self.running_id:
            self.running_id, self.ticks = skill.skill_id, 0
            self.policy.reset(str(skill))
        image = wrist.rgb if wrist is not None else np.zeros((*self.wrist_size, 3), dtype=np.uint8)
        seen = SkillObservation(t=self.ticks / self.policy_hz, skill=str(skill), state=np.asarray(state),
                                scene=np.asarray(scene), wrist=image)
        self.ticks += 1
        actions = self.policy.act(seen, round(self.horizon * self.control_hz), self.control_hz)
        return {"action": ActionChunk(skill_id=skill.skill_id, actions=np.asarray(actions, dtype=np.float64))}


class LearnedSkill(TorchPolicy):
    """A learned policy of one skill (``skill``, "Pick") in the slot of :class:`SkillActor`, the
    same ports: a :class:`retriever.learn.TorchPolicy` that runs the checkpoint directory ``path``
    (``python -m agents.learn train``: :class:`agents.learn.bc.PickMLP`'s ``policy.json`` and
    ``model.safetensors``) on the features the dataset export named (``state`` →
    ``observation.state``, ``scene`` → ``observation.environment_state``, the wrist frame →
    ``observation.images.wrist``); on the CPU its replay is exact. Its chunk's rows are absolute
    command targets; a chunk shorter than the controller needs holds its last row."""

    observation = ("state", "scene", "wrist")

    def __init__(self, path: str, skill: str = "Pick", horizon: float = 0.75, control_hz: float = 200.0,
                 wrist_size: list | None = None):
        super().__init__(path, features={"state": "observation.state", "scene": "observation.environment_state",
                                         "wrist": "observation.images.wrist"})
        self.skill, self.horizon, self.control_hz = skill, horizon, control_hz
        self.wrist_size = tuple(wrist_size or (64, 64))

    def build(self):
        from .learn.bc import make_module
        from .skill_policies import check_weights, read_config
        config = read_config(self.path)
        check_weights(self.path, config)
        return make_module(config)

    def step(self, skill: SkillCmd, state: np.ndarray, scene: np.ndarray, wrist: Frame | None = None):
        if skill.name != self.skill:
            return {}
        image = wrist.rgb if wrist is not None else np.zeros((*self.wrist_size, 3), dtype=np.uint8)
        rows = self.act(state=np.asarray(state), scene=np.asarray(scene), wrist=image)["chunk"]
        steps = round(self.horizon * self.control_hz)
        if rows.ndim != 2 or rows.shape[1] != NU or not len(rows):
            raise ValueError(f"{self._owner()}: its model returned a chunk of shape {rows.shape}: expected "
                             f"(steps, {NU})")
        rows = rows[:steps]
        if len(rows) < steps:
            rows = np.concatenate([rows, np.repeat(rows[-1:], steps - len(rows), axis=0)])
        return {"action": ActionChunk(skill_id=skill.skill_id, actions=rows.astype(np.float64))}


class SkillOrder(Flow):
    """Runs one skill and ends the run (``sys.exit(0)``) when the skill says done or failed:
    an episode of that skill alone, for collecting and evaluating it."""

    def __init__(self, skill: str = "Pick(spice)"):
        self.skill, self.said = skill, False

    def step(self, progress: list | None = None):
        if any(p.status != "running" for p in progress or ()):
            sys.exit(0)
        if self.said:
            return {}
        from .plan import parse_skill
        self.said = True
        parsed = parse_skill(self.skill, "drawers")
        return {"skill": SkillCmd(skill_id=1, name=parsed.name, arg=parsed.arg, source="plan")}


class Controller(Flow):
    """The 200 Hz controller (F6): plays the current action chunk's row, within the joints'
    limits and velocity limits, starting from ``home`` (the robot's parking command unless given).
    A row that is not finite is refused (a ValueError: the run stops rather than drive blind)."""

    def __init__(self, hz: float = 200.0, home: list | None = None):
        self.hz, self.start = hz, home
        self.last = None

    def setup(self):
        from . import world  # the robot's limits (and MuJoCo's import) before the first tick
        self.low, self.high = world.COMMAND_LOW, world.COMMAND_HIGH
        self.home = world.HOME if self.start is None else np.asarray(self.start, dtype=np.float64)
        self.limit = world.MAX_SPEED / self.hz

    def step(self, action: np.ndarray):
        target = np.asarray(action, dtype=np.float64)
        if not np.isfinite(target).all():
            raise ValueError(f"controller: the action row {target.tolist()} is not finite; a policy upstream sent "
                             "NaN or infinity, and no command is sent")
        target = np.clip(target, self.low, self.high)
        last = self.home if self.last is None else self.last
        limit = self.limit
        self.last = last + np.clip(target - last, -limit, limit)
        return {"command": Command(u=self.last.copy())}


class Teleop(Flow):
    """Teleoperation (Appendix E-k, E-n): interventions from a schedule file (JSON: a list of
    ``{"t_start", "t_end", "mode": "skill_override", "payload": "Pick(spice)"}``), sent when the
    world reaches their start; with ``recover=True``, a scripted operator who takes over after a
    failed skill: picks the spice up again when it dropped (in the bag task, opens the bag first
    when the target fell back into it), else re-runs the skill."""

    def __init__(self, schedule: str | None = None, recover: bool = False, task: str = "drawers"):
        self.schedule_path, self.recover, self.task = schedule, recover, task
        self.sent, self.failures_seen = 0, 0

    def setup(self):
        self.schedule = load_schedule(self.schedule_path, self.task) if self.schedule_path else []

    def step(self, obs: Observation, status: MonitorStatus | None = None):
        if self.sent < len(self.schedule) and self.schedule[self.sent]["t_start"] <= obs.t:
            item = self.schedule[self.sent]
            self.sent += 1
            return {"teleop": TeleopEvent(t_start=item["t_start"], t_end=item.get("t_end", item["t_start"]),
                                          mode="skill_override", payload=item["payload"])}
        if self.recover and status is not None and status.failures > self.failures_seen and status.last_failed:
            self.failures_seen = status.failures     # the operator takes over at once, by hand:
            pick = "Pick(target)" if self.task == "bag" else "Pick(spice)"
            dropped = status.last_failed in (pick, "Season(food)", "PlaceBack(spice)", "Extract(target)")
            payload = pick if dropped else status.last_failed   # picks it up again, or redoes it
            if dropped and obs.facts.get("object_location") == "bag" and not obs.facts.get("bag_opened"):
                payload = "OpenBag(bag)"    # it fell back into the bag, which springs shut: open it first
            return {"teleop": TeleopEvent(t_start=obs.t, t_end=obs.t, mode="skill_override", payload=payload)}
        return {}


#: the largest teleop schedule read (a schedule is a few interventions)
MAX_SCHEDULE_BYTES = 1 << 20


def load_schedule(path: str, task: str = "drawers") -> list[dict]:
    """A teleop schedule, checked: a list of interventions sorted by start time. The path comes
    from a flow's parameters, which an IR from elsewhere sets: only a regular file is read, and no
    error quotes what it holds (a worker's error goes back to whoever deployed it)."""
    from .plan import PlanError, parse_skill
    try:
        info = os.stat(path)
        if not stat.S_ISREG(info.st_mode) or info.st_size > MAX_SCHEDULE_BYTES:
            raise ValueError(f"not a regular file of at most {MAX_SCHEDULE_BYTES} bytes")
        with open(path, "rb") as f:
            items = json.loads(f.read(MAX_SCHEDULE_BYTES).decode("utf-8"))
    except json.JSONDecodeError as e:
        raise ValueError(f"teleop schedule {path}: not JSON (line {e.lineno}, column {e.colno})") from None
    except UnicodeDecodeError:
        raise ValueError(f"teleop schedule {path}: not UTF-8 text") from None
    except OSError as e:
        raise ValueError(f"teleop schedule {path}: {e.strerror}") from None
    except (ValueError, RecursionError) as e:
        raise ValueError(f"teleop schedule {path}: {e if isinstance(e, ValueError) else 'nested too deep'}") from None
    if not isinstance(items, list):
        raise ValueError(f"teleop schedule {path}: expected a JSON list of interventions")
    for i, item in enumerate(items):
        try:
            if not isinstance(item, dict):
                raise ValueError(f"expected an object with t_start and payload, got a {type(item).__name__}")
            for key in ("t_start", "t_end"):
                t = item.get(key, 0.0)
                if isinstance(t, bool) or not isinstance(t, (int, float)) or not 0 <= t < float("inf"):
                    raise ValueError(f"{key} must be a number of seconds >= 0")
            if "t_start" not in item:
                raise ValueError("needs a number t_start")
            if item.get("t_end", item["t_start"]) < item["t_start"]:
                raise ValueError("t_end is before t_start")
            if item.get("mode", "skill_override") != "skill_override":
                raise ValueError("mode must be 'skill_override'")
            if not isinstance(item.get("payload"), str):
                raise ValueError(f"payload must be a skill such as \"Pick(spice)\", got a "
                                 f"{type(item.get('payload')).__name__}")
            try:
                parse_skill(item["payload"], task)
            except PlanError:
                raise ValueError("payload is not a skill of the vocabulary, such as \"Pick(spice)\"") from None
        except (ValueError, KeyError, PlanError) as e:
            raise ValueError(f"teleop schedule {path}, item {i}: {e}") from None
    return sorted(items, key=lambda item: item["t_start"])
