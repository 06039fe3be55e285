"""The bag world of Retriever-0 ("fetch it out of the bag"): an MJCF model built here, in
Python, and :class:`BagSim`, driven exactly like :class:`~agents.world.Sim`: the same methods,
the same robot and command vector (:mod:`agents.robot`), the same step and tick (:mod:`agents.sim`).

    head camera (fixed)           a paper bag on the table, its mouth folded shut by two flaps;
          \\                       a magenta target stands in it, hidden until they open
           \\     gantry x/y/z           near flap ─┐  ┌─ far flap
            \\      └ wrist pitch           ════════  ════════        a tray with the spot where
             ▼        └ two fingers         ║        •       ║        the target goes; distractors
                                            ╚════════════════╝        on the table

Frames as in the drawer world: z up, the robot and the head camera stand at −y. The flaps are
hinged along the near and far rims and swing down into the bag; their hinges' dry friction
holds them wherever they were pushed, as folded paper stays. Pushing the closed fingers through
the slit between them and spreading the fingers opens both (``OpenBag``). The bag's inner faces
are lined teal: the head camera sees the lining only through an open mouth, which is how
perception tells "the target is not there" from "the camera cannot see in".

This is the articulated bag of ``notes/mujoco-world.md`` §5 (a rigid body with two lid flaps),
not a flex. A trilinear flex bag (flexcomp dim=2, elastic2d="stretch", young 1e4-5e4, plastic
yield 0.005-0.2) did not keep its mouth open: all six faces of the trilinear grid are elastic,
the open top's included, so pushing the near rim sheared the whole bag instead of widening it,
and a mouth spread by the fingers (0.04 → 0.078-0.096 m) sprang back to 0.053-0.057 m once they
let go (the plastic strain stopped near 0.35; frictionloss on the node dofs changed nothing).

Everything random about an episode is in :class:`BagLayout`, drawn from a seed; the same
layout and the same commands give bitwise identical states.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .mjcf import TABLE_TOP, box, camera, loose_shape, table, vec
from .sim import GantrySim, table_or_below, world_mjcf

# -- the bag (metres, in the world frame) --------------------------------------------------------
BAG_CENTRE = np.array([-0.05, 0.10])            # the bag's axis on the table
BAG_INNER = (0.06, 0.055)                       # inner half-width (x) and half-depth (y)
BAG_WALL = 0.004
BAG_HEIGHT = 0.12                               # the walls above the floor
BAG_FLOOR = TABLE_TOP + BAG_WALL                # the floor's top face
BAG_RIM = BAG_FLOOR + BAG_HEIGHT
FLAP_LENGTH = BAG_INNER[1] - 0.005              # hinge to tip: a 1 cm slit between the closed flaps
FLAP_THICKNESS = 0.003
FLAP_FRICTION = 0.02    # N·m at the hinge: 8× the closed flap's weight torque, 0.4 N at its tip to push
FLAP_OPEN = 1.5708      # rad: hanging down along the wall
BAG_RGBA = (0.78, 0.62, 0.42, 1.0)              # kraft paper, hue 34°
LINING_RGBA = (0.10, 0.55, 0.55, 1.0)           # teal, hue 180°: nothing else has it
FLAPS = ("flap_near", "flap_far")

# -- the target and where it goes ---------------------------------------------------------------
TARGET_RADIUS = 0.018
# Its top stands 5 cm below the rim: the flaps' tips swing clear of it (7.8 mm at the worst
# offset), and fingers grasping its top 2.5 cm keep the 12 cm palm above the rim.
TARGET_HALF_HEIGHT = 0.035
TARGET_OFFSET = (0.015, 0.008)                  # ± from the bag's axis in x and y: fingers closing along y
                                                # keep 7 mm from a flap hanging open
TRAY_POS = np.array([0.25, 0.02, TABLE_TOP + 0.012])          # the tray's top surface centre
TRAY_HALF = (0.09, 0.07)
SPOT_POS = TRAY_POS.copy()                      # the marked spot on the tray
SPOT_RADIUS = 0.04                              # the target counts as on the spot within this of its centre

# -- milestones ---------------------------------------------------------------------------------
OPENED = 0.07           # m between the flaps' tips (0.01 shut, 0.09 hanging open): the head camera sees in

DISTRACTOR_COLOURS = ((0.20, 0.65, 0.30), (0.20, 0.35, 0.85), (0.90, 0.85, 0.15), (0.95, 0.45, 0.10))
# Spots on the table away from the bag, the tray and the robot's ways between them.
DISTRACTOR_SPOTS = ((-0.30, 0.05), (-0.28, 0.30), (0.15, 0.32), (0.45, 0.25), (-0.45, -0.15))


# -- what is random about an episode -----------------------------------------------------------
@dataclass(frozen=True)
class TableObject:
    """A distractor standing on the table."""
    shape: str                  # "box" | "cylinder" | "sphere"
    size: float                 # half-extent / radius, metres
    pos: tuple                  # (x, y) on the table
    mass: float
    rgb: tuple


@dataclass(frozen=True)
class BagLayout:
    """Everything random about an episode, drawn by ``from_seed`` in a fixed order."""
    seed: int
    target_offset: tuple        # (x, y) of the target from the bag's axis
    target_mass: float
    target_rgb: tuple           # a shade of magenta (hue 315-330°)
    flap_friction: tuple        # N·m, near and far hinge: how stiff the folded paper is
    distractors: tuple = ()

    @classmethod
    def from_seed(cls, seed: int) -> BagLayout:
        rng = np.random.default_rng([seed, 20261126])
        offset = tuple(float(rng.uniform(-r, r)) for r in TARGET_OFFSET)
        mass = float(rng.uniform(0.05, 0.15))
        hue, value = float(rng.uniform(315.0, 330.0)), float(rng.uniform(0.75, 0.95))
        rgb = _hsv_to_rgb(hue, 0.8, value)
        friction = tuple(float(FLAP_FRICTION * rng.uniform(0.7, 1.3)) for _ in range(2))
        spots = rng.permutation(len(DISTRACTOR_SPOTS))[: int(rng.integers(0, 4))]
        distractors = []
        for i in sorted(spots.tolist()):
            shape, size = ("box", "cylinder", "sphere")[int(rng.integers(3))], float(rng.uniform(0.015, 0.025))
            pos = tuple(float(v) for v in np.add(DISTRACTOR_SPOTS[i], rng.uniform(-0.03, 0.03, 2)))
            distractors.append(TableObject(shape, size, pos, float(rng.uniform(0.05, 0.2)),
                                           DISTRACTOR_COLOURS[int(rng.integers(len(DISTRACTOR_COLOURS)))]))
        return cls(seed, offset, mass, rgb, friction, tuple(distractors))


def _hsv_to_rgb(hue: float, sat: float, value: float) -> tuple:
    c = value * sat
    x = c * (1 - abs((hue / 60.0) % 2 - 1))
    r, g, b = [(c, x, 0), (x, c, 0), (0, c, x), (0, x, c), (x, 0, c), (c, 0, x)][int(hue // 60) % 6]
    m = value - c
    return (round(r + m, 4), round(g + m, 4), round(b + m, 4))


# -- the MJCF model ----------------------------------------------------------------------------
# Above the table's front edge, looking down at about 50° over the bag's near rim: a target in a
# bag shut to its 1 cm slit never shows, one opened by OpenBag shows its top (21-30 pixels at
# 96x128), and the tray is in view. HOME (where InspectBag parks) is outside the picture.
HEAD_CAMERA_POS = (0.10, -0.28, 0.98)
HEAD_CAMERA_TARGET = (0.10, 0.08, 0.42)
HEAD_CAMERA_FOVY = 50.0


def _tray() -> str:
    t = TABLE_TOP
    tx, ty, tz = TRAY_POS
    hx, hy = TRAY_HALF
    rim = (0.85, 0.85, 0.85, 1)
    return f"""
    {box("tray", (tx - hx, ty - hy, t), (tx + hx, ty + hy, tz), "static", (0.96, 0.96, 0.96, 1))}
    {box("tray_rim_front", (tx - hx, ty - hy, tz), (tx + hx, ty - hy + 0.008, tz + 0.01), "static", rim)}
    {box("tray_rim_back", (tx - hx, ty + hy - 0.008, tz), (tx + hx, ty + hy, tz + 0.01), "static", rim)}
    <geom name="spot" class="visualonly" type="cylinder" pos="{vec(tx, ty, tz + 0.0005)}"
          size="{vec(SPOT_RADIUS, 0.0006)}" rgba="0.55 0.55 0.58 1"/>"""


def _flap(name: str, side: int, friction: float) -> str:
    """A flap hinged on the rim at ``side`` (−1 near, +1 far), closed (horizontal) at angle 0,
    swinging down into the bag as the angle grows. It is ``jointed`` for contacts (it
    touches the gripper and the target, not the walls it hangs on) and slippery paper's
    friction, which keeps fingers from wedging on it (notes §5)."""
    cx, cy = BAG_CENTRE
    hinge_y = cy + side * BAG_INNER[1]
    length, thick = FLAP_LENGTH, FLAP_THICKNESS
    return f"""
    <body name="{name}" pos="{vec(cx, hinge_y, BAG_RIM)}">
      <joint name="{name}" type="hinge" axis="{vec(side, 0, 0)}" range="0 {FLAP_OPEN}" frictionloss="{friction:.6g}"
             damping="0.002" armature="0.0005"/>
      <geom name="{name}" class="jointed" type="box" priority="1" friction="0.2 0.01 0.001"
            pos="{vec(0, -side * length / 2, -thick / 2)}" size="{vec(BAG_INNER[0] - 0.002, length / 2, thick / 2)}"
            rgba="{vec(*BAG_RGBA)}" mass="0.01"/>
      <site name="{name}_tip" pos="{vec(0, -side * length, 0)}"/>
    </body>"""


def _bag(layout: BagLayout) -> str:
    (cx, cy), (ix, iy), w = BAG_CENTRE, BAG_INNER, BAG_WALL
    t, rim = TABLE_TOP, BAG_RIM
    walls = [
        box("bag_floor", (cx - ix - w, cy - iy - w, t), (cx + ix + w, cy + iy + w, t + w), "static", BAG_RGBA),
        box("bag_near", (cx - ix - w, cy - iy - w, t), (cx + ix + w, cy - iy, rim), "static", BAG_RGBA),
        box("bag_far", (cx - ix - w, cy + iy, t), (cx + ix + w, cy + iy + w, rim), "static", BAG_RGBA),
        box("bag_left", (cx - ix - w, cy - iy, t), (cx - ix, cy + iy, rim), "static", BAG_RGBA),
        box("bag_right", (cx + ix, cy - iy, t), (cx + ix + w, cy + iy, rim), "static", BAG_RGBA),
    ]
    # the lining: teal on every inner face, seen only through an open mouth
    lo, hi, skin = (cx - ix, cy - iy, t + w), (cx + ix, cy + iy, rim), 0.0005
    lining = [
        box("lining_floor", lo, (hi[0], hi[1], lo[2] + skin), "visualonly", LINING_RGBA),
        box("lining_near", lo, (hi[0], lo[1] + skin, hi[2]), "visualonly", LINING_RGBA),
        box("lining_far", (lo[0], hi[1] - skin, lo[2]), hi, "visualonly", LINING_RGBA),
        box("lining_left", lo, (lo[0] + skin, hi[1], hi[2]), "visualonly", LINING_RGBA),
        box("lining_right", (hi[0] - skin, lo[1], lo[2]), hi, "visualonly", LINING_RGBA),
    ]
    return "\n    ".join(walls + lining) + _flap("flap_near", -1, layout.flap_friction[0]) \
        + _flap("flap_far", 1, layout.flap_friction[1])


def _loose_objects(layout: BagLayout) -> str:
    x, y = BAG_CENTRE + layout.target_offset
    out = [f"""
    <body name="target" pos="{vec(x, y, BAG_FLOOR + TARGET_HALF_HEIGHT + 0.0005)}">
      <freejoint name="target"/>
      <geom name="target" class="loose" type="cylinder" size="{vec(TARGET_RADIUS, TARGET_HALF_HEIGHT)}"
            rgba="{vec(*layout.target_rgb, 1)}" mass="{layout.target_mass:.6g}" friction="1 0.01 0.001"/>
    </body>"""]
    for i, o in enumerate(layout.distractors):
        out.append(loose_shape(f"distractor{i}", (*o.pos, TABLE_TOP + o.size + 0.0005), o.shape, o.size, o.rgb, o.mass))
    return "".join(out)


def build_bag_mjcf(layout: BagLayout) -> str:
    """The MJCF text of the bag world for ``layout`` (a pure function of it)."""
    return world_mjcf("retriever0-bag", f"""
    {camera("head", HEAD_CAMERA_POS, HEAD_CAMERA_TARGET, HEAD_CAMERA_FOVY)}
    {table()}
    {_tray()}
    {_bag(layout)}
    {_loose_objects(layout)}""")


# -- the simulation ----------------------------------------------------------------------------
class BagSim(GantrySim):
    """One episode of the bag world, driven exactly like :class:`~agents.world.Sim` (stepping,
    commands, slips and cameras are :class:`~agents.sim.GantrySim`'s; this adds the flaps and the
    observation). Its item is the target ("target"); both fingers on a flap hold it
    ("flap_near"). The flaps are joints, so ``load_qpos`` carries their angles too."""

    support_normal_z = 0.7      # within 45° of vertical: the bag's walls touching its side do not hold it up

    def __init__(self, layout: BagLayout):
        self.layout = layout
        super().__init__(build_bag_mjcf(layout), "target")
        m = self.model
        self._flap_q = [int(m.joint(f).qposadr[0]) for f in FLAPS]
        self._flap_tips = [m.site(f"{f}_tip").id for f in FLAPS]
        for f in FLAPS:
            self._labels[m.geom(f).id] = f

    # -- state --
    def flaps(self) -> dict:
        """Each flap's angle (rad, 0 shut, ``FLAP_OPEN`` hanging down)."""
        return {f: float(self.data.qpos[a]) for f, a in zip(FLAPS, self._flap_q)}

    def opening(self) -> float:
        """The mouth's free width front to back: from the near flap's tip to the far one's."""
        self._sync()
        near, far = (self.data.site_xpos[s] for s in self._flap_tips)
        return float(far[1] - near[1])

    def object_location(self, held: str, supported: bool) -> str:
        """Where the target is: "gripper", "bag", "spot", "tray", "table", "floor" or "air"."""
        pos = self.data.xpos[self._item]
        if held == "target" and not supported:
            return "gripper"
        x, y = pos[:2] - BAG_CENTRE
        if abs(x) < BAG_INNER[0] and abs(y) < BAG_INNER[1] and BAG_FLOOR < pos[2] < BAG_RIM:
            return "bag"
        on_tray = pos[2] < TRAY_POS[2] + 2 * TARGET_HALF_HEIGHT
        if np.hypot(*(pos[:2] - SPOT_POS[:2])) < SPOT_RADIUS and on_tray:
            return "spot"
        if abs(pos[0] - TRAY_POS[0]) < TRAY_HALF[0] and abs(pos[1] - TRAY_POS[1]) < TRAY_HALF[1] and on_tray:
            return "tray"
        return table_or_below(pos, 2 * TARGET_HALF_HEIGHT)

    def observe(self) -> dict:
        """The world's state as plain values (floats, lists, strings, bools; qpos/qvel/robot as arrays).

        - ``t``; ``qpos``, ``qvel``; ``robot``/``robot_vel``: the measured ``ACTUATORS`` values and
          their rates; ``command``: the targets being applied; ``tcp``: the point between the fingertips
        - ``bag_opening``: the mouth's free width front to back, between the flaps' tips (m; 0.01
          shut, about 0.09 once OpenBag has swung both down); ``flaps``: their angles (rad);
          ``bag_pos``: the middle of the bag's mouth (its axis at the rim's height)
        - ``object_pos`` (the target's centre), ``object_upright`` (cos of its tilt), ``object_speed``, ``spot_pos``;
          ``held``: what both fingers touch ("target", "flap_near", "flap_far", "")
        - ``object_location``: "bag", "gripper", "spot", "tray", "table", "floor" or "air"
        - milestones: ``bag_opened`` (the mouth at least ``OPENED`` wide; the flaps stay so),
          ``grasped`` (both fingers on the target, nothing under it holding it up),
          ``extracted`` (the target out of the bag, resting on the spot, let go of)
        """
        robot = self._observe_robot()
        d = self.data
        held, supported = self.held()
        opening = self.opening()
        where = self.object_location(held, supported)
        target = d.xpos[self._item]
        return {
            **robot,
            "bag_opening": opening,
            "flaps": self.flaps(),
            "bag_pos": [float(BAG_CENTRE[0]), float(BAG_CENTRE[1]), BAG_RIM],
            "object_pos": target.tolist(),
            "object_upright": float(d.xmat[self._item][8]),
            "object_speed": self._item_speed(),
            "spot_pos": SPOT_POS.tolist(),
            "held": held,
            "object_location": where,
            "bag_opened": opening >= OPENED,
            "grasped": held == "target" and not supported,
            "extracted": where == "spot" and held == "",
        }
