"""What every world with the gantry robot has in common: the MJCF document around a task's
scene (:func:`world_mjcf`), and :class:`GantrySim`, the base of each task's simulation.

    GantrySim: stepping, commands, the held item's contacts and slips, cameras, close
       ├── world.Sim         the drawers: its scene, observe(), seasoning time, set_openings
       └── bag_world.BagSim  the bag: its scene, observe(), the flex bag's mouth

The settings (render quality, contact bits, gains) are the ones measured on this machine in
``notes/mujoco-world.md``; where they differ the constant's comment says why.
"""

from __future__ import annotations

import importlib.util
import os
import sys

os.environ.setdefault("MUJOCO_GL", "egl")       # CPU rendering without a display
os.environ.setdefault("LP_NUM_THREADS", "0")    # llvmpipe rasterises in the calling thread

import mujoco
import numpy as np

from .mjcf import JOINTED, LOOSE, SLIPPING, STATIC, TABLE_TOP, default_classes
from .robot import COMMAND_HIGH, COMMAND_LOW, FINGER_OPEN, HOME, NU, robot_actuators, robot_body

def load_triton_before_gl() -> None:
    """Load triton, if it is installed, before the process's first GL context. Mesa's software
    renderer (llvmpipe: MUJOCO_GL=egl on a machine without a GPU) links LLVM, and triton, which torch
    imports on first use of many of its parts (a learned policy's flow in the same process, lerobot's
    models), bundles an LLVM of its own: loaded after a GL context, triton's library crashes the
    process (SIGSEGV in its import); loaded before, both work (tests/agents/test_sim.py)."""
    if "triton" not in sys.modules and importlib.util.find_spec("triton") is not None:
        import triton  # noqa: F401


# The world is ticked at 200 Hz, so the step must divide 5 ms; 2.5 ms is the closest to the 2 ms
# the notes verified (5 ms let the handle slip), and grasping was re-verified with it (tests).
TIMESTEP = 0.0025
TICK = 0.005
SLIP_CLEARANCE = 0.1    # m: a slipped item collides with the gripper again once this far from the TCP


def world_mjcf(model: str, scene: str, integrator: str = "implicitfast") -> str:
    """The MJCF document of a world named ``model``: physics and render settings, the contact
    classes, light and floor, then ``scene`` (the task's cameras and bodies), then the robot.
    A scene with an elastic flex needs ``integrator="discrete"`` (MuJoCo 4 integrates flex
    elasticity only there; notes §5)."""
    return f"""<mujoco model="{model}">
  <compiler angle="radian" autolimits="true"/>
  <option timestep="{TIMESTEP}" integrator="{integrator}" cone="elliptic" impratio="10"/>
  <visual>
    <quality offsamples="0" numslices="16" numstacks="8" numquads="1"/>
    <global offwidth="640" offheight="480"/>
    <headlight ambient="0.35 0.35 0.35" diffuse="0.45 0.45 0.45" specular="0 0 0"/>
  </visual>
  {default_classes()}
  <worldbody>
    <light name="sun" directional="true" pos="0 -0.5 2.5" dir="0.15 0.35 -1" castshadow="false"
           diffuse="0.6 0.6 0.6" specular="0.1 0.1 0.1"/>
    <geom name="floor" class="static" type="plane" size="3 3 1" rgba="0.30 0.31 0.33 1"/>
    {scene}
    {robot_body()}
  </worldbody>
  <contact>
    <exclude body1="finger_l" body2="finger_r"/>
  </contact>
  {robot_actuators()}
</mujoco>
"""


def table_or_below(pos, height: float) -> str:
    """Where an item that is in no container is: on the table (its centre at most ``height`` above
    the top), on the floor, or in the air."""
    if abs(pos[0]) < 0.75 and -0.55 < pos[1] < 0.5 and TABLE_TOP < pos[2] < TABLE_TOP + height:
        return "table"
    if pos[2] < TABLE_TOP - 0.05:
        return "floor"
    return "air"


