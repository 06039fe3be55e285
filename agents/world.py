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
drawer opens toward −y. The command vector (``ACTUATORS``) is the wrist pivot's world position,
the wrist pitch (0: fingers down, π/2: fingers pointing +y, into the cabinet) and the grip
(0 open … 1 closed, both fingers). Everything random about an episode is in :class:`Layout`,
drawn from a seed; the same layout and the same commands give bitwise identical states.

The settings (render quality, contact bits, gains) are the ones measured on this machine in
``notes/mujoco-world.md``; where they differ the constant's comment says why.
"""

from __future__ import annotations

import os

os.environ.setdefault("MUJOCO_GL", "egl")       # CPU rendering without a display
os.environ.setdefault("LP_NUM_THREADS", "0")    # llvmpipe rasterises in the calling thread

from dataclasses import dataclass

import mujoco
import numpy as np

# -- the command vector ------------------------------------------------------------------------
DRAWERS = ("TL", "TR", "BL", "BR")
HANDLES = tuple(f"{d}-H" for d in DRAWERS)
ACTUATORS = ("x", "y", "z", "pitch", "grip")
NU = len(ACTUATORS)
COMMAND_LOW = np.array([-0.65, -0.65, 0.40, -0.30, 0.0])
COMMAND_HIGH = np.array([0.65, 0.45, 1.20, 2.80, 1.0])
MAX_SPEED = np.array([0.5, 0.5, 0.5, 4.0, 6.0])           # m/s, m/s, m/s, rad/s, grip/s
HOME = np.array([0.52, -0.10, 1.00, 0.0, 0.0])            # parked right of the cabinet, out of the head camera's way

# -- physics -----------------------------------------------------------------------------------
# The world is ticked at 200 Hz, so the step must divide 5 ms; 2.5 ms is the closest to the 2 ms
# the notes verified (5 ms let the handle slip), and grasping was re-verified with it (tests).
TIMESTEP = 0.0025
TICK = 0.005

# -- geometry (metres) -------------------------------------------------------------------------
TABLE_TOP = 0.40
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

# -- the gripper (wrist frame at pitch 0: z up, fingers hang down and close along y) ------------
FINGER_OPEN = 0.04                      # each finger's travel from the centre line: an 8 cm gap
TCP_OFFSET = 0.12                       # wrist pivot → tool centre point, along the fingers
PALM_BOTTOM = 0.065                     # wrist pivot → palm's lower face
FINGER_LENGTH = 0.08

# -- milestones --------------------------------------------------------------------------------
SEASON_COS = -0.2                       # the bottle counts as pouring when tilted past ~100°
SEASON_SECONDS = 1.0                    # … for this long over the plate
SEASON_REACH = PLATE_RADIUS + 0.03      # horizontal distance from the plate's centre
SEASON_HEIGHT = 0.40                    # at most this far above the plate
CLOSED_OPENING = 0.01

# -- collision bits: contype is what a geom is, conaffinity what it collides with ---------------
# Cabinet and drawers never touch (the drawers slide inside it on their joints), everything else
# does. SLIPPING is the bottle's type during an injected slip: then nothing of the gripper touches it.
STATIC, DRAWER, GRIPPER, LOOSE, SLIPPING = 1, 2, 4, 8, 16
CONTACT_BITS = {
    "static": (STATIC, GRIPPER | LOOSE),
    "drawer": (DRAWER, GRIPPER | LOOSE),
    "gripper": (GRIPPER, STATIC | DRAWER | LOOSE),
    "loose": (LOOSE, STATIC | DRAWER | GRIPPER | LOOSE),
}

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
def _v(*xs) -> str:
    return " ".join(f"{float(x):.6g}" for x in xs)


def _box(name: str, lo, hi, cls: str, rgba, **extra) -> str:
    """An axis-aligned box from its two corners (the way the cabinet is drawn on paper)."""
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    attrs = "".join(f' {k}="{v}"' for k, v in extra.items())
    return (f'<geom name="{name}" class="{cls}" type="box" pos="{_v(*(lo + hi) / 2)}" '
            f'size="{_v(*(hi - lo) / 2)}" rgba="{_v(*rgba)}"{attrs}/>')


def _look_at(pos, target) -> str:
    """``xyaxes`` of a camera at ``pos`` looking at ``target`` with world z up."""
    forward = np.asarray(target, float) - np.asarray(pos, float)
    forward /= np.linalg.norm(forward)
    right = np.cross(forward, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    up = np.cross(right, forward)
    return _v(*right, *up)


# High and in front: it sees into every open drawer over its front panel, and the plate; the
# gantry's parking spots beside the cabinet (HOME, InspectDrawer's) hide none of the drawers.
HEAD_CAMERA_POS = (0.08, -0.62, 1.30)
HEAD_CAMERA_TARGET = (0.08, -0.04, 0.50)
HEAD_CAMERA_FOVY = 55.0

CABINET_RGBA = (0.86, 0.86, 0.83, 1)
DRAWER_RGBA = (0.72, 0.76, 0.80, 1)
HANDLE_RGBA = (0.25, 0.25, 0.28, 1)


def _defaults() -> str:
    classes = "".join(f'<default class="{name}"><geom contype="{t}" conaffinity="{a}"/></default>'
                      for name, (t, a) in CONTACT_BITS.items())
    return f"""
  <default>
    <geom solref="0.005 1" friction="0.8 0.01 0.001"/>
    {classes}
    <default class="visualonly"><geom contype="0" conaffinity="0" group="1" mass="0"/></default>
    <site group="4"/>
  </default>"""


def _table_and_plate() -> str:
    t = TABLE_TOP
    legs = "".join(_box(f"leg{i}", (sx * 0.72 - 0.03, sy - 0.03, 0), (sx * 0.72 + 0.03, sy + 0.03, t - 0.04),
                        "visualonly", (0.35, 0.35, 0.37, 1))
                   for i, (sx, sy) in enumerate([(-1, -0.5), (1, -0.5), (-1, 0.46), (1, 0.46)]))
    px, py, pz = PLATE_POS
    food = "".join(f'<geom class="visualonly" type="ellipsoid" pos="{_v(px + dx, py + dy, pz + 0.012)}" '
                   f'size="{_v(0.035, 0.025, 0.014)}" euler="0 0 {a}" rgba="0.3 0.62 0.22 1"/>'
                   for dx, dy, a in [(-0.03, 0.01, 0.3), (0.03, -0.02, 1.2), (0.0, 0.035, 2.0)])
    return f"""
    {_box("table", (-0.75, -0.55, t - 0.04), (0.75, 0.50, t), "static", (0.50, 0.50, 0.53, 1))}
    {legs}
    <geom name="plate" class="static" type="cylinder" pos="{_v(px, py, pz - 0.006)}" size="{_v(PLATE_RADIUS, 0.006)}"
          rgba="0.96 0.96 0.96 1"/>
    {food}"""


def _cabinet() -> str:
    f, b, top = CABINET_FRONT_Y, CABINET_BACK_Y, CABINET_TOP
    t, bot, mid = TABLE_TOP, ROW_BOTTOM["B"], ROW_BOTTOM["B"] + 0.15
    parts = [
        _box("cabinet_left", (-0.30, f, t), (-0.29, b, top), "static", CABINET_RGBA),
        _box("cabinet_right", (0.29, f, t), (0.30, b, top), "static", CABINET_RGBA),
        _box("cabinet_divider", (-0.01, f, bot), (0.01, b, top - 0.02), "static", CABINET_RGBA),
        _box("cabinet_bottom", (-0.29, f, t), (0.29, b, bot), "static", CABINET_RGBA),
        _box("cabinet_shelf", (-0.29, f, mid), (0.29, b, ROW_BOTTOM["T"]), "static", CABINET_RGBA),
        _box("cabinet_top", (-0.30, f, top - 0.02), (0.30, b, top), "static", CABINET_RGBA),
        _box("cabinet_back", (-0.29, b - 0.01, bot), (0.29, b, top - 0.02), "static", CABINET_RGBA),
    ]
    return "\n    ".join(parts)


def _drawer(d: str, damping: float, friction: float) -> str:
    w, fr, bk, fz, wall = INTERIOR_HALF_WIDTH, INTERIOR_FRONT, INTERIOR_BACK, FLOOR_Z, WALL_HEIGHT
    s, hz, hr, hl = HANDLE_STANDOFF, HANDLE_Z, HANDLE_RADIUS, HANDLE_HALF_LENGTH
    return f"""
    <body name="drawer_{d}" pos="{_v(*drawer_origin(d))}">
      <joint name="drawer_{d}" type="slide" axis="0 -1 0" range="0 {DRAWER_TRAVEL}" damping="{damping:.6g}"
             frictionloss="{friction:.6g}" armature="0.05"/>
      {_box(f"{d}_front", (-0.138, 0, 0.005), (0.138, fr, 0.145), "drawer", DRAWER_RGBA, mass="0.4")}
      {_box(f"{d}_floor", (-w - 0.01, fr, fz - 0.01), (w + 0.01, bk + 0.01, fz), "drawer", DRAWER_RGBA, mass="0.4")}
      {_box(f"{d}_left", (-w - 0.01, fr, fz), (-w, bk + 0.01, fz + wall), "drawer", DRAWER_RGBA, mass="0.1")}
      {_box(f"{d}_right", (w, fr, fz), (w + 0.01, bk + 0.01, fz + wall), "drawer", DRAWER_RGBA, mass="0.1")}
      {_box(f"{d}_back", (-w, bk, fz), (w, bk + 0.01, fz + wall), "drawer", DRAWER_RGBA, mass="0.1")}
      <geom name="{d}-H" class="drawer" type="capsule" fromto="{_v(-hl, -s, hz, hl, -s, hz)}" size="{hr}"
            rgba="{_v(*HANDLE_RGBA)}" mass="0.05" friction="1 0.01 0.001"/>
      <geom name="{d}-H_l" class="drawer" type="cylinder" fromto="{_v(-hl, -s, hz, -hl, 0, hz)}" size="0.006"
            rgba="{_v(*HANDLE_RGBA)}" mass="0.01"/>
      <geom name="{d}-H_r" class="drawer" type="cylinder" fromto="{_v(hl, -s, hz, hl, 0, hz)}" size="0.006"
            rgba="{_v(*HANDLE_RGBA)}" mass="0.01"/>
      <site name="{d}-H" pos="{_v(0, -s, hz)}"/>
    </body>"""


def _loose_objects(layout: Layout) -> str:
    d = layout.target_drawer
    x, y = layout.bottle_offset
    base = drawer_origin(d) + [x, INTERIOR_FRONT + y, FLOOR_Z]
    out = [f"""
    <body name="spice" pos="{_v(*(base + [0, 0, BOTTLE_HALF_HEIGHT + 0.0005]))}">
      <freejoint name="spice"/>
      <geom name="spice" class="loose" type="cylinder" size="{_v(BOTTLE_RADIUS, BOTTLE_HALF_HEIGHT)}"
            rgba="{_v(*BOTTLE_RGBA)}" mass="{layout.bottle_mass:.6g}" friction="1 0.01 0.001"/>
      <geom name="spice_cap" class="loose" type="cylinder" pos="0 0 {BOTTLE_HALF_HEIGHT + 0.006}"
            size="0.013 0.006" rgba="0.15 0.15 0.15 1" mass="0.005"/>
    </body>"""]
    for i, o in enumerate(layout.distractors):
        size = {"box": _v(o.size, o.size, o.size), "cylinder": _v(o.size, o.size), "sphere": _v(o.size)}[o.shape]
        p = drawer_origin(o.drawer) + [o.offset[0], INTERIOR_FRONT + o.offset[1], FLOOR_Z + o.size + 0.0005]
        out.append(f"""
    <body name="distractor{i}" pos="{_v(*p)}">
      <freejoint/>
      <geom class="loose" type="{o.shape}" size="{size}" rgba="{_v(*o.rgb, 1)}" mass="{o.mass:.6g}"/>
    </body>""")
    return "".join(out)


def _robot() -> str:
    pb, fl, tcp = PALM_BOTTOM, FINGER_LENGTH, TCP_OFFSET
    grey, dark = "0.55 0.57 0.6 1", "0.2 0.2 0.22 1"
    fingers = "".join(f"""
          <body name="finger_{side}" pos="0 0 {-pb}" gravcomp="1">
            <joint name="finger_{side}" type="slide" axis="0 {sign} 0" range="0 {FINGER_OPEN}" armature="0.01"
                   damping="2"/>
            <geom name="finger_{side}" class="gripper" type="box" pos="{_v(0, sign * 0.004, -fl / 2)}"
                  size="{_v(0.02, 0.004, fl / 2)}" rgba="{dark}" mass="0.05" condim="4" friction="1.2 0.02 0.001"/>
          </body>""" for side, sign in (("l", -1), ("r", 1)))
    return f"""
    <body name="carriage_x" gravcomp="1">
      <joint name="x" type="slide" axis="1 0 0" range="{_v(COMMAND_LOW[0], COMMAND_HIGH[0])}" armature="0.5"/>
      <inertial pos="0 0 0" mass="3" diaginertia="0.05 0.05 0.05"/>
      <body name="carriage_y" gravcomp="1">
        <joint name="y" type="slide" axis="0 1 0" range="{_v(COMMAND_LOW[1], COMMAND_HIGH[1])}" armature="0.5"/>
        <inertial pos="0 0 0" mass="2" diaginertia="0.03 0.03 0.03"/>
        <body name="carriage_z" gravcomp="1">
          <joint name="z" type="slide" axis="0 0 1" range="{_v(COMMAND_LOW[2], COMMAND_HIGH[2])}" armature="0.5"/>
          <inertial pos="0 0 0.2" mass="1.5" diaginertia="0.02 0.02 0.005"/>
          <geom class="visualonly" type="capsule" fromto="0 0 0.04 0 0 0.5" size="0.012" rgba="{grey}"/>
          <body name="wrist" gravcomp="1">
            <joint name="pitch" type="hinge" axis="1 0 0" range="{_v(COMMAND_LOW[3], COMMAND_HIGH[3])}"
                   armature="0.01" damping="0.5"/>
            <geom name="wrist_hub" class="gripper" type="cylinder" fromto="-0.03 0 0 0.03 0 0" size="0.025"
                  rgba="{grey}" mass="0.2"/>
            <geom name="wrist_neck" class="gripper" type="box" pos="0 0 -0.03" size="0.015 0.015 0.02"
                  rgba="{grey}" mass="0.05"/>
            <geom name="palm" class="gripper" type="box" pos="0 0 -0.05" size="0.025 0.06 0.015" rgba="{grey}"
                  mass="0.2"/>
            <site name="tcp" pos="0 0 {-tcp}"/>
            <camera name="wrist" pos="0 0.0 {-pb - 0.002}" fovy="75"/>
            {fingers}
          </body>
        </body>
      </body>
    </body>"""


def _actuators() -> str:
    lo, hi = COMMAND_LOW, COMMAND_HIGH
    gantry = "".join(f'<position name="{a}" joint="{a}" kp="3000" kv="300" forcerange="-200 200" '
                     f'ctrlrange="{_v(lo[i], hi[i])}"/>' for i, a in enumerate("xyz"))
    # Both fingers get the same target; grip force = kp × (target − contact), so "closed" (target 0)
    # squeezes a 4 cm bottle with 20 N and a 16 mm handle bar with 8 N.
    fingers = "".join(f'<position name="finger_{s}" joint="finger_{s}" kp="1000" kv="10" forcerange="-25 25" '
                      f'ctrlrange="0 {FINGER_OPEN}"/>' for s in "lr")
    return f"""
  <actuator>
    {gantry}
    <position name="pitch" joint="pitch" kp="150" kv="15" forcerange="-30 30" ctrlrange="{_v(lo[3], hi[3])}"/>
    {fingers}
  </actuator>"""


def build_mjcf(layout: Layout) -> str:
    """The MJCF text of the world for ``layout`` (a pure function of it)."""
    drawers = "".join(_drawer(d, layout.drawer_damping[i], layout.drawer_friction[i]) for i, d in enumerate(DRAWERS))
    return f"""<mujoco model="retriever0-drawers">
  <compiler angle="radian" autolimits="true"/>
  <option timestep="{TIMESTEP}" integrator="implicitfast" cone="elliptic" impratio="10"/>
  <visual>
    <quality offsamples="0" numslices="16" numstacks="8" numquads="1"/>
    <global offwidth="640" offheight="480"/>
    <headlight ambient="0.35 0.35 0.35" diffuse="0.45 0.45 0.45" specular="0 0 0"/>
  </visual>
  {_defaults()}
  <worldbody>
    <light name="sun" directional="true" pos="0 -0.5 2.5" dir="0.15 0.35 -1" castshadow="false"
           diffuse="0.6 0.6 0.6" specular="0.1 0.1 0.1"/>
    <geom name="floor" class="static" type="plane" size="3 3 1" rgba="0.30 0.31 0.33 1"/>
    <camera name="head" pos="{_v(*HEAD_CAMERA_POS)}" xyaxes="{_look_at(HEAD_CAMERA_POS, HEAD_CAMERA_TARGET)}"
            fovy="{HEAD_CAMERA_FOVY}"/>
    {_table_and_plate()}
    {_cabinet()}
    {drawers}
    {_loose_objects(layout)}
    {_robot()}
  </worldbody>
  <contact>
    <exclude body1="finger_l" body2="finger_r"/>
  </contact>
  {_actuators()}
