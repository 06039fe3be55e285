"""Scripted skills of Retriever-0: state-feedback controllers standing in for the VLA.

A skill is a phase machine. Each phase plans a trajectory once, when it is entered, from the
reference command at that moment to the phase's goal (through collision-free waypoints), and
is left only when the *observed* state shows the goal reached (within tolerance), never because
time passed. Each call of :meth:`SkillController.act` returns the next chunk of that trajectory:

    obs (t) ─▶ phase machine ─▶ trajectory of the current phase, sampled at t, t+1/hz, …
                 │  advance when the observed state reaches the phase goal
                 └─ progress p (dense, monotone), status running | done | failed

Trajectories are indexed by observation time, so consecutive chunks join up whatever the
policy's latency is: a chunk computed from the observation at t starts applying at t + latency,
and so did the previous one, from its own t. Skills read ground truth from the observation
(handle and bottle poses, which fingers touch what): they stand in for a learned policy.

The phase machine (:class:`Trajectory`, :class:`Phase`, :class:`Recipe`, :class:`SkillController`)
serves any task: a task's :class:`SkillSet` names its recipes (``SKILL_SET`` here, for the
drawers; :mod:`agents.bag_skills` for the bag). ``run_skills`` emulates the agent's timing
(policy rate, latency, a rate-limited 200 Hz controller) around either world's sim, for tests
and benchmarks.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np

from .mjcf import TABLE_TOP
from .robot import COMMAND_HIGH, COMMAND_LOW, MAX_SPEED, pivot_for, tcp_of
from .world import (
    BOTTLE_HALF_HEIGHT, CLOSED_OPENING, DRAWERS, FLOOR_Z, HANDLE_STANDOFF, HANDLES, INTERIOR_FRONT, PLATE_POS,
    drawer_above, drawer_origin,
)

SKILL_ARGS = {
    "OpenDrawer": HANDLES, "InspectDrawer": DRAWERS, "CloseDrawer": HANDLES,
    "Pick": ("spice",), "Season": ("food",), "PlaceBack": ("spice",),
}
SKILLS = tuple(SKILL_ARGS)

# -- motion ------------------------------------------------------------------------------------
# Cruise speeds of planned segments, kept below MAX_SPEED so the controller's rate limit never
# bends a planned path.
TRANSIT = np.array([0.45, 0.45, 0.45, 3.5, 5.0])
FINE = np.array([0.2, 0.2, 0.2, 1.5, 5.0])               # the last centimetres to a handle or the bottle
PULL = np.array([0.3, 0.3, 0.3, 1.5, 5.0])               # drawers: gentle enough that a bottle stays standing
# m/s², rad/s², grip/s²: a bottle standing in a drawer being pulled neither slides nor tips
ACCEL = np.array([2.0, 2.0, 2.0, 15.0, 40.0])
Z_SAFE = 0.88           # TCP height for transit with the bottle: its bottom clears the cabinet top by 7 cm
Z_CLEAR = 0.82          # … and with an empty hand: the fingertips clear it by 3.5 cm
CABINET_ZONE_X = 0.34   # |x| beyond this is beside the cabinet (its sides are at ±0.30)
LOW_PASS_Z = 0.52       # the lowest TCP for going around the cabinet: clears the plate's food and a standing bottle
STANDOFF = 0.10         # pre-grasp distance in front of a handle (fingertips 7.5 cm from the bar)
OPEN_TARGET = 0.27      # how far OpenDrawer pulls: a bottom drawer's bottle is then reachable from above
OPEN_ENOUGH = 0.20      # the post-condition of OpenDrawer, and what Pick/PlaceBack need
FINGERS_FORWARD = np.pi / 2
PARK_X = 0.52           # InspectDrawer parks beside the cabinet, outside the head camera's view of any drawer
PARK_Y = -0.10
POUR_HEIGHT = 0.25      # TCP above the plate while pouring
POUR_PITCH = 2.2        # rad: the bottle's opening points 36° below horizontal
SHAKE = (0.2, 2.0)      # rad amplitude, Hz
SET_DOWN = np.array([0.45, -0.07])                     # beside the plate, clear of the drawers' path
PLACE_DEPTH = 0.10      # PlaceBack puts the bottle this far behind a drawer's front wall
GRASP_ABOVE_CENTRE = 0.01                              # TCP above the bottle's centre when grasping

# -- tolerances --------------------------------------------------------------------------------
AT_POSE = 0.008         # m, measured TCP to goal
AT_PITCH = 0.05         # rad
GRIP_OPEN = 0.12        # measured grip below this: the fingers have let go
SETTLED = 0.01          # m/s: the robot has stopped (for a picture)
IN_HAND = 0.07          # m: farther than this from the TCP, the bottle is not in the hand (it is 1-3 cm when held)
# m: a set-down bottle stands on its spot within this of it (under 2 mm off when the hand put it
# there); farther, it slipped and fell there
ON_SPOT = 0.02
PATIENCE = 3.0          # s a phase may take beyond its planned duration before the skill fails
POSE_SCALE = np.array([1.0, 1.0, 1.0, 0.1, 0.05])      # command-space distance: m, 10 cm/rad, 5 cm per full grip


# -- trajectories ------------------------------------------------------------------------------

@dataclass(frozen=True)
class _Profile:
    """A trapezoidal speed profile over [0, seconds] for a move of ``distance`` (per axis),
    synchronised on the axis that needs longest: accelerate, cruise, decelerate."""
    seconds: float
    ramp: float             # seconds of acceleration (and of deceleration)

    @classmethod
    def for_move(cls, distance, speed, accel=ACCEL) -> _Profile:
        distance, speed, accel = np.abs(distance), np.asarray(speed, float), np.asarray(accel, float)
        full = distance >= speed * speed / accel             # reaches cruise speed
        seconds = np.where(full, distance / speed + speed / accel, 2.0 * np.sqrt(distance / accel))
        axis = int(np.argmax(seconds))
        total = float(seconds[axis])
        ramp = float(speed[axis] / accel[axis]) if full[axis] else total / 2.0
        return cls(total, min(ramp, total / 2.0))

    def __call__(self, u: float) -> float:
        """Fraction of the way covered at ``u`` = elapsed / seconds."""
        tau, T, r = min(max(u, 0.0), 1.0) * self.seconds, self.seconds, self.ramp
        if T <= 0:
            return 1.0
        v = 1.0 / (T - r)                                    # cruise speed, in fractions per second
        if tau < r:
            return 0.5 * v / r * tau * tau
        if tau <= T - r:
            return v * (tau - r / 2.0)
        return 1.0 - 0.5 * v / r * (T - tau) ** 2


def command_at(tcp, pitch: float, grip: float) -> np.ndarray:
    """The command that puts the TCP at ``tcp`` with ``pitch`` and ``grip``."""
    return np.concatenate([pivot_for(tcp, pitch), [pitch, grip]])


class Trajectory:
    """Absolute commands as a function of seconds since the phase began: trapezoidal segments,
    then either a hold of the last command or an endless periodic motion."""

    def __init__(self, start):
        self.end = np.clip(np.asarray(start, dtype=np.float64), COMMAND_LOW, COMMAND_HIGH)
        self.start = self.end.copy()
        self.duration = 0.0
        self._segments: list = []           # (t_begin, seconds, f(u) -> command)
        self._tail: Callable | None = None

    def line(self, goal, speed=TRANSIT) -> Trajectory:
        """Straight in command space to ``goal``, timed by the slowest axis at cruise ``speed``."""
        a, b = self.end.copy(), np.clip(np.asarray(goal, dtype=np.float64), COMMAND_LOW, COMMAND_HIGH)
        profile = _Profile.for_move(b - a, speed)
        if profile.seconds > 1e-6:
            self._add(profile.seconds, lambda u: a + (b - a) * profile(u), b)
        return self

    def turn(self, pitch: float, speed=TRANSIT, grip: float | None = None) -> Trajectory:
        """Rotate the wrist to ``pitch`` about the TCP (the TCP stays where it is)."""
        a = self.end.copy()
        tcp, grip = tcp_of(a), a[4] if grip is None else grip
        profile = _Profile.for_move(np.array([pitch - a[3]]), speed[3:4], ACCEL[3:4])
        if profile.seconds > 1e-6:
            self._add(profile.seconds, lambda u: command_at(tcp, a[3] + (pitch - a[3]) * profile(u), grip),
                      command_at(tcp, pitch, grip))
        return self

    def grip(self, grip: float, speed=TRANSIT) -> Trajectory:
        return self.line(np.concatenate([self.end[:4], [grip]]), speed)

    def dwell(self, seconds: float) -> Trajectory:
        held = self.end.copy()
        self._add(seconds, lambda u: held, held)
        return self

    def forever(self, motion: Callable[[float], np.ndarray]) -> Trajectory:
        """After the segments, ``motion(seconds since they ended)`` instead of a hold."""
        self._tail = motion
        return self

    def _add(self, seconds: float, f: Callable, end) -> None:
        self._segments.append((self.duration, seconds, f))
        self.duration += seconds
        self.end = np.asarray(end, dtype=np.float64)

    def at(self, tau: float) -> np.ndarray:
        if tau >= self.duration:
            return self._tail(tau - self.duration) if self._tail else self.end.copy()
        for begin, seconds, f in self._segments:
            if tau < begin + seconds:
                return f((tau - begin) / seconds)
        return self.end.copy()

    def sample(self, tau0: float, steps: int, hz: float) -> np.ndarray:
        return np.array([self.at(tau0 + k / hz) for k in range(steps)])


# -- reading the observation -------------------------------------------------------------------
def robot(obs) -> np.ndarray:
    return np.asarray(obs["robot"], dtype=np.float64)


def at_command(obs, goal, tol: float = AT_POSE) -> bool:
    """The measured TCP and pitch are at ``goal``'s."""
    r = robot(obs)
    return (np.linalg.norm(tcp_of(r) - tcp_of(goal)) < tol) and abs(r[3] - goal[3]) < AT_PITCH


