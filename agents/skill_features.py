"""What a learned skill policy of Retriever-0 sees: two numeric vectors the world publishes at
every tick (ports ``state`` and ``scene``) and the wrist camera's frame.

- ``state`` (:data:`STATE_NAMES`, 18 floats): proprioception, what the robot's own encoders and
  controller know: the measured joints (x, y, z, pitch, grip), their velocities, the commanded
  targets, and the tool centre point (the forward kinematics of the joints).
- ``scene`` (:data:`SCENE_NAMES`, 10 floats): **simulator ground truth**, standing in for
  perception: the bottle's position and uprightness, whether both fingers touch it and whether
  they alone hold it up (a touch sensor), and each drawer's opening.
- ``wrist``: the wrist camera's newest frame (uint8 64×64×3).

The scripted skills read a dict of facts (``Sim.observe()``); :func:`facts_of` rebuilds, from
the two vectors, the facts the Pick skill reads, so that the scripted Pick can run behind the
same inputs as a learned one (it is the teacher whose actions a dataset records).
"""

from __future__ import annotations

import numpy as np

from .robot import ACTUATORS
from .world import DRAWERS, HANDLES, bottle_location, handle_position

STATE_NAMES = (*ACTUATORS, *(f"{a}_vel" for a in ACTUATORS), *(f"{a}_cmd" for a in ACTUATORS),
               "tcp_x", "tcp_y", "tcp_z")
SCENE_NAMES = ("bottle_x", "bottle_y", "bottle_z", "bottle_upright", "touching_bottle", "holding_bottle",
               *(f"opening_{d}" for d in DRAWERS))


def sensors(facts: dict) -> tuple[np.ndarray, np.ndarray]:
    """The ``state`` and ``scene`` vectors of one world observation (``Sim.observe()``'s dict)."""
    state = np.concatenate([np.asarray(facts["robot"], dtype=np.float64), facts["robot_vel"], facts["command"],
                            facts["tcp"]])
    scene = np.array([*facts["bottle_pos"], facts["bottle_upright"], facts["held"] == "spice", facts["grasped"],
                      *(facts["drawers"][d] for d in DRAWERS)], dtype=np.float64)
    return state, scene


def facts_of(t: float, state: np.ndarray, scene: np.ndarray) -> dict:
    """The facts a drawer-world skill reads, as far as ``state`` and ``scene`` tell them (what
    the Pick skill reads: the robot, the bottle, what the hand holds, the drawers and handles)."""
    n = len(ACTUATORS)
    state, scene = np.asarray(state, dtype=np.float64), np.asarray(scene, dtype=np.float64)
    if state.shape != (len(STATE_NAMES),) or scene.shape != (len(SCENE_NAMES),):
        raise ValueError(f"a skill's state has {len(STATE_NAMES)} values and its scene {len(SCENE_NAMES)}, "
                         f"got shapes {state.shape} and {scene.shape}")
    openings = {d: float(o) for d, o in zip(DRAWERS, scene[6:])}
    touching, grasped = bool(scene[4]), bool(scene[5])
    return {
        "t": t, "robot": state[:n].copy(), "robot_vel": state[n:2 * n].tolist(), "command": state[2 * n:3 * n].tolist(),
        "tcp": state[3 * n:].tolist(), "bottle_pos": scene[:3].tolist(), "bottle_upright": float(scene[3]),
        "held": "spice" if touching else "", "grasped": grasped, "drawers": openings,
        "handles": {h: handle_position(h[:2], openings[h[:2]]).tolist() for h in HANDLES},
        "bottle_location": bottle_location(scene[:3], grasped, openings),
    }
