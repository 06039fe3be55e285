"""The robot both worlds share: a gantry (x, y, z) carrying a wrist that pitches about x and a
two-finger gripper, with a camera in the palm. Here: its command vector, its gripper's
geometry, its MJCF and actuators, and the kinematics from a command to the tool centre point.

    carriage x ─ carriage y ─ carriage z ─ wrist (pitch) ─ palm ─ finger_l, finger_r
                                                              └ tcp site, wrist camera

The command vector (``ACTUATORS``) is the wrist pivot's world position, the wrist pitch
(0: fingers down, π/2: fingers pointing +y, away from the robot) and the grip (0 open … 1
closed, both fingers). The wrist frame at pitch 0: z up, the fingers hang down and close along y.
"""

from __future__ import annotations

import numpy as np

from .mjcf import vec

# -- the command vector ------------------------------------------------------------------------
ACTUATORS = ("x", "y", "z", "pitch", "grip")
NU = len(ACTUATORS)
COMMAND_LOW = np.array([-0.65, -0.65, 0.40, -0.30, 0.0])
COMMAND_HIGH = np.array([0.65, 0.45, 1.20, 2.80, 1.0])
MAX_SPEED = np.array([0.5, 0.5, 0.5, 4.0, 6.0])           # m/s, m/s, m/s, rad/s, grip/s
HOME = np.array([0.52, -0.10, 1.00, 0.0, 0.0])            # parked on the right, out of either head camera's view

# -- the gripper -------------------------------------------------------------------------------
FINGER_OPEN = 0.04                      # each finger's travel from the centre line: an 8 cm gap
TCP_OFFSET = 0.12                       # wrist pivot → tool centre point, along the fingers
PALM_BOTTOM = 0.065                     # wrist pivot → palm's lower face
FINGER_LENGTH = 0.08


def robot_body() -> str:
    """The robot's MJCF body tree (geoms of class ``gripper``, the arm's ``visualonly``)."""
    pb, fl, tcp = PALM_BOTTOM, FINGER_LENGTH, TCP_OFFSET
    grey, dark = "0.55 0.57 0.6 1", "0.2 0.2 0.22 1"
    fingers = "".join(f"""
          <body name="finger_{side}" pos="0 0 {-pb}" gravcomp="1">
            <joint name="finger_{side}" type="slide" axis="0 {sign} 0" range="0 {FINGER_OPEN}" armature="0.01"
                   damping="2"/>
            <geom name="finger_{side}" class="gripper" type="box" pos="{vec(0, sign * 0.004, -fl / 2)}"
                  size="{vec(0.02, 0.004, fl / 2)}" rgba="{dark}" mass="0.05" condim="4" friction="1.2 0.02 0.001"/>
          </body>""" for side, sign in (("l", -1), ("r", 1)))
    return f"""
    <body name="carriage_x" gravcomp="1">
      <joint name="x" type="slide" axis="1 0 0" range="{vec(COMMAND_LOW[0], COMMAND_HIGH[0])}" armature="0.5"/>
      <inertial pos="0 0 0" mass="3" diaginertia="0.05 0.05 0.05"/>
      <body name="carriage_y" gravcomp="1">
        <joint name="y" type="slide" axis="0 1 0" range="{vec(COMMAND_LOW[1], COMMAND_HIGH[1])}" armature="0.5"/>
        <inertial pos="0 0 0" mass="2" diaginertia="0.03 0.03 0.03"/>
        <body name="carriage_z" gravcomp="1">
          <joint name="z" type="slide" axis="0 0 1" range="{vec(COMMAND_LOW[2], COMMAND_HIGH[2])}" armature="0.5"/>
          <inertial pos="0 0 0.2" mass="1.5" diaginertia="0.02 0.02 0.005"/>
          <geom class="visualonly" type="capsule" fromto="0 0 0.04 0 0 0.5" size="0.012" rgba="{grey}"/>
          <body name="wrist" gravcomp="1">
            <joint name="pitch" type="hinge" axis="1 0 0" range="{vec(COMMAND_LOW[3], COMMAND_HIGH[3])}"
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


def robot_actuators() -> str:
    """The ``<actuator>`` block: position servos on x, y, z, pitch and on each finger, in the
    order ``GantrySim.command`` fills ``ctrl``."""
    lo, hi = COMMAND_LOW, COMMAND_HIGH
    gantry = "".join(f'<position name="{a}" joint="{a}" kp="3000" kv="300" forcerange="-200 200" '
                     f'ctrlrange="{vec(lo[i], hi[i])}"/>' for i, a in enumerate("xyz"))
    # Both fingers get the same target; grip force = kp × (target − contact), so "closed" (target 0)
    # squeezes a 4 cm bottle with 20 N and a 16 mm handle bar with 8 N.
    fingers = "".join(f'<position name="finger_{s}" joint="finger_{s}" kp="1000" kv="10" forcerange="-25 25" '
                      f'ctrlrange="0 {FINGER_OPEN}"/>' for s in "lr")
    return f"""
  <actuator>
    {gantry}
    <position name="pitch" joint="pitch" kp="150" kv="15" forcerange="-30 30" ctrlrange="{vec(lo[3], hi[3])}"/>
    {fingers}
  </actuator>"""


# -- kinematics shared with the skills ----------------------------------------------------------
def tcp_of(command) -> np.ndarray:
    """The tool centre point for a command (or measured robot vector): the pivot plus the
    fingers' direction, rotated about x by the pitch."""
    x, y, z, pitch = command[:4]
    return np.array([x, y + TCP_OFFSET * np.sin(pitch), z - TCP_OFFSET * np.cos(pitch)])


def pivot_for(tcp, pitch: float) -> np.ndarray:
    """The inverse of :func:`tcp_of`: where the pivot goes to put the TCP at ``tcp``."""
    return np.array([tcp[0], tcp[1] - TCP_OFFSET * np.sin(pitch), tcp[2] + TCP_OFFSET * np.cos(pitch)])