def settled(obs) -> bool:
    v = np.asarray(obs["robot_vel"], dtype=np.float64)
    return float(np.linalg.norm(v[:3])) < SETTLED and abs(v[3]) < 10 * SETTLED


def bottle_in_hand(obs) -> bool:
    return float(np.linalg.norm(np.subtract(obs["bottle_pos"], obs["tcp"]))) < IN_HAND


def holding_spice(obs) -> bool:
    """The fingers are closed on the bottle: it is at the hand, and they stopped on it (a pad
    may lose touch for a tick, so this does not ask the contacts)."""
    return bottle_in_hand(obs) and 0.3 < robot(obs)[4] < 0.9


def front_of(obs, drawer: str) -> float:
    """The y of an approach point in front of ``drawer``'s handle and of the open drawer above it."""
    y = obs["handles"][drawer + "-H"][1] - STANDOFF
    above = drawer_above(drawer)
    if above and obs["drawers"][above] > CLOSED_OPENING:
        y = min(y, obs["handles"][above + "-H"][1] - STANDOFF - 0.02)
    return y


def reachable_from_above(obs, drawer: str) -> str | None:
    """Why a drawer's inside cannot be reached from above, or None."""
    if obs["drawers"][drawer] < OPEN_ENOUGH:
        return f"{drawer} is open {obs['drawers'][drawer]:.2f} m, not the {OPEN_ENOUGH} m needed to reach into it"
    above = drawer_above(drawer)
    if above and obs["drawers"][above] > CLOSED_OPENING:
        return f"{above} is open above {drawer} and blocks the way down"
    return None


