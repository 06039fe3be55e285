"""The drawer world of Retriever-0 ("seasoning with drawers"): an MJCF model built here, in
Python, and :class:`Sim`, the one object other modules drive it through.

    head camera (fixed)                 cabinet on the table, four drawers on slide joints
          \\                                 ┌──────┬──────┐
           \\       gantry x/y/z            │  TL  │  TR  │   each with a bar handle (TL-H …)
            \\        └ wrist pitch         ├──────┼──────┤   the orange spice bottle in one of them,
             \\          └ two fingers      │  BL  │  BR  │   distractors of other colours in others
              ▼        (+ wrist camera)      └──────┴──────┘
                                                 plate (food) on the table, to the right

Frames: z up, the robot and the head camera stand at −y, the cabinet's front faces −y, and a
drawer opens toward −y (a wrist pitch of π/2 points the fingers into the cabinet). The robot,
its command vector (``ACTUATORS``) and the clock are :mod:`agents.robot`'s and
:mod:`agents.sim`'s, re-exported here. Everything random about an episode is in
:class:`Layout`, drawn from a seed; the same layout and the same commands give bitwise
identical states.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .mjcf import TABLE_TOP, box, camera, loose_shape, table, vec
from .plan import DRAWERS, HANDLES
from .robot import ACTUATORS, COMMAND_HIGH, COMMAND_LOW, HOME, MAX_SPEED, NU
from .sim import TICK, TIMESTEP, GantrySim, table_or_below, world_mjcf

# What other modules drive the drawer world with (the robot's and the clock's names included).
__all__ = [
    "ACTUATORS", "COMMAND_HIGH", "COMMAND_LOW", "DRAWERS", "Distractor", "HANDLES", "HOME", "Layout", "MAX_SPEED",
    "NU", "Sim", "TICK", "TIMESTEP", "bottle_location", "build_mjcf", "check_drawer", "drawer_above", "drawer_origin",
    "handle_position",
]


# -- geometry (metres) -------------------------------------------------------------------------
CABINET_FRONT_Y = 0.05                  # the closed drawers' front faces
CABINET_BACK_Y = 0.43
CABINET_TOP = 0.76
COLUMN_X = {"L": -0.15, "R": 0.15}
ROW_BOTTOM = {"B": 0.42, "T": 0.59}     # each row's opening is 0.15 m tall
DRAWER_TRAVEL = 0.30                    # slide range; skills open to 0.27 so bottom drawers are reachable from above
PANEL_THICKNESS = 0.015
INTERIOR_HALF_WIDTH = 0.125
INTERIOR_FRONT = PANEL_THICKNESS        # drawer-frame y of the interior's front and back faces
INTERIOR_BACK = 0.335
FLOOR_Z = 0.02                          # drawer-frame z of the floor's top face
WALL_HEIGHT = 0.06                      # low walls: the head camera sees over them into an open drawer
HANDLE_STANDOFF = 0.04                  # bar centre in front of the front face: room for the fingertips
HANDLE_Z = 0.075                        # drawer-frame z of the bar (the panel's middle)
HANDLE_RADIUS = 0.008
HANDLE_HALF_LENGTH = 0.05

BOTTLE_RADIUS = 0.02
BOTTLE_HALF_HEIGHT = 0.04
BOTTLE_RGBA = (0.95, 0.35, 0.05, 1.0)   # hue 20°: nothing else in the scene is orange or red
PLATE_POS = np.array([0.45, -0.28, TABLE_TOP + 0.012])   # the plate's top surface centre
PLATE_RADIUS = 0.10

# -- milestones --------------------------------------------------------------------------------
SEASON_COS = -0.2                       # the bottle counts as pouring when tilted past ~100°
SEASON_SECONDS = 1.0                    # … for this long over the plate
SEASON_REACH = PLATE_RADIUS + 0.03      # horizontal distance from the plate's centre
SEASON_HEIGHT = 0.40                    # at most this far above the plate
CLOSED_OPENING = 0.01

DISTRACTOR_COLOURS = ((0.20, 0.65, 0.30), (0.20, 0.35, 0.85), (0.55, 0.30, 0.75), (0.90, 0.85, 0.15))


def drawer_origin(drawer: str) -> np.ndarray:
    """World position of a closed drawer's frame: the front face's centre line, at the row's bottom."""
    return np.array([COLUMN_X[drawer[1]], CABINET_FRONT_Y, ROW_BOTTOM[drawer[0]]])


