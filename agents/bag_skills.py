"""Scripted skills for the bag world: open the bag, look into it, pick the target out of it and
put it on the tray's spot. They are phase machines built from :mod:`agents.skills`' parts
(trajectories, phases, the controller that runs them), reading the observation of
:class:`~agents.bag_world.BagSim`:

    OpenBag(bag)      closed fingers in through the narrow mouth, spread, draw the mouth towards
                      the robot, and hold it so (the paper springs back shut when let go of)
    InspectBag(bag)   keep holding the mouth open and keep still (the head camera's picture is
                      taken then); with no hand in the bag, park out of the camera's view instead
    Pick(target)      slide the spread fingers over the target, down around it, close, lift it
                      out (the mouth closes behind the fingers as they rise)
    Extract(target)   carry it over to the spot, stand it there, let go, rise

``run_skills(sim, plan, make=make_bag_skill)`` runs a plan of them with the agent's timing.
"""

from __future__ import annotations

import numpy as np

from .bag_world import BAG_INNER, BAG_RIM, OPENED, SPOT_POS, SPOT_RADIUS, TARGET_HALF_HEIGHT, TRAY_POS
from .robot import FINGER_LENGTH, HOME, PALM_BOTTOM, TCP_OFFSET, tcp_of
from .skills import (
    FINE,
    PULL,
    Phase,
    Recipe,
    SkillController,
    SkillSet,
    Trajectory,
    at_command,
    command_at,
    let_go,
    robot,
    settled,
)

BAG_SKILL_ARGS = {"OpenBag": ("bag",), "InspectBag": ("bag",), "Pick": ("target",), "Extract": ("target",)}
BAG_SKILLS = tuple(BAG_SKILL_ARGS)

# -- motion ------------------------------------------------------------------------------------
# Grip speed while the fingers spread the mouth: fast finger motion makes them tunnel through the paper (notes §5).
SPREAD = np.array([0.2, 0.2, 0.2, 1.5, 1.5])
Z_CARRY = BAG_RIM + 0.14        # TCP height between places: a held target's bottom clears the rim by 7 cm
PUSH_DEPTH = 0.03               # fingertips below the rim while spreading: 1.4 cm above the target's top
TIPS_BELOW_TCP = PALM_BOTTOM + FINGER_LENGTH - TCP_OFFSET
# Where the hand spreads the mouth: 4 cm left of the bag's axis, so that the near finger (4 cm
# wide) is out of the head camera's lines of sight to the target (the camera is to the right),
# then it draws the mouth 4 cm towards the robot (and the camera): the near rim stops hiding it.
HOLD_X = -0.04
DRAW = 0.04
GRIP_AROUND = 0.4               # fingers' opening while reaching around a target outside the bag
PARK = tcp_of(HOME)             # InspectBag parks at HOME's TCP when there is no bag to hold open
HOLD_STILL = 0.3                # s InspectBag holds the mouth open and still (the walls settle) before it is done

# -- tolerances --------------------------------------------------------------------------------
SPREAD_OPEN = 0.5               # measured grip below this: the fingers are spread (the walls stop them near 0.15)
STOPPED = 0.05                  # grip/s: the spreading fingers have stopped against the walls
IN_HAND = 0.07                  # m: the target is in the hand closer than this to the TCP (2-4 cm held)
CLEAR_OF_BAG = 0.02             # the lifted target's bottom this far above the rim: out of the bag


# -- reading the observation -------------------------------------------------------------------
def target_in_hand(obs) -> bool:
    return float(np.linalg.norm(np.subtract(obs["object_pos"], obs["tcp"]))) < IN_HAND


def holding_target(obs) -> bool:
    """The fingers are closed on the target (they stopped on it, so they are not shut)."""
    return target_in_hand(obs) and 0.3 < robot(obs)[4] < 0.9


def target_bottom(obs) -> float:
    return obs["object_pos"][2] - TARGET_HALF_HEIGHT


def hand_in_bag(obs) -> bool:
    """The TCP is in the bag's mouth, below the rim (the fingers are between its walls)."""
    x, y, z = obs["tcp"]
    bx, by, rim = obs["bag_pos"]
    return abs(x - bx) < BAG_INNER[0] and abs(y - by) < BAG_INNER[1] + 0.03 and z < rim + 0.01


def holding_bag_open(obs) -> bool:
    """The spread fingers hold the mouth open (it closes when they let go)."""
    return hand_in_bag(obs) and obs["bag_opened"] and robot(obs)[4] < SPREAD_OPEN