def add_transit(traj: Trajectory, obs, goal, grip: float) -> Trajectory:
    """Append a collision-free path from the trajectory's end to ``goal``.

    First let go of and back away from a handle the fingers are at. Then, if both ends are
    outside the cabinet's zone (beside it, or in front of every handle), go around it low, in
    front of everything; otherwise rise to the transit height (first stepping in front of any
    open drawer overhead), cross at that height and come down onto the goal. The height is
    ``Z_SAFE`` with the hand closed (it may hold the bottle), else ``Z_CLEAR``.
    """
    goal = np.asarray(goal, dtype=np.float64)
    _back_off_handle(traj, obs)
    if traj.end[4] > grip + 0.05:
        traj.grip(grip).dwell(0.1)
    tcp, goal_tcp = tcp_of(traj.end), tcp_of(goal)
    front = min(hp[1] for hp in obs["handles"].values()) - STANDOFF + 0.005
    if _outside_zone(tcp, front) and _outside_zone(goal_tcp, front):
        low = max(LOW_PASS_Z, goal_tcp[2])
        if tcp[1] > front:
            traj.line(command_at([tcp[0], front - 0.005, max(low, tcp[2])], traj.end[3], grip))
        traj.line(command_at([goal_tcp[0], front - 0.005, low], goal[3], grip))
        return traj.line(np.concatenate([goal[:4], [grip]]))
    height = Z_SAFE if grip > 0.5 else Z_CLEAR
    if tcp[2] < height - 0.005:
        y = min(tcp[1], _clear_overhead_y(obs, tcp))
        if y < tcp[1] - 0.005:
            traj.line(command_at([tcp[0], y, tcp[2]], traj.end[3], grip), PULL)
        traj.line(command_at([tcp[0], y, height], traj.end[3], grip))
    exit_xy = _zone_exit(tcp_of(traj.end)[:2], goal_tcp[:2], front)
    if exit_xy is not None:      # once out of the zone, head down to the goal at once
        traj.line(command_at([*exit_xy, max(height, goal_tcp[2])], goal[3], grip))
    else:
        traj.line(command_at([goal_tcp[0], goal_tcp[1], max(height, goal_tcp[2])], goal[3], grip))
    return traj.line(np.concatenate([goal[:4], [grip]]))


def _zone_exit(a, b, front: float):
    """Where the straight way from ``a`` to ``b`` (xy) leaves the cabinet's zone, if it does
    before ``b`` (the zone is convex, so it does not come back)."""
    a, b = np.asarray(a, float), np.asarray(b, float)
    d = b - a
    exits = []
    if abs(b[0]) > CABINET_ZONE_X and abs(d[0]) > 1e-9:
        exits.append((np.sign(b[0]) * CABINET_ZONE_X - a[0]) / d[0])
    if b[1] <= front and abs(d[1]) > 1e-9:
        exits.append((front - a[1]) / d[1])
    exits = [s for s in exits if 0.0 <= s < 0.95]
    return a + d * min(exits) if exits else None


def _back_off_handle(traj: Trajectory, obs) -> None:
    """With the fingers forward at a handle: open them and back away to the standoff."""
    cur, tcp = traj.end, tcp_of(traj.end)
    if cur[3] < 1.0:
        return
    for hp in obs["handles"].values():
        if abs(tcp[0] - hp[0]) < 0.08 and abs(tcp[2] - hp[2]) < 0.08 and tcp[1] > hp[1] - STANDOFF + 0.005:
            if cur[4] > 0.05:
                traj.grip(0.0).dwell(0.1)
            traj.line(command_at([tcp[0], hp[1] - STANDOFF, tcp[2]], cur[3], 0.0), PULL)
            return