def drawer_above(drawer: str) -> str | None:
    """The drawer right above ``drawer`` (whose open body hides a bottom drawer from above)."""
    return "T" + drawer[1] if drawer[0] == "B" else None


def check_drawer(drawer: str) -> str:
    if drawer not in DRAWERS:
        raise ValueError(f"unknown drawer {drawer!r}: expected one of {', '.join(DRAWERS)}")
    return drawer


def handle_position(drawer: str, opening: float) -> np.ndarray:
    """The centre of ``drawer``'s handle bar when the drawer is open ``opening`` metres."""
    return drawer_origin(drawer) + [0.0, -opening - HANDLE_STANDOFF, HANDLE_Z]


def bottle_location(pos, grasped: bool, openings: dict) -> str:
    """Where a bottle at ``pos`` is: a drawer's name, "gripper" (``grasped``: held up by the
    fingers alone), "plate", "table", "floor" or "air" (``openings``: metres per drawer)."""
    pos = np.asarray(pos, dtype=np.float64)
    if grasped:
        return "gripper"
    for d in DRAWERS:
        o = drawer_origin(d) - [0, openings[d], 0]
        x, y, z = pos - o
        if abs(x) < INTERIOR_HALF_WIDTH and INTERIOR_FRONT < y < INTERIOR_BACK and FLOOR_Z < z < FLOOR_Z + 0.13:
            return d
    if np.hypot(*(pos[:2] - PLATE_POS[:2])) < PLATE_RADIUS and pos[2] < PLATE_POS[2] + 0.1:
        return "plate"
    return table_or_below(pos, 0.1)


# -- what is random about an episode -----------------------------------------------------------
@dataclass(frozen=True)
class Distractor:
    """A non-orange object lying in a drawer that does not hold the bottle."""
    drawer: str
    shape: str                  # "box" | "cylinder" | "sphere"
    size: float                 # half-extent / radius, metres
    offset: tuple               # (x, y) in the drawer's interior frame (y from the interior's front)
    mass: float
    rgb: tuple


@dataclass(frozen=True)
class Layout:
    """Everything random about an episode. ``from_seed`` draws every value in a fixed order
    whatever ``drawer`` says, so one seed gives the same bottle offsets in any drawer."""
    seed: int
    target_drawer: str
    bottle_offset: tuple        # (x from the drawer's centre line, y from the interior's front face)
    bottle_mass: float
    drawer_damping: tuple       # per drawer, in DRAWERS order
    drawer_friction: tuple
    distractors: tuple = ()

    @classmethod
    def from_seed(cls, seed: int, drawer: str | None = None) -> Layout:
        rng = np.random.default_rng([seed, 20261125])
        chosen = DRAWERS[int(rng.integers(len(DRAWERS)))]
        target = chosen if drawer is None else check_drawer(drawer)
        # ±7 cm sideways; 7.5-12 cm behind the front wall: fingers closing along y keep 2.5 cm from
        # it, a fully opened bottom drawer keeps the palm 2.5 cm in front of the handle above, and
        # the head camera sees the bottle over the front panel.
        offset = (float(rng.uniform(-0.07, 0.07)), float(rng.uniform(0.075, 0.12)))
        mass = float(rng.uniform(0.10, 0.25))
        damping = tuple(float(4.0 * rng.uniform(0.7, 1.3)) for _ in DRAWERS)
        friction = tuple(float(0.5 * rng.uniform(0.7, 1.3)) for _ in DRAWERS)
        distractors = []
        for d in DRAWERS:
            present, shape, size = rng.random() < 0.6, int(rng.integers(3)), float(rng.uniform(0.015, 0.028))
            x, y = float(rng.uniform(-0.08, 0.08)), float(rng.uniform(0.05, 0.27))
            mass_d, colour = float(rng.uniform(0.05, 0.2)), DISTRACTOR_COLOURS[int(rng.integers(4))]
            if present and d != target:
                distractors.append(Distractor(d, ("box", "cylinder", "sphere")[shape], size, (x, y), mass_d, colour))
        return cls(seed, target, offset, mass, damping, friction, tuple(distractors))


