"""The bag world of Retriever-0 ("fetch it out of the bag"): an MJCF model built here, in
Python, and :class:`BagSim`, driven exactly like :class:`~agents.world.Sim`: the same methods,
the same robot and command vector (:mod:`agents.robot`), the same step and tick (:mod:`agents.sim`).

    head camera (fixed, right           a paper bag on the table: wide (16 cm), narrow front to
          \\    of the robot, low)       back (5.4 cm), 12 cm tall; a magenta target stands in it
           \\     gantry x/y/z                       near wall   far wall
            \\      └ wrist pitch                      ║   •   ║         a tray with the spot where
             ▼        └ two fingers                   ╚═══════╝         the target goes; distractors
                                                       teal base          on the table

Frames as in the drawer world: z up, the robot and the head camera stand at −y.

The bag is a MuJoCo flexcomp: an open-top box shell (dim=2, 168 vertices, an 8 mm thick skin
for contacts) with dof="trilinear", so its shape is the trilinear map of its bounding box's eight
corner nodes. The bottom four are pinned to the table; the top four are free (12 dofs), held by
the paper's stretching elasticity (elastic2d="stretch", Young's modulus 2.1-3.9e4 Pa by seed,
1 mm, Rayleigh damping 1 ms). That needs integrator="discrete" (Newton): MuJoCo 4 integrates
flex elasticity nowhere else. Physics costs about 0.1 ms a step (see ``notes/mujoco-world.md`` §5).

What widening does: at rest the mouth is 5.4 cm front to back, and the near rim hides the
target from the head camera (no pixel of it at 96x128, whatever its place). ``OpenBag`` pushes
the closed fingers in 4 cm left of the bag's axis, spreads them, which widens the mouth to about
9 cm, and draws the spread mouth 4 cm towards the robot: the near wall leans out of the camera's
lines of sight and the target's top shows (41-46 pixels), past the near finger, which is to the
left of those lines. The paper is elastic: the mouth stays open only while the fingers hold it,
so the head camera looks in then (``InspectBag`` keeps still), ``Pick`` slides the spread fingers
over the target, goes down around it and closes (the walls close in behind the fingers), and the
mouth springs back shut as the hand lifts the target out. A rigid base insert, teal on top, is
what the camera sees of the inside past a near wall drawn open: an empty bag held open shows it.

Tried first, and why it failed (measured with MuJoCo 4.0.0):
- Plasticity, to keep the mouth open once let go (yield 0.001-0.1, Young 2e4-1e5 Pa, a 7 cm
  wide mouth): spread to 10.1-12.1 cm it came back to 8.7-9.6 cm whatever the yield, because the
  plastic strain of the trilinear grid's faces (all six are elastic, the open top's included)
  stops near 0.35 while the widening strains the top face by 0.45-0.7; yields below 0.01 also let
  the bag sag under its own weight (the rim dropped 1.1 cm at 0.005). The first attempt saw the
  same (a 4 cm mouth spread to 7.8-9.6 cm came back to 5.3-5.7) and that pushing the near rim
  sheared the whole bag. 1.2 cm of kept widening per wall moves the camera's view over the near
  rim only about 1.4 cm deeper, against a target top 3.6 cm across placed within ±0.5 cm: by the
  geometry, a few millimetres between "hidden at rest" and "seen after" at best, so I did not
  build on it. The paper's friction (0.05-1, with priority over the fingers') changed nothing.
- Holding the mouth open with the hand over the bag's axis: the near finger (4 cm wide) stood in
  the camera's lines of sight to the target (0-24 pixels); hence the hand 4 cm to the left.
- Spreading without drawing the mouth towards the robot: 4-16 pixels of the target, too few;
  drawn 2.5 cm: 14-29; drawn 4 cm: 41-46, and the base shows in an empty bag.
- A teal lining on the walls' inner faces, as a second, visual-only flex on the same nodes: a raw
  ``<flex dof="trilinear" node=...>`` did not compile ("flex grid rotation R0 is not
  orthonormal"), and a flex has one colour; so only the base is teal and "no" rests on it.

Everything random about an episode is in :class:`BagLayout`, drawn from a seed; the same
layout and the same commands give bitwise identical states.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .mjcf import CONTACT_BITS, TABLE_TOP, box, camera, loose_shape, table, vec
from .sim import GantrySim, table_or_below, world_mjcf

# -- the bag (metres, in the world frame) --------------------------------------------------------
BAG_CENTRE = np.array([-0.05, 0.10])            # the bag's axis on the table
BAG_INNER = (0.08, 0.027)                       # free half-width (x) and half-depth (y) between the walls, at rest
BAG_SKIN = 0.004        # the flex radius: walls 8 mm thick to contacts (thinner, the fingers tunnel; notes §5)
BAG_HEIGHT = 0.12                               # the walls' mid-surface, from the bottom's to the rim's
BAG_FLOOR = TABLE_TOP + 2 * BAG_SKIN + 0.002    # the top of the base insert the target stands on
BAG_RIM = TABLE_TOP + BAG_SKIN + BAG_HEIGHT     # the rim's mid-surface, at rest
BAG_GRID = (9, 4, 7)                            # the flex's vertices along x, y, z (160 on the open box)
BAG_YOUNG = 3.0e4       # Pa, 1 mm paper: the spread fingers widen the mouth 5.4 → 9 cm against ~3 N
BAG_THICKNESS = 0.001
BAG_MASS = 0.005
BAG_DAMPING = 0.001     # s, Rayleigh: the walls settle within a few tenths of a second
BAG_FRICTION = 0.3      # slippery paper: it wins over the fingers' 1.2 (priority), so they slide along the walls
BAG_RGBA = (0.78, 0.62, 0.42, 1.0)              # kraft paper, hue 34°
LINING_RGBA = (0.10, 0.55, 0.55, 1.0)           # teal, hue 180°: the base insert, seen only through an open mouth
# The flex's corner nodes (dof="trilinear"): bodies "bag_<ix>_<iy>_<iz>" for the free top ones;
# the bottom four are pinned to the bag's body (node ids 0 2 4 6, z fastest).
TOP_NODES = {"near": ("bag_0_0_1", "bag_1_0_1"), "far": ("bag_0_1_1", "bag_1_1_1")}

# -- the target and where it goes ---------------------------------------------------------------
TARGET_RADIUS = 0.018
# Its top stands 4.4 cm below the rim: fingers grasping its top 2.5 cm keep the 12 cm palm above the rim.
TARGET_HALF_HEIGHT = 0.035
TARGET_OFFSET = (0.015, 0.005)                  # ± from the bag's axis in x and y
TRAY_POS = np.array([0.25, 0.02, TABLE_TOP + 0.012])          # the tray's top surface centre
TRAY_HALF = (0.09, 0.07)
SPOT_POS = TRAY_POS.copy()                      # the marked spot on the tray
SPOT_RADIUS = 0.04                              # the target counts as on the spot within this of its centre

# -- milestones ---------------------------------------------------------------------------------
OPENED = 0.08           # m front to back between the walls at the rim (0.054 at rest, 0.09 held spread and drawn)

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
    bag_young: float            # Pa: how stiff the bag's paper is
    distractors: tuple = ()

    @classmethod
    def from_seed(cls, seed: int) -> BagLayout:
        rng = np.random.default_rng([seed, 20261126])
        offset = tuple(float(rng.uniform(-r, r)) for r in TARGET_OFFSET)
        mass = float(rng.uniform(0.05, 0.15))
        hue, value = float(rng.uniform(315.0, 330.0)), float(rng.uniform(0.75, 0.95))
        rgb = _hsv_to_rgb(hue, 0.8, value)
        young = float(BAG_YOUNG * rng.uniform(0.7, 1.3))
        spots = rng.permutation(len(DISTRACTOR_SPOTS))[: int(rng.integers(0, 4))]
        distractors = []
        for i in sorted(spots.tolist()):
            shape, size = ("box", "cylinder", "sphere")[int(rng.integers(3))], float(rng.uniform(0.015, 0.025))
            pos = tuple(float(v) for v in np.add(DISTRACTOR_SPOTS[i], rng.uniform(-0.03, 0.03, 2)))
            distractors.append(TableObject(shape, size, pos, float(rng.uniform(0.05, 0.2)),
                                           DISTRACTOR_COLOURS[int(rng.integers(len(DISTRACTOR_COLOURS)))]))
        return cls(seed, offset, mass, rgb, young, tuple(distractors))


def _hsv_to_rgb(hue: float, sat: float, value: float) -> tuple:
    c = value * sat
    x = c * (1 - abs((hue / 60.0) % 2 - 1))
    r, g, b = [(c, x, 0), (x, c, 0), (0, c, x), (0, x, c), (x, 0, c), (c, 0, x)][int(hue // 60) % 6]
    m = value - c
    return (round(r + m, 4), round(g + m, 4), round(b + m, 4))


# -- the MJCF model ----------------------------------------------------------------------------
# Right of the robot and low, looking down at about 40° across the bag's near wall: a target in
# the bag at rest never shows (the near rim hides it), one in a mouth held open and drawn towards
# the camera by OpenBag shows its top (20-45 pixels at 96x128).
HEAD_CAMERA_POS = (0.25, -0.30, 0.85)
HEAD_CAMERA_TARGET = (-0.05, 0.12, 0.48)
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


def _bag(layout: BagLayout) -> str:
    """The bag: an open-top box of paper (a 2D flexcomp) whose shape is the trilinear map of its
    bounding box's eight corners; the bottom four are pinned to the table, the top four are free
    (12 dofs). A rigid base insert (teal on top) lies on its bottom: the target stands on it.
    The flex touches the gripper and loose things, not the table it is pinned to."""
    (cx, cy), (ix, iy), r, h = BAG_CENTRE, BAG_INNER, BAG_SKIN, BAG_HEIGHT
    (nx, ny, nz), (contype, conaffinity) = BAG_GRID, CONTACT_BITS["jointed"]
    spacing = (2 * (ix + r) / (nx - 1), 2 * (iy + r) / (ny - 1), h / (nz - 1))
    base = box("bag_base", (cx - ix, cy - iy, TABLE_TOP), (cx + ix, cy + iy, BAG_FLOOR), "static", LINING_RGBA)
    return f"""
    {base}
    <body name="bag" pos="{vec(cx, cy, TABLE_TOP + r + h / 2)}">
      <flexcomp name="bag" type="box" dim="2" dof="trilinear" count="{vec(*BAG_GRID)}" spacing="{vec(*spacing)}"
                radius="{r}" rgba="{vec(*BAG_RGBA)}" mass="{BAG_MASS}">
        <contact contype="{contype}" conaffinity="{conaffinity}" condim="3" solref="0.004 1"
                 friction="{BAG_FRICTION}" priority="1" selfcollide="none"/>
        <elasticity young="{layout.bag_young:.6g}" poisson="0.2" thickness="{BAG_THICKNESS}" elastic2d="stretch"
                    damping="{BAG_DAMPING}"/>
        <pin id="0 2 4 6"/>
      </flexcomp>
    </body>"""


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
    {_loose_objects(layout)}""", integrator="discrete")