def _outside_zone(tcp, front: float) -> bool:
    """Beside the cabinet or in front of every handle: only the low plate and bottle are there."""
    return abs(tcp[0]) > CABINET_ZONE_X or tcp[1] <= front


def _clear_overhead_y(obs, tcp) -> float:
    """A y in front of every open drawer above ``tcp`` in its column (rising there is free)."""
    y = tcp[1]
    for d in DRAWERS:
        o = drawer_origin(d)
        if (obs["drawers"][d] > CLOSED_OPENING and abs(tcp[0] - o[0]) < 0.22 and o[2] + 0.02 > tcp[2] - 0.1
                and tcp[1] > obs["handles"][d + "-H"][1] - STANDOFF):
            y = min(y, obs["handles"][d + "-H"][1] - STANDOFF)
    return y


# -- the phase machine -------------------------------------------------------------------------
@dataclass
class Phase:
    """One step of a skill: ``plan`` (observation, reference now → trajectory) runs when the
    phase is entered; ``reached`` says when the observed state shows its goal; ``check`` names a
    failure that makes the skill impossible; ``fraction`` is its share of progress so far."""
    name: str
    weight: float
    plan: Callable[[dict, np.ndarray], Trajectory]
    reached: Callable[[dict], bool]
    check: Callable[[dict], str | None] = lambda obs: None
    fraction: Callable[[dict], float] | None = None
    patience: float = PATIENCE
    retries: int = 0        # times the phase is planned afresh (from a new observation) before failing
    stalled: str = ""       # the failure's reason when it never gets there


@dataclass
class SkillOutput:
    actions: np.ndarray     # (steps, NU): absolute command targets, one row per control tick
    progress: float         # p in [0, 1], from the observed state
    status: str             # "running" | "done" | "failed"
    phase: str = ""         # the phase running (for logs and tests)
    reason: str = ""        # why it failed


@dataclass(frozen=True)
class SkillSet:
    """A task's skills: the arguments each takes (in the order errors list them), its
    :class:`Recipe`, and what errors call one of them."""
    args: dict[str, tuple[str, ...]]
    recipes: dict[str, type[Recipe]]
    noun: str = "skill"

    def recipe(self, name: str, arg: str) -> Recipe:
        """Skill ``name``'s recipe for ``arg``; a ValueError lists the valid skills or arguments."""
        if name not in self.args:
            raise ValueError(f"unknown {self.noun} {name!r}: expected one of {', '.join(self.args)}")
        if arg not in self.args[name]:
            raise ValueError(f"{name}({arg!r}): unknown argument, expected one of {', '.join(self.args[name])}")
        return self.recipes[name](arg)


class SkillController:
    """One skill invocation, e.g. ``SkillController("OpenDrawer", "TR-H")``: call :meth:`act`
    with each new observation; after "done" or "failed" it keeps answering the same and holds
    the robot still. ``skills``: the task's skill set (the drawer skills' ``SKILL_SET`` unless given)."""

    def __init__(self, name: str, arg: str, skills: SkillSet | None = None):
        self.name, self.arg = name, arg
        self.recipe = (skills or SKILL_SET).recipe(name, arg)
        self.status, self.progress, self.reason = "running", 0.0, ""
        self.phases: list[Phase] | None = None
        self.index = 0
        self._traj: Trajectory | None = None
        self._t0 = 0.0
        self._hold: np.ndarray | None = None
        self._tries = 0

    def __repr__(self) -> str:
        return f"SkillController({self.name}({self.arg}), {self.status}, p={self.progress:.2f})"

    def act(self, obs: dict, steps: int, control_hz: float) -> SkillOutput:
        t = float(obs["t"])
        if self.status == "running":
            self._step(obs, t)
        if self.status != "running":
            if self._hold is None:
                self._hold = self._reference(obs, t)
            actions = np.repeat(self._hold[None, :], steps, axis=0)
        else:
            actions = self._traj.sample(t - self._t0, steps, control_hz)
        name = self.phases[self.index].name if self.phases and self.index < len(self.phases) else self.status
        return SkillOutput(actions, self.progress, self.status, name, self.reason)

    def _reference(self, obs, t) -> np.ndarray:
        """The command the trajectory gives now (the controller's own command before any)."""
        if self._traj is None:
            return np.asarray(obs["command"], dtype=np.float64)
        return self._traj.at(t - self._t0)

    def _step(self, obs, t) -> None:
        if self.phases is None:
            start = self.recipe.start(obs)
            if isinstance(start, str):
                return self._fail(start, obs, t)
            self.phases = start
            self._enter(obs, t)
        for _ in range(len(self.phases)):           # several phases may already hold
            if self.index >= len(self.phases):
                break
            phase = self.phases[self.index]
            if not phase.reached(obs):
                problem = phase.check(obs)
                if problem:
                    return self._fail(problem, obs, t)
                if t - self._t0 > self._traj.duration + phase.patience:
                    if self._tries >= phase.retries:
                        return self._fail(phase.stalled or f"{phase.name} did not reach its goal in time", obs, t)
                    self._tries += 1
                    self._enter(obs, t, retry=True)
                break
            self.index += 1
            if self.index < len(self.phases):
                self._enter(obs, t)
        self._update_progress(obs)
        if self.index >= len(self.phases):
            problem = self.recipe.postcondition(obs)
            if problem:
                return self._fail(problem, obs, t)
            self.status, self.progress = "done", 1.0

    def _enter(self, obs, t, retry: bool = False) -> None:
        self._tries = self._tries if retry else 0
        ref = self._reference(obs, t)
        self._traj = self.phases[self.index].plan(obs, ref)
        self._t0 = t

    def _fail(self, reason: str, obs, t) -> None:
        self.status, self.reason = "failed", reason
        self._hold = self._reference(obs, t)

    def _update_progress(self, obs) -> None:
        total = sum(p.weight for p in self.phases)
        done = sum(p.weight for p in self.phases[:self.index])
        if self.index < len(self.phases):
            phase = self.phases[self.index]
            f = phase.fraction(obs) if phase.fraction else self._distance_fraction(obs)
            done += phase.weight * min(max(f, 0.0), 0.95)
        p = done / total * self.recipe.cap
        self.progress = max(self.progress, min(p, 0.99))

    def _distance_fraction(self, obs) -> float:
        """How far the measured robot has come from the phase's start to its end, in command space."""
        traj = self._traj
        span = float(np.linalg.norm((traj.end - traj.start) * POSE_SCALE))
        if span < 1e-6:
            return 0.0
        left = float(np.linalg.norm((traj.end - robot(obs)) * POSE_SCALE))
        return 1.0 - left / span