# -- the MJCF model ----------------------------------------------------------------------------
# High and in front: it sees into every open drawer over its front panel, and the plate; the
# gantry's parking spots beside the cabinet (HOME, InspectDrawer's) hide none of the drawers.
HEAD_CAMERA_POS = (0.08, -0.62, 1.30)
HEAD_CAMERA_TARGET = (0.08, -0.04, 0.50)
HEAD_CAMERA_FOVY = 55.0

CABINET_RGBA = (0.86, 0.86, 0.83, 1)
DRAWER_RGBA = (0.72, 0.76, 0.80, 1)
HANDLE_RGBA = (0.25, 0.25, 0.28, 1)


def _plate() -> str:
    px, py, pz = PLATE_POS
    food = "".join(f'<geom class="visualonly" type="ellipsoid" pos="{vec(px + dx, py + dy, pz + 0.012)}" '
                   f'size="{vec(0.035, 0.025, 0.014)}" euler="0 0 {a}" rgba="0.3 0.62 0.22 1"/>'
                   for dx, dy, a in [(-0.03, 0.01, 0.3), (0.03, -0.02, 1.2), (0.0, 0.035, 2.0)])
    return f"""
    <geom name="plate" class="static" type="cylinder" pos="{vec(px, py, pz - 0.006)}" size="{vec(PLATE_RADIUS, 0.006)}"
          rgba="0.96 0.96 0.96 1"/>
    {food}"""


def _cabinet() -> str:
    f, b, top = CABINET_FRONT_Y, CABINET_BACK_Y, CABINET_TOP
    t, bot, mid = TABLE_TOP, ROW_BOTTOM["B"], ROW_BOTTOM["B"] + 0.15
    parts = [
        box("cabinet_left", (-0.30, f, t), (-0.29, b, top), "static", CABINET_RGBA),
        box("cabinet_right", (0.29, f, t), (0.30, b, top), "static", CABINET_RGBA),
        box("cabinet_divider", (-0.01, f, bot), (0.01, b, top - 0.02), "static", CABINET_RGBA),
        box("cabinet_bottom", (-0.29, f, t), (0.29, b, bot), "static", CABINET_RGBA),
        box("cabinet_shelf", (-0.29, f, mid), (0.29, b, ROW_BOTTOM["T"]), "static", CABINET_RGBA),
        box("cabinet_top", (-0.30, f, top - 0.02), (0.30, b, top), "static", CABINET_RGBA),
        box("cabinet_back", (-0.29, b - 0.01, bot), (0.29, b, top - 0.02), "static", CABINET_RGBA),
    ]
    return "\n    ".join(parts)