</mujoco>
"""


# -- kinematics shared with the skills ----------------------------------------------------------
def tcp_of(command) -> np.ndarray:
    """The tool centre point for a command (or measured robot vector): the pivot plus the
    fingers' direction, rotated about x by the pitch."""
    x, y, z, pitch = command[:4]
    return np.array([x, y + TCP_OFFSET * np.sin(pitch), z - TCP_OFFSET * np.cos(pitch)])


def pivot_for(tcp, pitch: float) -> np.ndarray:
    """The inverse of :func:`tcp_of`: where the pivot goes to put the TCP at ``tcp``."""
    return np.array([tcp[0], tcp[1] - TCP_OFFSET * np.sin(pitch), tcp[2] + TCP_OFFSET * np.cos(pitch)])


# -- the simulation ----------------------------------------------------------------------------
class Sim:
    """One episode's physics, and the only way other modules touch it.

    ``advance`` steps whole physics steps; ``observe`` returns plain values (it travels as a
    message); ``load_qpos`` lets a camera process rebuild the scene from another world's state.
    """

    def __init__(self, layout: Layout):
        self.layout = layout
        self.model = mujoco.MjModel.from_xml_string(build_mjcf(layout))
        self.data = mujoco.MjData(self.model)
        self._steps = 0
        self._stale = False
        self._renderers: dict = {}
        self._index()
        self._season_time = 0.0
        self._slipping = False
        self._u = HOME.copy()
        self._set_robot(HOME)
        self.command(HOME)
        mujoco.mj_forward(self.model, self.data)

    def _index(self) -> None:
        """Addresses of everything observe() reads, looked up once by name."""
        m = self.model
        obj = mujoco.mjtObj

        def joint(n: str) -> int:
            return mujoco.mj_name2id(m, obj.mjOBJ_JOINT, n)

        def ident(kind, n: str) -> int:
            return mujoco.mj_name2id(m, kind, n)

        robot_joints = [joint(a) for a in ("x", "y", "z", "pitch")]
        finger_joints = [joint(f"finger_{s}") for s in "lr"]
        self._robot_q, self._robot_v = m.jnt_qposadr[robot_joints], m.jnt_dofadr[robot_joints]
        self._finger_q, self._finger_v = m.jnt_qposadr[finger_joints], m.jnt_dofadr[finger_joints]
        self._drawer_q = {d: int(m.jnt_qposadr[joint(f"drawer_{d}")]) for d in DRAWERS}
        self._handle_site = {h: ident(obj.mjOBJ_SITE, h) for h in HANDLES}
        self._tcp_site = ident(obj.mjOBJ_SITE, "tcp")
        self._bottle = ident(obj.mjOBJ_BODY, "spice")
        self._bottle_v = int(m.jnt_dofadr[joint("spice")])
        self._bottle_geoms = np.flatnonzero(m.geom_bodyid == self._bottle)
        self._bottle_bits = (m.geom_contype[self._bottle_geoms].copy(), m.geom_conaffinity[self._bottle_geoms].copy())
        # contact labels: what each geom is, for "which thing do both fingers touch"
        self._label = np.full(m.ngeom, "", dtype=object)
        self._label[self._bottle_geoms] = "spice"
        for h in HANDLES:
            for g in (h, h + "_l", h + "_r"):
                self._label[ident(obj.mjOBJ_GEOM, g)] = h
        self._finger_geoms = (ident(obj.mjOBJ_GEOM, "finger_l"), ident(obj.mjOBJ_GEOM, "finger_r"))
        robot_bodies = [ident(obj.mjOBJ_BODY, b) for b in ("wrist", "finger_l", "finger_r")]
        self._is_gripper = np.isin(m.geom_bodyid, robot_bodies)
        self._loose = [b for b in range(m.nbody) if m.body_jntnum[b] == 1
                       and m.jnt_type[m.body_jntadr[b]] == mujoco.mjtJoint.mjJNT_FREE]

    def _set_robot(self, u) -> None:
        self.data.qpos[self._robot_q] = u[:4]
        self.data.qpos[self._finger_q] = FINGER_OPEN * (1.0 - u[4])

    # -- time and commands --
    @property
    def time(self) -> float:
        """Simulated seconds (counted in whole steps, so it is exact to the step)."""
        return self._steps * TIMESTEP

    def command(self, u) -> None:
        """Actuator targets in ``ACTUATORS`` order, clipped to ``COMMAND_LOW``/``COMMAND_HIGH``."""
        u = np.clip(np.asarray(u, dtype=np.float64).reshape(NU), COMMAND_LOW, COMMAND_HIGH)
        self._u = u
        ctrl = self.data.ctrl
        ctrl[:4] = u[:4]
        ctrl[4] = ctrl[5] = FINGER_OPEN * (1.0 - u[4])

    def advance(self, seconds: float) -> None:
        """Step physics by ``seconds``, which must be a whole number of steps (a 5 ms tick is two)."""
        n = round(seconds / TIMESTEP)
        if n < 0 or abs(n * TIMESTEP - seconds) > 1e-9:
            raise ValueError(f"Sim.advance({seconds!r}): expected a non-negative multiple of the "
                             f"{TIMESTEP} s physics step")
        per_tick = round(TICK / TIMESTEP)
        while n > 0:
            k = min(n, per_tick)
            mujoco.mj_step(self.model, self.data, nstep=k)
            self._steps += k
            n -= k
            self._stale = True
            self._after_tick(k * TIMESTEP)

    def _sync(self) -> None:
        """Bring poses up to the stepped positions. mj_step leaves them one step behind (they
        are computed before it integrates); a camera rebuilding from qpos must see the same."""
        if self._stale:
            mujoco.mj_kinematics(self.model, self.data)
            mujoco.mj_camlight(self.model, self.data)
            self._stale = False

    def _after_tick(self, dt: float) -> None:
        """Per-tick bookkeeping: seasoning time, and the end of an injected slip."""
        self._sync()
        d = self.data
        pos = d.xpos[self._bottle]
        if d.xmat[self._bottle][8] < SEASON_COS and self._over_plate(pos):
            self._season_time += dt
        if self._slipping and np.linalg.norm(pos - d.site_xpos[self._tcp_site]) > 0.1:
            self._restore_bottle_contacts()

    @staticmethod
    def _over_plate(pos) -> bool:
        dx, dy = pos[0] - PLATE_POS[0], pos[1] - PLATE_POS[1]
        return dx * dx + dy * dy < SEASON_REACH ** 2 and 0.0 < pos[2] - PLATE_POS[2] < SEASON_HEIGHT

    # -- state --
    def openings(self) -> dict:
        return {d: float(self.data.qpos[a]) for d, a in self._drawer_q.items()}

    def held(self) -> tuple[str, bool]:
        """What both fingers touch ("spice", "TR-H", or ""), and whether the bottle touches
        anything but the gripper (its support)."""
        d = self.data
        if d.ncon == 0:
            return "", False
        pairs = d.contact.geom[: d.ncon]
        touched = ([], [])
        supported = False
        bottle = set(self._bottle_geoms.tolist())
        for g1, g2 in pairs:
            for a, b in ((g1, g2), (g2, g1)):
                if a == self._finger_geoms[0]:
                    touched[0].append(self._label[b])
                elif a == self._finger_geoms[1]:
                    touched[1].append(self._label[b])
                elif a in bottle and not self._is_gripper[b] and b not in bottle:
                    supported = True
        both = set(touched[0]) & set(touched[1]) - {""}
        return (min(both) if both else ""), supported

    def bottle_location(self, held: str, supported: bool, openings: dict) -> str:
        """Where the bottle is: a drawer's name, "gripper", "plate", "table", "floor" or "air"."""
        pos = self.data.xpos[self._bottle]
        if held == "spice" and not supported:
            return "gripper"
        for d in DRAWERS:
            o = drawer_origin(d) - [0, openings[d], 0]
            x, y, z = pos - o
            if (abs(x) < INTERIOR_HALF_WIDTH and INTERIOR_FRONT < y < INTERIOR_BACK
                    and FLOOR_Z < z < FLOOR_Z + 0.13):
                return d
        if np.hypot(*(pos[:2] - PLATE_POS[:2])) < PLATE_RADIUS and pos[2] < PLATE_POS[2] + 0.1:
            return "plate"
        if abs(pos[0]) < 0.75 and -0.55 < pos[1] < 0.5 and TABLE_TOP < pos[2] < TABLE_TOP + 0.1:
            return "table"
        if pos[2] < TABLE_TOP - 0.05:
            return "floor"
        return "air"

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
        self._sync()
        d = self.data
        robot = np.empty(NU)
        robot[:4] = d.qpos[self._robot_q]
        robot[4] = 1.0 - float(np.mean(d.qpos[self._finger_q])) / FINGER_OPEN
        robot_vel = np.empty(NU)
        robot_vel[:4] = d.qvel[self._robot_v]
        robot_vel[4] = -float(np.mean(d.qvel[self._finger_v])) / FINGER_OPEN
        held, supported = self.held()
        openings = self.openings()
        bottle = d.xpos[self._bottle]
        return {
            "t": self.time,
            "qpos": d.qpos.copy(),
            "qvel": d.qvel.copy(),
            "robot": robot,
            "robot_vel": robot_vel.tolist(),
            "command": self._u.tolist(),
            "tcp": d.site_xpos[self._tcp_site].tolist(),
            "drawers": openings,
            "handles": {h: d.site_xpos[s].tolist() for h, s in self._handle_site.items()},
            "bottle_pos": bottle.tolist(),
            "bottle_upright": float(d.xmat[self._bottle][8]),
            "bottle_speed": float(np.linalg.norm(d.qvel[self._bottle_v:self._bottle_v + 3])),
            "bottle_home": self.layout.target_drawer,
            "plate_pos": PLATE_POS.tolist(),
            "held": held,
            "grasped": held == "spice" and not supported,
            "season_time": self._season_time,
            "seasoned": self._season_time >= SEASON_SECONDS,
            "drawers_closed": all(o < CLOSED_OPENING for o in openings.values()),
            "bottle_location": self.bottle_location(held, supported, openings),
        }

    def load_qpos(self, qpos) -> None:
        """Show another world's positions (velocities zeroed): for cameras, not for stepping on."""
        self.data.qpos[:] = np.asarray(qpos, dtype=np.float64)
        self.data.qvel[:] = 0.0
        mujoco.mj_forward(self.model, self.data)

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
        mujoco.mj_forward(self.model, self.data)

    def set_robot(self, u) -> None:
        """Put the robot at command ``u`` and hold it there (scene setup; physics is not stepped)."""
        self._set_robot(np.clip(np.asarray(u, float), COMMAND_LOW, COMMAND_HIGH))
        self.command(u)
        mujoco.mj_forward(self.model, self.data)

    # -- failure injection --
    def slip(self) -> None:
        """A slipped grasp: the bottle stops touching the gripper until it has fallen 10 cm clear
        of the fingers, so it drops out of a closed hand whatever the hand does."""
        m = self.model
        m.geom_contype[self._bottle_geoms] = SLIPPING
        m.geom_conaffinity[self._bottle_geoms] = STATIC | DRAWER | LOOSE
        self._slipping = True

    def _restore_bottle_contacts(self) -> None:
        self.model.geom_contype[self._bottle_geoms] = self._bottle_bits[0]
        self.model.geom_conaffinity[self._bottle_geoms] = self._bottle_bits[1]
        self._slipping = False

    # -- cameras --
    def render(self, camera: str, height: int, width: int) -> np.ndarray:
        """An RGB image (uint8 H×W×3) from ``camera`` ("head" or "wrist"); one renderer per size, made on first use."""
        self._sync()
        r = self._renderer(height, width, segmentation=False)
        r.update_scene(self.data, camera=camera)
        return r.render()

    def render_segmentation(self, camera: str, height: int, width: int) -> np.ndarray:
        """Geom ids per pixel (int32 H×W, −1 for background): ground truth for perception tests."""
        self._sync()
        r = self._renderer(height, width, segmentation=True)
        r.update_scene(self.data, camera=camera)
        return r.render()[..., 0].copy()

    def _renderer(self, height: int, width: int, segmentation: bool):
        key = (height, width, segmentation)
        if key not in self._renderers:
            r = mujoco.Renderer(self.model, height, width)
            if segmentation:
                r.enable_segmentation_rendering()
            self._renderers[key] = r
        return self._renderers[key]

    def close(self) -> None:
        for r in self._renderers.values():
            r.close()
        self._renderers.clear()

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.close()