def make_skill(name: str, arg: str) -> SkillController:
    return SkillController(name, arg)


# -- the skills --------------------------------------------------------------------------------
class Recipe:
    """What one skill is: its phases for the state it starts in (or why it cannot start), and
    its post-condition. ``cap`` scales progress before "done" (InspectDrawer keeps it under the
    monitor's hand-off threshold until the picture can be taken)."""
    cap = 1.0

    def __init__(self, arg: str):
        self.arg = arg

    def start(self, obs) -> list[Phase] | str:
        raise NotImplementedError

    def postcondition(self, obs) -> str | None:
        return None


class _DrawerRecipe(Recipe):
    """Shared by OpenDrawer and CloseDrawer: pinch the handle's bar from above and below
    (fingers forward), move the drawer to ``target`` with it, let go and back away."""
    target = 0.0

    def __init__(self, arg: str):
        super().__init__(arg)
        self.drawer, self.handle = arg[:2], arg

    def start(self, obs):
        if holding_spice(obs):
            return f"the hand holds the spice: it cannot take {self.handle}"
        return [self._grasp(), self._move()]

    def moved(self, obs) -> bool:
        raise NotImplementedError

    def _grasp(self) -> Phase:
        def plan(obs, ref):
            hp = np.asarray(obs["handles"][self.handle])
            pre = command_at([hp[0], hp[1] - STANDOFF, hp[2]], FINGERS_FORWARD, 0.0)
            approach = command_at([hp[0], front_of(obs, self.drawer), hp[2]], FINGERS_FORWARD, 0.0)
            traj = add_transit(Trajectory(ref), obs, approach, 0.0).line(pre, PULL)
            return traj.line(command_at(hp, FINGERS_FORWARD, 0.0), FINE).dwell(0.1).grip(1.0)

        return Phase("grasp", 0.45, plan, lambda obs: obs["held"] == self.handle and robot(obs)[4] > 0.5,
                     patience=1.0, retries=2, stalled=f"the fingers did not close on {self.handle}")

    def _move(self) -> Phase:
        goal, start = {}, {}

        def plan(obs, ref):
            # the drawer moves with the pinching fingers, so the travel left is measured on the
            # drawer's own joint (not on the handle's estimated position)
            tcp, opening = tcp_of(ref), obs["drawers"][self.drawer]
            to = command_at([tcp[0], tcp[1] - (self.target - opening), tcp[2]], ref[3], 1.0)
            back_y = tcp[1] - (max(self.target, 0.0) - opening) - STANDOFF
            goal["back"] = command_at([tcp[0], back_y, tcp[2]], ref[3], 0.0)
            start["opening"] = opening
            return Trajectory(ref).line(to, PULL).grip(0.0).dwell(0.05).line(goal["back"], PULL)

        def check(obs):
            if not self.moved(obs) and obs["held"] != self.handle:
                return f"lost hold of {self.handle} with {self.drawer} at {obs['drawers'][self.drawer]:.3f} m"
            return None

        def reached(obs):
            return (self.moved(obs) and obs["held"] == "" and robot(obs)[4] < GRIP_OPEN
                    and at_command(obs, goal["back"], 0.015))

        def fraction(obs):
            span = self.target - start["opening"]
            moved = 1.0 if abs(span) < 1e-3 else (obs["drawers"][self.drawer] - start["opening"]) / span
            return 0.8 * min(moved, 1.0) + 0.2 * (robot(obs)[4] < GRIP_OPEN)

        return Phase("pull" if self.target > 0 else "push", 0.55, plan, reached, check, fraction)