def _drawer(d: str, damping: float, friction: float) -> str:
    w, fr, bk, fz, wall = INTERIOR_HALF_WIDTH, INTERIOR_FRONT, INTERIOR_BACK, FLOOR_Z, WALL_HEIGHT
    s, hz, hr, hl = HANDLE_STANDOFF, HANDLE_Z, HANDLE_RADIUS, HANDLE_HALF_LENGTH
    return f"""
    <body name="drawer_{d}" pos="{vec(*drawer_origin(d))}">
      <joint name="drawer_{d}" type="slide" axis="0 -1 0" range="0 {DRAWER_TRAVEL}" damping="{damping:.6g}"
             frictionloss="{friction:.6g}" armature="0.05"/>
      {box(f"{d}_front", (-0.138, 0, 0.005), (0.138, fr, 0.145), "jointed", DRAWER_RGBA, mass="0.4")}
      {box(f"{d}_floor", (-w - 0.01, fr, fz - 0.01), (w + 0.01, bk + 0.01, fz), "jointed", DRAWER_RGBA, mass="0.4")}
      {box(f"{d}_left", (-w - 0.01, fr, fz), (-w, bk + 0.01, fz + wall), "jointed", DRAWER_RGBA, mass="0.1")}
      {box(f"{d}_right", (w, fr, fz), (w + 0.01, bk + 0.01, fz + wall), "jointed", DRAWER_RGBA, mass="0.1")}
      {box(f"{d}_back", (-w, bk, fz), (w, bk + 0.01, fz + wall), "jointed", DRAWER_RGBA, mass="0.1")}
      <geom name="{d}-H" class="jointed" type="capsule" fromto="{vec(-hl, -s, hz, hl, -s, hz)}" size="{hr}"
            rgba="{vec(*HANDLE_RGBA)}" mass="0.05" friction="1 0.01 0.001"/>
      <geom name="{d}-H_l" class="jointed" type="cylinder" fromto="{vec(-hl, -s, hz, -hl, 0, hz)}" size="0.006"
            rgba="{vec(*HANDLE_RGBA)}" mass="0.01"/>
      <geom name="{d}-H_r" class="jointed" type="cylinder" fromto="{vec(hl, -s, hz, hl, 0, hz)}" size="0.006"
            rgba="{vec(*HANDLE_RGBA)}" mass="0.01"/>
      <site name="{d}-H" pos="{vec(0, -s, hz)}"/>
    </body>"""


def _loose_objects(layout: Layout) -> str:
    d = layout.target_drawer
    x, y = layout.bottle_offset
    base = drawer_origin(d) + [x, INTERIOR_FRONT + y, FLOOR_Z]
    out = [f"""
    <body name="spice" pos="{vec(*(base + [0, 0, BOTTLE_HALF_HEIGHT + 0.0005]))}">
      <freejoint name="spice"/>
      <geom name="spice" class="loose" type="cylinder" size="{vec(BOTTLE_RADIUS, BOTTLE_HALF_HEIGHT)}"
            rgba="{vec(*BOTTLE_RGBA)}" mass="{layout.bottle_mass:.6g}" friction="1 0.01 0.001"/>
      <geom name="spice_cap" class="loose" type="cylinder" pos="0 0 {BOTTLE_HALF_HEIGHT + 0.006}"
            size="0.013 0.006" rgba="0.15 0.15 0.15 1" mass="0.005"/>
    </body>"""]
    for i, o in enumerate(layout.distractors):
        p = drawer_origin(o.drawer) + [o.offset[0], INTERIOR_FRONT + o.offset[1], FLOOR_Z + o.size + 0.0005]
        out.append(loose_shape(f"distractor{i}", p, o.shape, o.size, o.rgb, o.mass))
    return "".join(out)


def build_mjcf(layout: Layout) -> str:
    """The MJCF text of the world for ``layout`` (a pure function of it)."""
    drawers = "".join(_drawer(d, layout.drawer_damping[i], layout.drawer_friction[i]) for i, d in enumerate(DRAWERS))
    return world_mjcf("retriever0-drawers", f"""
    {camera("head", HEAD_CAMERA_POS, HEAD_CAMERA_TARGET, HEAD_CAMERA_FOVY)}
    {table()}
    {_plate()}
    {_cabinet()}
    {drawers}
    {_loose_objects(layout)}""")