def add_carry(traj: Trajectory, goal, grip: float) -> Trajectory:
    """Append a way from the trajectory's end to ``goal``: set the grip, rise to ``Z_CARRY``,
    cross at that height (nothing on the table reaches it), come straight down onto the goal."""
    goal = np.asarray(goal, dtype=np.float64)
    if abs(traj.end[4] - grip) > 0.05:
        traj.grip(grip).dwell(0.1)
    tcp, goal_tcp = tcp_of(traj.end), tcp_of(goal)
    if tcp[2] < Z_CARRY - 0.005:
        traj.line(command_at([tcp[0], tcp[1], Z_CARRY], traj.end[3], grip), PULL)
    traj.line(command_at([goal_tcp[0], goal_tcp[1], max(Z_CARRY, tcp_of(traj.end)[2])], goal[3], grip))
    return traj.line(np.concatenate([goal[:4], [grip]]))


# -- the skills --------------------------------------------------------------------------------
class OpenBag(Recipe):
    """Push the closed fingers in through the narrow mouth, spread them so the walls give, and
    draw the spread mouth towards the robot; then hold it so (done while holding: the paper
    springs back shut once the fingers let go)."""

    def start(self, obs):
        if holding_target(obs):
            return "the hand holds the target: it cannot open the bag"
        if holding_bag_open(obs):
            return [Phase("open already", 1.0, lambda obs, ref: Trajectory(ref), lambda obs: True)]
        hold = np.add(obs["bag_pos"], [HOLD_X, 0.0, TIPS_BELOW_TCP - PUSH_DEPTH])
        inside = command_at(hold, 0.0, 1.0)
        up = command_at([hold[0], hold[1], Z_CARRY], 0.0, 1.0)
        drawn = command_at(hold - [0.0, DRAW, 0.0], 0.0, 0.0)
        start = {}

        def plan_push(obs, ref):
            return add_carry(Trajectory(ref), up, 1.0).line(inside, FINE)

        def plan_spread(obs, ref):
            start["opening"] = obs["bag_opening"]
            return Trajectory(ref).grip(0.0, SPREAD).dwell(0.2)

        def spread(obs):
            return obs["bag_opened"] and robot(obs)[4] < SPREAD_OPEN and abs(obs["robot_vel"][4]) < STOPPED

        def widened(obs):
            return (obs["bag_opening"] - start["opening"]) / max(OPENED - start["opening"], 1e-3)

        def plan_draw(obs, ref):
            return Trajectory(ref).line(drawn, FINE).dwell(0.1)

        def still_open(obs):
            return None if obs["bag_opened"] else f"the mouth closed again ({obs['bag_opening']:.3f} m wide)"

        return [
            Phase("push in", 0.4, plan_push, lambda obs: at_command(obs, inside), patience=1.5,
                  stalled="the fingers could not push in through the mouth"),
            Phase("spread", 0.35, plan_spread, spread, fraction=widened, patience=1.0,
                  stalled="the mouth did not widen: the bag's walls did not give"),
            Phase("draw", 0.25, plan_draw, lambda obs: at_command(obs, drawn, 0.01) and settled(obs), still_open),
        ]

    def postcondition(self, obs):
        return None if obs["bag_opened"] else f"the bag is open only {obs['bag_opening']:.3f} m"


class InspectBag(Recipe):
    """Keep still while the head camera looks: holding the mouth open if the fingers are in it,
    else parked out of the camera's view of the bag. The belief reads the head camera's next
    frame; progress stays below 0.9 until then (the monitor's hand-off)."""
    cap = 0.85

    def start(self, obs):
        if holding_bag_open(obs):
            since = {}

            def plan_hold(obs, ref):
                since["t"] = obs["t"]
                return Trajectory(ref).dwell(HOLD_STILL)

            def still(obs):
                return settled(obs) and obs["t"] >= since["t"] + HOLD_STILL

            def still_open(obs):
                return None if obs["bag_opened"] else f"the mouth closed ({obs['bag_opening']:.3f} m wide)"

            return [Phase("hold open", 1.0, plan_hold, still, still_open)]
        grip = 1.0 if holding_target(obs) else 0.0
        park = command_at(PARK, 0.0, grip)

        def plan(obs, ref):
            return add_carry(Trajectory(ref), park, grip)

        return [Phase("park", 1.0, plan, lambda obs: at_command(obs, park, 0.01) and settled(obs))]