class OpenDrawer(_DrawerRecipe):
    target = OPEN_TARGET

    def moved(self, obs):
        return obs["drawers"][self.drawer] >= OPEN_TARGET - 0.012

    def postcondition(self, obs):
        o = obs["drawers"][self.drawer]
        return None if o >= OPEN_ENOUGH else f"{self.drawer} is open only {o:.3f} m"


class CloseDrawer(_DrawerRecipe):
    target = -0.004        # push 4 mm past shut: the drawer's stop takes the rest, the pinch stays firm

    def moved(self, obs):
        return obs["drawers"][self.drawer] < 0.6 * CLOSED_OPENING

    def postcondition(self, obs):
        o = obs["drawers"][self.drawer]
        return None if o < CLOSED_OPENING else f"{self.drawer} is still open {o:.3f} m"


class InspectDrawer(Recipe):
    """Park beside the cabinet, out of the head camera's view of ``arg``, and keep still: the
    belief reads the head camera's next frame. Progress stays below 0.9 until then, so the
    monitor cannot hand off before the picture exists."""
    cap = 0.85

    def start(self, obs):
        side = -1.0 if self.arg[1] == "L" else 1.0
        grip = 1.0 if holding_spice(obs) else 0.0
        park = command_at([side * PARK_X, PARK_Y, Z_SAFE if grip else Z_CLEAR], 0.0, grip)

        def plan(obs, ref):
            return add_transit(Trajectory(ref), obs, park, grip)

        return [Phase("park", 1.0, plan, lambda obs: at_command(obs, park, 0.01) and settled(obs))]


class _BottleRecipe(Recipe):
    """Shared by Pick, Season and PlaceBack: take the bottle, carry it, set it down."""

    def _take(self, obs) -> list[Phase] | str:
        """Reach the standing bottle from above and close on it, then lift it to ``Z_SAFE``; only
        the lift if it is in the hand already."""
        lift = Phase("lift", 0.35, self._plan_lift,
                     lambda obs: obs["grasped"] and tcp_of(robot(obs))[2] > Z_SAFE - 0.015, self._keep_hold)
        if holding_spice(obs):
            return [lift]
        problem = self._reachable(obs)
        if problem:
            return problem
        if obs["bottle_upright"] < 0.9:
            return "the bottle is not standing: it cannot be taken from above"

        def plan(obs, ref):
            b = np.asarray(obs["bottle_pos"])
            grasp = b + [0.0, 0.0, GRASP_ABOVE_CENTRE]
            traj = add_transit(Trajectory(ref), obs, command_at(grasp + [0, 0, 0.09], 0.0, 0.0), 0.0)
            return traj.line(command_at(grasp, 0.0, 0.0), FINE).dwell(0.1).grip(1.0)

        def check(obs):
            if obs["bottle_upright"] < 0.9:
                return "the bottle was knocked over"
            return self._reachable(obs)

        grasp = Phase("grasp", 0.65, plan, lambda obs: obs["held"] == "spice" and robot(obs)[4] > 0.3, check,
                      patience=1.0, retries=2, stalled="the fingers did not close on the spice")
        return [grasp, lift]

    @staticmethod
    def _plan_lift(obs, ref):
        tcp = tcp_of(ref)
        return Trajectory(ref).line(command_at([tcp[0], tcp[1], Z_SAFE], 0.0, 1.0), PULL)

    @staticmethod
    def _keep_hold(obs) -> str | None:
        return None if holding_spice(obs) else "the bottle slipped out of the hand"

    @staticmethod
    def _reachable(obs) -> str | None:
        where = obs["bottle_location"]
        if where in DRAWERS:
            return reachable_from_above(obs, where)
        if where in ("table", "plate", "gripper"):
            return None
        return f"the bottle is not where the hand can take it ({where})"

    def _set_down(self, name: str, weight: float, above_xy, support_z: float, route) -> list[Phase]:
        """Bring the held bottle above ``above_xy`` (``route(traj, obs, goal)``), lower it until it
        stands there on ``support_z``, open the hand and rise clear of it. Standing at that height
        is not enough: a bottle that slipped on the way may stand on something lower, such as the
        table below a top drawer."""
        def plan_lower(obs, ref):
            hand_to_bottom = obs["tcp"][2] - (obs["bottle_pos"][2] - BOTTLE_HALF_HEIGHT)
            low = command_at([above_xy[0], above_xy[1], support_z + hand_to_bottom + 0.002], 0.0, 1.0)
            high = command_at([above_xy[0], above_xy[1], support_z + hand_to_bottom + 0.04], 0.0, 1.0)
            return route(Trajectory(ref), obs, high).line(low, FINE)

        def standing(obs):
            on_spot = np.hypot(*np.subtract(obs["bottle_pos"][:2], above_xy)) < ON_SPOT
            return (on_spot and obs["bottle_pos"][2] - BOTTLE_HALF_HEIGHT < support_z + 0.006
                    and obs["bottle_upright"] > 0.95)

        return [Phase(name, weight, plan_lower, standing, self._keep_hold), let_go("bottle_upright", "the bottle")]