# -- the simulation ----------------------------------------------------------------------------
class Sim(GantrySim):
    """One episode of the drawer world, and the only way other modules touch it. Stepping,
    commands, slips and cameras are :class:`~agents.sim.GantrySim`'s; this adds the drawers, the
    seasoning and the observation. Its item is the spice bottle ("spice"); both fingers on a
    handle's bar or posts hold that handle ("TR-H")."""

    def __init__(self, layout: Layout):
        self.layout = layout
        super().__init__(build_mjcf(layout), "spice")
        self._season_time = 0.0
        m = self.model
        self._drawer_q = {d: int(m.joint(f"drawer_{d}").qposadr[0]) for d in DRAWERS}
        self._handle_site = {h: m.site(h).id for h in HANDLES}
        for h in HANDLES:
            for g in (h, h + "_l", h + "_r"):
                self._labels[m.geom(g).id] = h
        # the free bodies set_openings carries along with a drawer
        self._loose = [self._item] + [m.body(f"distractor{i}").id for i in range(len(layout.distractors))]

    def _after_tick(self, dt: float) -> None:
        """Seasoning time, then the end of an injected slip."""
        self._sync()
        d = self.data
        if d.xmat[self._item][8] < SEASON_COS and self._over_plate(d.xpos[self._item]):
            self._season_time += dt
        super()._after_tick(dt)

    @staticmethod
    def _over_plate(pos) -> bool:
        dx, dy = pos[0] - PLATE_POS[0], pos[1] - PLATE_POS[1]
        return dx * dx + dy * dy < SEASON_REACH ** 2 and 0.0 < pos[2] - PLATE_POS[2] < SEASON_HEIGHT

    # -- state --
    def openings(self) -> dict:
        return {d: float(self.data.qpos[a]) for d, a in self._drawer_q.items()}

    def bottle_location(self, held: str, supported: bool, openings: dict) -> str:
        """Where the bottle is: a drawer's name, "gripper", "plate", "table", "floor" or "air"."""
        return bottle_location(self.data.xpos[self._item], held == "spice" and not supported, openings)

    def observe(self) -> dict:
        """The world's state as plain values (floats, lists, strings, bools; qpos/qvel/robot as arrays).

        - ``t``; ``qpos``, ``qvel``; ``robot``/``robot_vel``: the measured ``ACTUATORS`` values and
          their rates; ``command``: the targets being applied; ``tcp``: the point between the fingertips
        - ``drawers``: opening in metres per drawer; ``handles``: bar centre per handle ("TL-H" …)
        - ``bottle_pos``, ``bottle_upright`` (cos of its tilt), ``bottle_speed``, ``bottle_home`` (its
          drawer in the layout), ``plate_pos``; ``held``: what both fingers touch ("spice", "TR-H", "")
        - milestones: ``grasped`` (both fingers on the bottle, nothing else holding it up),
          ``seasoned`` (tilted past ~100° over the plate for a cumulative ``SEASON_SECONDS``; stays
          true; ``season_time`` so far), ``drawers_closed`` (every opening under 1 cm),
          ``bottle_location`` (a drawer, "gripper", "plate", "table", "floor" or "air")
        """
        robot = self._observe_robot()
        d = self.data
        held, supported = self.held()
        openings = self.openings()
        return {
            **robot,
            "drawers": openings,
            "handles": {h: d.site_xpos[s].tolist() for h, s in self._handle_site.items()},
            "bottle_pos": d.xpos[self._item].tolist(),
            "bottle_upright": float(d.xmat[self._item][8]),
            "bottle_speed": self._item_speed(),
            "bottle_home": self.layout.target_drawer,
            "plate_pos": PLATE_POS.tolist(),
            "held": held,
            "grasped": held == "spice" and not supported,
            "season_time": self._season_time,
            "seasoned": self._season_time >= SEASON_SECONDS,
            "drawers_closed": all(o < CLOSED_OPENING for o in openings.values()),
            "bottle_location": self.bottle_location(held, supported, openings),
        }

    def set_openings(self, openings: dict) -> None:
        """Put drawers at the given openings, carrying whatever lies in them (scene setup for
        tests and pictures; physics is not stepped)."""
        old = self.openings()
        for b in self._loose:
            adr = self.model.jnt_qposadr[self.model.body_jntadr[b]]
            pos = self.data.qpos[adr:adr + 3]
            for d in DRAWERS:
                x, y, z = pos - (drawer_origin(d) - [0, old[d], 0])
                if abs(x) < INTERIOR_HALF_WIDTH + 0.01 and 0 < y < INTERIOR_BACK + 0.01 and 0 < z < 0.15:
                    pos[1] -= openings.get(d, old[d]) - old[d]
                    break
        for d, o in openings.items():
            self.data.qpos[self._drawer_q[check_drawer(d)]] = float(o)
        self._forward()
