"""MJCF text shared by the worlds the gantry works in: number formatting, the contact classes,
and the parts every scene draws the same way (boxes from two corners, the table, loose objects,
the fixed head camera).

Collision bits: ``contype`` is what a geom is, ``conaffinity`` what it collides with. Fixed
furniture and the parts moving on joints (drawers, a flex bag's walls) never touch each other (the
joints keep them apart); everything else does. ``SLIPPING`` is a held object's type during an
injected slip: then nothing of the gripper touches it.
"""

from __future__ import annotations

import numpy as np

STATIC, JOINTED, GRIPPER, LOOSE, SLIPPING = 1, 2, 4, 8, 16
CONTACT_BITS = {
    "static": (STATIC, GRIPPER | LOOSE),
    "jointed": (JOINTED, GRIPPER | LOOSE),
    "gripper": (GRIPPER, STATIC | JOINTED | LOOSE),
    "loose": (LOOSE, STATIC | JOINTED | GRIPPER | LOOSE),
}

TABLE_TOP = 0.40        # metres; the table spans x ±0.75, y −0.55 … 0.50


def vec(*xs) -> str:
    """Numbers as an MJCF attribute value ("0.1 -0.2 0.4")."""
    return " ".join(f"{float(x):.6g}" for x in xs)


def box(name: str, lo, hi, cls: str, rgba, **extra) -> str:
    """An axis-aligned box from its two corners (the way furniture is drawn on paper)."""
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    attrs = "".join(f' {k}="{v}"' for k, v in extra.items())
    return (f'<geom name="{name}" class="{cls}" type="box" pos="{vec(*(lo + hi) / 2)}" '
            f'size="{vec(*(hi - lo) / 2)}" rgba="{vec(*rgba)}"{attrs}/>')


def camera(name: str, pos, target, fovy: float) -> str:
    """A fixed camera at ``pos`` looking at ``target``, with world z up in its picture."""
    forward = np.asarray(target, float) - np.asarray(pos, float)
    forward /= np.linalg.norm(forward)
    right = np.cross(forward, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    up = np.cross(right, forward)
    return f'<camera name="{name}" pos="{vec(*pos)}" xyaxes="{vec(*right, *up)}" fovy="{fovy}"/>'


def table() -> str:
    """The table both scenes stand on, its top at ``TABLE_TOP``, on four (visual) legs."""
    t = TABLE_TOP
    legs = "".join(box(f"leg{i}", (sx * 0.72 - 0.03, sy - 0.03, 0), (sx * 0.72 + 0.03, sy + 0.03, t - 0.04),
                       "visualonly", (0.35, 0.35, 0.37, 1))
                   for i, (sx, sy) in enumerate([(-1, -0.5), (1, -0.5), (-1, 0.46), (1, 0.46)]))
    return f"""
    {box("table", (-0.75, -0.55, t - 0.04), (0.75, 0.50, t), "static", (0.50, 0.50, 0.53, 1))}
    {legs}"""


def loose_shape(name: str, pos, shape: str, size: float, rgb, mass: float) -> str:
    """A free body made of one ``shape`` ("box" | "cylinder" | "sphere"; ``size`` its
    half-extent or radius) centred at ``pos``: a distractor."""
    sizes = {"box": vec(size, size, size), "cylinder": vec(size, size), "sphere": vec(size)}[shape]
    return f"""
    <body name="{name}" pos="{vec(*pos)}">
      <freejoint/>
      <geom class="loose" type="{shape}" size="{sizes}" rgba="{vec(*rgb, 1)}" mass="{mass:.6g}"/>
    </body>"""


def default_classes() -> str:
    """The ``<default>`` block: contact softness and friction, one class per kind of geom
    (``CONTACT_BITS``), ``visualonly`` geoms, and sites hidden from the cameras."""
    classes = "".join(f'<default class="{name}"><geom contype="{t}" conaffinity="{a}"/></default>'
                      for name, (t, a) in CONTACT_BITS.items())
    return f"""
  <default>
    <geom solref="0.005 1" friction="0.8 0.01 0.001"/>
    {classes}
    <default class="visualonly"><geom contype="0" conaffinity="0" group="1" mass="0"/></default>
    <site group="4"/>
  </default>"""