def let_go(upright: str, what: str) -> Phase:
    """Open the hand, then rise 10 cm straight up: done when the fingers are open, nothing is held
    and the hand is up; failed if ``what`` (its uprightness in ``obs[upright]``) fell over."""
    goal = {}

    def plan(obs, ref):
        tcp = tcp_of(ref)
        goal["up"] = command_at([tcp[0], tcp[1], tcp[2] + 0.10], 0.0, 0.0)
        return Trajectory(ref).grip(0.0).dwell(0.05).line(goal["up"], PULL)

    def released(obs):
        return robot(obs)[4] < GRIP_OPEN and obs["held"] == "" and at_command(obs, goal["up"], 0.015)

    def check(obs):
        return None if obs[upright] > 0.9 else f"{what} fell over when let go"

    return Phase("let go", 0.15, plan, released, check)


class Pick(_BottleRecipe):
    def start(self, obs):
        return self._take(obs)

    def postcondition(self, obs):
        return None if obs["grasped"] else "the bottle is not in the hand"


class Season(_BottleRecipe):
    """Tilt the bottle over the plate and shake it until the world counts the food seasoned,
    then stand it on the table beside the plate and let go (the next skill needs the hand)."""

    def start(self, obs):
        if not holding_spice(obs):
            return "the hand does not hold the spice"
        over = np.array([PLATE_POS[0], PLATE_POS[1], PLATE_POS[2] + POUR_HEIGHT])

        def plan_pour(obs, ref):
            return add_transit(Trajectory(ref), obs, command_at(over, 0.0, 1.0), 1.0).turn(POUR_PITCH)

        def pouring(obs):
            return obs["bottle_upright"] < -0.35 and np.hypot(*np.subtract(obs["bottle_pos"][:2], over[:2])) < 0.1

        def plan_shake(obs, ref):
            amplitude, hz = SHAKE
            tcp = tcp_of(ref)
            return Trajectory(ref).forever(
                lambda tau: command_at(tcp, POUR_PITCH + amplitude * np.sin(2 * np.pi * hz * tau), 1.0))

        def upright_then_across(traj, obs, goal):
            # in free space beside the cabinet: straighten up while moving over to the spot
            return traj.line(command_at(tcp_of(traj.end), POUR_PITCH, 1.0)).line(goal)

        return [
            Phase("pour", 0.3, plan_pour, pouring, self._keep_hold),
            Phase("shake", 0.3, plan_shake, lambda obs: obs["seasoned"], self._keep_hold,
                  fraction=lambda obs: obs["season_time"]),
            *self._set_down("set down", 0.25, SET_DOWN, TABLE_TOP, upright_then_across),
        ]

    def postcondition(self, obs):
        if not obs["seasoned"]:
            return "the food was not seasoned"
        if obs["bottle_location"] != "table" or obs["bottle_upright"] < 0.9 or obs["held"]:
            return f"the bottle was not left standing on the table ({obs['bottle_location']})"
        return None


class PlaceBack(_BottleRecipe):
    """Put the bottle back in the drawer it came from (``bottle_home``), which must be open:
    take it first if the hand is empty, stand it behind the front wall, let go, rise."""

    def start(self, obs):
        home = obs["bottle_home"]
        problem = reachable_from_above(obs, home)
        if problem:
            return problem
        take = self._take(obs)
        if isinstance(take, str):
            return take
        origin = drawer_origin(home)
        front = obs["handles"][home + "-H"][1] + HANDLE_STANDOFF + INTERIOR_FRONT
        spot = np.array([origin[0], front + PLACE_DEPTH])

        def route(traj, obs, goal):
            return add_transit(traj, obs, goal, 1.0)

        return [*take, *self._set_down("put back", 0.3, spot, origin[2] + FLOOR_Z, route)]

    def postcondition(self, obs):
        home = obs["bottle_home"]
        if obs["bottle_location"] != home or obs["held"]:
            return f"the bottle is not back in {home}, free of the hand ({obs['bottle_location']})"
        return None


SKILL_SET = SkillSet(SKILL_ARGS, {
    "OpenDrawer": OpenDrawer, "InspectDrawer": InspectDrawer, "CloseDrawer": CloseDrawer,
    "Pick": Pick, "Season": Season, "PlaceBack": PlaceBack,
})


# -- the agent's timing, emulated ---------------------------------------------------------------
class SkillRun(NamedTuple):
    skill: str              # "OpenDrawer(TR-H)"
    status: str             # "done" | "failed" | "timeout" | "handed off"
    seconds: float          # simulated seconds from its start to its end
    progress: float
    reason: str = ""
    trace: tuple = ()       # (t, p, status, phase) of every policy call