class _TargetRecipe(Recipe):
    """Shared by Pick and Extract: take the target from above, lift it clear of the bag."""

    def _lift(self) -> Phase:
        def plan(obs, ref):
            tcp = tcp_of(ref)
            return Trajectory(ref).line(command_at([tcp[0], tcp[1], Z_CARRY], 0.0, 1.0), PULL)

        def lifted(obs):
            return obs["grasped"] and target_bottom(obs) > BAG_RIM + CLEAR_OF_BAG

        return Phase("lift", 0.35, plan, lifted, self._keep_hold)

    def _take(self, obs) -> list[Phase] | str:
        if holding_target(obs):
            return [self._lift()]
        problem = self._reachable(obs)
        if problem:
            return problem
        if obs["object_upright"] < 0.9:
            return "the target is not standing: it cannot be taken from above"

        def plan(obs, ref):
            top = np.asarray(obs["object_pos"]) + [0.0, 0.0, TARGET_HALF_HEIGHT]
            if hand_in_bag(obs):        # spread (again), slide over the target at this height, go down around it
                tcp = tcp_of(ref)
                traj = Trajectory(ref).grip(0.0, SPREAD).line(command_at([top[0], top[1], tcp[2]], 0.0, 0.0), FINE)
                return traj.line(command_at(top, 0.0, 0.0), FINE).dwell(0.1).grip(1.0)
            above = command_at([top[0], top[1], Z_CARRY], 0.0, GRIP_AROUND)
            traj = add_carry(Trajectory(ref), above, GRIP_AROUND)
            return traj.line(command_at(top, 0.0, GRIP_AROUND), FINE).dwell(0.1).grip(1.0)

        def check(obs):     # the mouth closes on the fingers as they close: it need not stay open now
            if obs["object_upright"] < 0.9:
                return "the target was knocked over"
            return None if obs["object_location"] in ("bag", "spot", "tray", "table", "gripper") else \
                f"the target is not where the hand can take it ({obs['object_location']})"

        grasp = Phase("grasp", 0.65, plan, lambda obs: obs["held"] == "target" and robot(obs)[4] > 0.3, check,
                      patience=1.0, retries=2, stalled="the fingers did not close on the target")
        return [grasp, self._lift()]

    @staticmethod
    def _keep_hold(obs) -> str | None:
        return None if holding_target(obs) else "the target slipped out of the hand"

    @staticmethod
    def _reachable(obs) -> str | None:
        where = obs["object_location"]
        if where == "bag":
            if not obs["bag_opened"]:
                return (f"the bag is shut ({obs['bag_opening']:.3f} m between its walls): "
                        f"the target cannot be seen or reached")
            return None
        if where in ("spot", "tray", "table", "gripper"):
            return None
        return f"the target is not where the hand can take it ({where})"


class Pick(_TargetRecipe):
    def start(self, obs):
        return self._take(obs)

    def postcondition(self, obs):
        return None if obs["grasped"] else "the target is not in the hand"


class Extract(_TargetRecipe):
    """Take the held target out of the bag (if Pick did not lift it clear), carry it to the
    spot, stand it there, let go and rise."""

    def start(self, obs):
        if not holding_target(obs):
            return "the hand does not hold the target"
        phases = [] if target_bottom(obs) > BAG_RIM + CLEAR_OF_BAG else [self._lift()]

        def plan_down(obs, ref):
            hand_to_bottom = obs["tcp"][2] - target_bottom(obs)
            low = command_at([SPOT_POS[0], SPOT_POS[1], TRAY_POS[2] + hand_to_bottom + 0.002], 0.0, 1.0)
            high = command_at([SPOT_POS[0], SPOT_POS[1], TRAY_POS[2] + hand_to_bottom + 0.04], 0.0, 1.0)
            return add_carry(Trajectory(ref), high, 1.0).line(low, FINE)

        def standing(obs):
            on_spot = np.hypot(*np.subtract(obs["object_pos"][:2], SPOT_POS[:2])) < SPOT_RADIUS
            return on_spot and target_bottom(obs) < TRAY_POS[2] + 0.006 and obs["object_upright"] > 0.95

        return [*phases,
                Phase("carry", 0.5, plan_down, standing, self._keep_hold),
                let_go("object_upright", "the target")]

    def postcondition(self, obs):
        if not obs["extracted"]:
            return f"the target is not standing on the spot, let go of ({obs['object_location']})"
        return None


BAG_SKILL_SET = SkillSet(BAG_SKILL_ARGS, {"OpenBag": OpenBag, "InspectBag": InspectBag, "Pick": Pick,
                                         "Extract": Extract}, noun="bag skill")


def make_bag_skill(name: str, arg: str) -> SkillController:
    return SkillController(name, arg, BAG_SKILL_SET)


BAG_TRACE = (("OpenBag", "bag"), ("InspectBag", "bag"), ("Pick", "target"), ("Extract", "target"))