# -- the simulation ----------------------------------------------------------------------------
class BagSim(GantrySim):
    """One episode of the bag world, driven exactly like :class:`~agents.world.Sim` (stepping,
    commands, slips and cameras are :class:`~agents.sim.GantrySim`'s; this adds the bag's mouth
    and the observation). Its item is the target ("target"); both fingers on the bag's walls hold
    "bag". The flex's free nodes are joints, so ``load_qpos`` carries the bag's shape too."""

    support_normal_z = 0.7      # within 45° of vertical: the bag's walls touching its side do not hold it up

    def __init__(self, layout: BagLayout):
        self.layout = layout
        super().__init__(build_bag_mjcf(layout), "target")
        m = self.model
        self._flex_label = "bag"
        self._nodes = {side: [m.body(b).id for b in bodies] for side, bodies in TOP_NODES.items()}

    # -- state --
    def rim(self) -> dict:
        """Where the mouth's near and far walls are at the rim (y of their mid-surface, averaged
        along x: the rim in the middle of the bag), and the rim's height."""
        self._sync()
        xpos = self.data.xpos
        near, far = (xpos[self._nodes[side]] for side in ("near", "far"))
        return {"near": float(near[:, 1].mean()), "far": float(far[:, 1].mean()),
                "z": float(np.concatenate([near, far])[:, 2].mean())}

    def opening(self) -> float:
        """The mouth's free width front to back, between the walls' inner faces at the rim."""
        rim = self.rim()
        return rim["far"] - rim["near"] - 2 * BAG_SKIN

    def object_location(self, held: str, supported: bool) -> str:
        """Where the target is: "gripper", "bag", "spot", "tray", "table", "floor" or "air"."""
        pos = self.data.xpos[self._item]
        if held == "target" and not supported:
            return "gripper"
        x, y = pos[:2] - BAG_CENTRE
        if abs(x) < BAG_INNER[0] and abs(y) < BAG_INNER[1] + 0.01 and BAG_FLOOR < pos[2] < BAG_RIM:
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
        - ``bag_opening``: the mouth's free width front to back at the rim (m; 0.054 at rest, about
          0.09 while OpenBag's fingers hold it spread); ``bag_rim``: the near and far walls' y and the
          rim's height; ``bag_pos``: the middle of the bag's mouth at rest (its axis at the rim's height)
        - ``object_pos`` (the target's centre), ``object_upright`` (cos of its tilt), ``object_speed``, ``spot_pos``;
          ``held``: what both fingers touch ("target", "bag", "")
        - ``object_location``: "bag", "gripper", "spot", "tray", "table", "floor" or "air"
        - milestones: ``bag_opened`` (the mouth at least ``OPENED`` wide: it springs back shut when
          let go of), ``grasped`` (both fingers on the target, nothing under it holding it up),
          ``extracted`` (the target out of the bag, resting on the spot, let go of)
        """
        robot = self._observe_robot()
        d = self.data
        held, supported = self.held()
        rim = self.rim()
        opening = rim["far"] - rim["near"] - 2 * BAG_SKIN
        where = self.object_location(held, supported)
        target = d.xpos[self._item]
        return {
            **robot,
            "bag_opening": opening,
            "bag_rim": rim,
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