@dataclass
class _Player:
    """The controller side: the newest chunk that has started, rate-limited to MAX_SPEED."""
    command: np.ndarray
    hz: float
    chunks: list = field(default_factory=list)      # (first tick, actions), oldest first

    def tick(self, tick: int) -> np.ndarray:
        while len(self.chunks) > 1 and self.chunks[1][0] <= tick:
            self.chunks.pop(0)
        if self.chunks and self.chunks[0][0] <= tick:
            start, actions = self.chunks[0]
            target = np.clip(actions[min(tick - start, len(actions) - 1)], COMMAND_LOW, COMMAND_HIGH)
            limit = MAX_SPEED / self.hz
            self.command = self.command + np.clip(target - self.command, -limit, limit)
        return self.command


def run_skills(sim, plan, policy_hz: float = 2.0, control_hz: float = 200.0, latency: float = 0.2,
               timeout: float = 20.0, chunk_seconds: float = 0.75, obs_delay: float = 0.0,
               handoff: str = "done", stop_on_failure: bool = True, on_tick=None,
               make: Callable[[str, str], SkillController] = make_skill) -> list[SkillRun]:
    """Run ``plan`` (a list of ``(name, arg)``) on ``sim`` the way Retriever-0 does.

    Every 1/policy_hz s the running skill gets the observation taken ``obs_delay`` earlier and
    returns a chunk, which starts applying ``latency`` later; a ``control_hz`` controller plays
    the newest started chunk's rows, rate-limited by ``MAX_SPEED``, and physics advances one
    control period per row. A skill ends when it says done or failed (``handoff="progress"``:
    also once p ≥ 0.9 for 0.5 s, like the monitor), or after ``timeout`` s. ``on_tick(sim, i, t)``
    runs after every control tick of skill ``i``, ``t`` being ``sim.time`` (failure injection).
    ``make(name, arg)`` makes each skill's controller: ``make_bag_skill`` runs the bag's skills.
    """
    period = round(control_hz / policy_hz)
    delay, lag, steps = round(obs_delay * control_hz), round(latency * control_hz), round(chunk_seconds * control_hz)
    dt = 1.0 / control_hz
    player = _Player(np.asarray(sim.observe()["command"], dtype=np.float64), control_hz)
    results, tick, captured = [], 0, None
    for i, (name, arg) in enumerate(plan):
        skill, begin, above_since, status = make(name, arg), tick, None, None
        out, trace = None, []
        while status is None:
            if delay and (tick + delay) % period == 0:
                captured = sim.observe()
            if tick % period == 0:
                obs = captured if delay and captured is not None else sim.observe()
                out = skill.act(obs, steps, control_hz)
                trace.append((round(float(obs["t"]), 9), out.progress, out.status, out.phase))
                player.chunks.append((tick + lag, out.actions))
                if out.progress >= 0.9:
                    above_since = tick if above_since is None else above_since
                else:
                    above_since = None
                if out.status != "running":
                    status = out.status
                elif handoff == "progress" and above_since is not None and tick - above_since >= 0.5 * control_hz:
                    status = "handed off"
                elif (tick - begin) * dt >= timeout:
                    status = "timeout"
                if status is not None:
                    break
            sim.command(player.tick(tick))
            sim.advance(dt)
            tick += 1
            if on_tick is not None:
                on_tick(sim, i, sim.time)
        results.append(SkillRun(f"{name}({arg})", status, round((tick - begin) * dt, 3), out.progress, out.reason,
                                tuple(trace)))
        if status in ("failed", "timeout") and stop_on_failure:
            break
    return results


PAPER_TRACE = (("OpenDrawer", "{first}-H"), ("InspectDrawer", "{first}"), ("CloseDrawer", "{first}-H"),
               ("OpenDrawer", "{target}-H"), ("InspectDrawer", "{target}"), ("Pick", "spice"),
               ("Season", "food"), ("CloseDrawer", "{target}-H"))


def paper_trace(target: str, first: str | None = None) -> list[tuple[str, str]]:
    """The paper's trace: look into a wrong drawer first (TL, or TR when the spice is in TL),
    then fetch from ``target``, season, and close it."""
    first = first or ("TR" if target == "TL" else "TL")
    return [(name, arg.format(first=first, target=target)) for name, arg in PAPER_TRACE]


def pick_start(layout) -> tuple[dict, np.ndarray]:
    """Where Pick begins in the task (a drawer world's ``Layout``): the drawers' openings (the
    spice's drawer as OpenDrawer leaves it, open 0.258-0.27 m by the seed, the others shut) and
    the command of the hand parked as InspectDrawer leaves it, empty and open, beside the
    cabinet on that drawer's side."""
    drawer = layout.target_drawer
    opening = float(np.random.default_rng([layout.seed, 36]).uniform(OPEN_TARGET - 0.012, OPEN_TARGET))
    side = -1.0 if drawer[1] == "L" else 1.0
    return {drawer: opening}, command_at([side * PARK_X, PARK_Y, Z_CLEAR], 0.0, 0.0)