class GantrySim:
    """One episode of a world built by :func:`world_mjcf`, and the only way other modules touch
    it. ``item`` names the object the task is about (its body, its free joint and the label
    :meth:`held` gives it are all called so).

    ``advance`` steps whole physics steps; ``observe`` (each task's own) returns plain values (it
    travels as a message); ``load_qpos`` lets a camera process rebuild the scene from another
    world's state. A task's class builds its scene, indexes what its ``observe`` reads, labels
    the geoms :meth:`held` should name (``_labels``) and may add bookkeeping to ``_after_tick``.
    """

    # A contact holds the item up when its normal's |z| exceeds this (None: any contact does).
    support_normal_z: float | None = None

    def __init__(self, mjcf: str, item: str):
        self.model = mujoco.MjModel.from_xml_string(mjcf)
        self.data = mujoco.MjData(self.model)
        self._steps = 0
        self._stale = False
        self._renderers: dict = {}
        self._index_robot()
        self._index_item(item)
        self._slipping = False
        self._u = HOME.copy()
        self._set_robot(HOME)
        self.command(HOME)
        self._forward()

    def _index_robot(self) -> None:
        m = self.model
        robot_joints = [m.joint(a).id for a in ("x", "y", "z", "pitch")]
        finger_joints = [m.joint(f"finger_{s}").id for s in "lr"]
        self._robot_q, self._robot_v = m.jnt_qposadr[robot_joints], m.jnt_dofadr[robot_joints]
        self._finger_q, self._finger_v = m.jnt_qposadr[finger_joints], m.jnt_dofadr[finger_joints]
        self._tcp_site = m.site("tcp").id
        self._finger_geoms = (m.geom("finger_l").id, m.geom("finger_r").id)
        self._is_gripper = np.isin(m.geom_bodyid, [m.body(b).id for b in ("wrist", "finger_l", "finger_r")])
        # what each geom is, for "which thing do both fingers touch" ("" for nothing of interest);
        # a contact with a flex has no geom on the flex's side (-1): it is labelled ``_flex_label``
        self._labels = np.full(m.ngeom, "", dtype=object)
        self._flex_label = ""

    def _index_item(self, name: str) -> None:
        m = self.model
        self._item_name = name
        self._item = m.body(name).id
        self._item_v = int(m.joint(name).dofadr[0])
        self._item_geoms = np.flatnonzero(m.geom_bodyid == self._item)
        self._item_geom_set = frozenset(self._item_geoms.tolist())
        self._item_bits = (m.geom_contype[self._item_geoms].copy(), m.geom_conaffinity[self._item_geoms].copy())
        self._labels[self._item_geoms] = name

    def _set_robot(self, u) -> None:
        self.data.qpos[self._robot_q] = u[:4]
        self.data.qpos[self._finger_q] = FINGER_OPEN * (1.0 - u[4])

    def _forward(self) -> None:
        """Recompute everything that follows from the positions (poses, contacts), without stepping."""
        mujoco.mj_forward(self.model, self.data)

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
            raise ValueError(f"{type(self).__name__}.advance({seconds!r}): expected a non-negative multiple "
                             f"of the {TIMESTEP} s physics step")
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
            if self.model.nflex:
                mujoco.mj_flex(self.model, self.data)       # the flex's vertices, for cameras and observe
            self._stale = False

    def _after_tick(self, dt: float) -> None:
        """Per-tick bookkeeping after ``dt`` seconds of physics: the end of an injected slip."""
        if self._slipping:
            self._sync()
            d = self.data
            if np.linalg.norm(d.xpos[self._item] - d.site_xpos[self._tcp_site]) > SLIP_CLEARANCE:
                self._restore_item_contacts()

    # -- state --
    def held(self) -> tuple[str, bool]:
        """What both fingers touch (the item's name, another label from ``_labels`` or ""; the item
        if they touch it and something else, such as a bag's walls pressing on the fingers), and
        whether the item rests on something other than the gripper (see ``support_normal_z``)."""
        d = self.data
        touched = ([], [])
        supported = False
        item = self._item_geom_set
        for (g1, g2), normal_z in zip(d.contact.geom[: d.ncon], d.contact.frame[: d.ncon, 2]):
            for a, b in ((g1, g2), (g2, g1)):
                label = self._labels[b] if b >= 0 else self._flex_label
                if a == self._finger_geoms[0]:
                    touched[0].append(label)
                elif a == self._finger_geoms[1]:
                    touched[1].append(label)
                elif (a in item and (b < 0 or not self._is_gripper[b]) and b not in item
                      and (self.support_normal_z is None or abs(normal_z) > self.support_normal_z)):
                    supported = True
        both = set(touched[0]) & set(touched[1]) - {""}
        if self._item_name in both:
            return self._item_name, supported
        return (min(both) if both else ""), supported

    def _observe_robot(self) -> dict:
        """The facts every world's observation starts with: ``t``; ``qpos``, ``qvel``;
        ``robot``/``robot_vel``: the measured ``ACTUATORS`` values and their rates; ``command``:
        the targets being applied; ``tcp``: the point between the fingertips."""
        self._sync()
        d = self.data
        robot = np.empty(NU)
        robot[:4] = d.qpos[self._robot_q]
        robot[4] = 1.0 - float(np.mean(d.qpos[self._finger_q])) / FINGER_OPEN
        robot_vel = np.empty(NU)
        robot_vel[:4] = d.qvel[self._robot_v]
        robot_vel[4] = -float(np.mean(d.qvel[self._finger_v])) / FINGER_OPEN
        return {
            "t": self.time,
            "qpos": d.qpos.copy(),
            "qvel": d.qvel.copy(),
            "robot": robot,
            "robot_vel": robot_vel.tolist(),
            "command": self._u.tolist(),
            "tcp": d.site_xpos[self._tcp_site].tolist(),
        }

    def _item_speed(self) -> float:
        return float(np.linalg.norm(self.data.qvel[self._item_v:self._item_v + 3]))

    def observe(self) -> dict:
        """The world's state as plain values, starting with :meth:`_observe_robot`'s (each task's own)."""
        raise NotImplementedError

    def load_qpos(self, qpos) -> None:
        """Show another world's positions (velocities zeroed): for cameras, not for stepping on."""
        self.data.qpos[:] = np.asarray(qpos, dtype=np.float64)
        self.data.qvel[:] = 0.0
        self._forward()

    def set_robot(self, u) -> None:
        """Put the robot at command ``u`` and hold it there (scene setup; physics is not stepped)."""
        self._set_robot(np.clip(np.asarray(u, float), COMMAND_LOW, COMMAND_HIGH))
        self.command(u)
        self._forward()

    # -- failure injection --
    def slip(self) -> None:
        """A slipped grasp: the item stops touching the gripper until it has fallen
        ``SLIP_CLEARANCE`` clear of the fingers, so it drops out of a closed hand whatever the hand does."""
        m = self.model
        m.geom_contype[self._item_geoms] = SLIPPING
        m.geom_conaffinity[self._item_geoms] = STATIC | JOINTED | LOOSE
        self._slipping = True

    def _restore_item_contacts(self) -> None:
        self.model.geom_contype[self._item_geoms] = self._item_bits[0]
        self.model.geom_conaffinity[self._item_geoms] = self._item_bits[1]
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
            load_triton_before_gl()
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
