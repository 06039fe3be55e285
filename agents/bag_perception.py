"""Is the target in the bag? Colour segmentation of the head camera's image, standing in for the
belief VLM in the bag world (as :mod:`agents.perception` does for the drawers).

Two colours nothing else in the world has: the target's magenta, and the teal of the base
insert the target stands on. The target is looked for in the bag's projected box; if it is not
there, the base tells whether the camera could have seen it: the base shows only past a near
wall drawn out of the way (the mouth held open by OpenBag), and a target standing on it would
show in front of it. At rest the near rim hides both.

    rgb ──HSV──▶ magenta in the bag's box? ──centroid's ray lands inside the bag?──▶ yes
                     │ (too few pixels)
                     └─▶ teal base showing where the target would stand? ──▶ no     (walls there) ──▶ unknown
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np

from .bag_world import (
    BAG_CENTRE, BAG_FLOOR, BAG_INNER, BAG_RIM, BAG_SKIN, TARGET_HALF_HEIGHT,
)
from .perception import PinholeCamera, head_camera, hsv

# HSV thresholds (hue in degrees; saturation and value in 0..1). The target is 315-330°, the
# base 180°; the nearest other hues are the blue distractor's 226° and the kraft paper's 34°.
TARGET_HUES, LINING_HUES = (295.0, 345.0), (165.0, 195.0)
SAT_MIN, VAL_MIN = 0.45, 0.10
MIN_TARGET = 3          # magenta pixels in the bag's box for a "yes"
# The share of the base's window that must show teal for a "no". At 96x128 an empty bag whose
# mouth OpenBag holds open shows 0.041-0.048 (the base's far strip past the drawn near wall);
# random mouth shapes 0-0.03, a bag at rest 0.
MIN_LINING = 0.025
SEEN_HEIGHT = 1.5 * TARGET_HALF_HEIGHT    # above the floor: the middle of what the camera sees of the target
# How far the walls' rim may lean out of the bag's box at rest when OpenBag draws the mouth open (m)
LEAN = (0.06, 0.02)                       # towards the robot (−y), away from it (+y)


def colour_mask(rgb: np.ndarray, hues: tuple[float, float]) -> np.ndarray:
    """Saturated pixels (bool H×W) whose hue lies in ``hues`` (degrees)."""
    hue, sat, val = hsv(rgb)
    return (hue >= hues[0]) & (hue <= hues[1]) & (sat >= SAT_MIN) & (val >= VAL_MIN)


def target_mask(rgb: np.ndarray) -> np.ndarray:
    return colour_mask(rgb, TARGET_HUES)


def lining_mask(rgb: np.ndarray) -> np.ndarray:
    return colour_mask(rgb, LINING_HUES)


@lru_cache(maxsize=8)
def _default_camera(height: int, width: int) -> PinholeCamera:
    """The head camera of the bag world (it does not depend on the layout)."""
    from .bag_world import BagLayout, BagSim
    sim = BagSim(BagLayout.from_seed(0))
    try:
        return head_camera(sim, height, width)
    finally:
        sim.close()


def bag_box(camera: PinholeCamera) -> tuple[int, int, int, int]:
    """Image rows and columns (r0, r1, c0, c1; half-open) covering the bag, walls included, as far
    as they lean when the mouth is drawn open."""
    (cx, cy), (ix, iy), w = BAG_CENTRE, BAG_INNER, 2 * BAG_SKIN
    corners = [(cx + sx * (ix + w), y, z) for sx in (-1, 1) for y in (cy - iy - w - LEAN[0], cy + iy + w + LEAN[1])
               for z in (BAG_FLOOR, BAG_RIM + w)]
    return camera.box(corners)


def base_window(camera: PinholeCamera) -> tuple[int, int, int, int]:
    """Image rows and columns (r0, r1, c0, c1) where the base's top shows (where it is not hidden)."""
    (cx, cy), (ix, iy) = BAG_CENTRE, BAG_INNER
    corners = [(cx + sx * ix, cy + sy * iy, BAG_FLOOR) for sx in (-1, 1) for sy in (-1, 1)]
    return camera.box(corners)


def in_bag(camera: PinholeCamera, column: float, row: float) -> bool:
    """Whether the ray through (column, row) meets the bag's inside at the target's mid height
    (a target held above the bag projects onto the box but lands behind it)."""
    hit = camera.point_at_height(column, row, BAG_FLOOR + SEEN_HEIGHT)
    if hit is None:
        return False
    margin = 0.02
    return (abs(hit[0] - BAG_CENTRE[0]) < BAG_INNER[0] + margin
            and abs(hit[1] - BAG_CENTRE[1]) < BAG_INNER[1] + margin)


def inspect_bag(rgb: np.ndarray, sim=None) -> str:
    """``"yes"`` if the head camera's image shows the target inside the bag, ``"no"`` if it sees
    the base where the target would stand and the target is not there, ``"unknown"`` if the
    walls hide the inside (``sim``: a BagSim or MjModel for the camera, else the bag world's default)."""
    rgb = np.asarray(rgb)
    height, width = rgb.shape[:2]
    camera = head_camera(sim, height, width) if sim is not None else _default_camera(height, width)
    r0, r1, c0, c1 = bag_box(camera)
    rows, cols = np.nonzero(target_mask(rgb[r0:r1, c0:c1]))
    if rows.size >= MIN_TARGET and in_bag(camera, cols.mean() + c0 + 0.5, rows.mean() + r0 + 0.5):
        return "yes"
    return "no" if lining_share(rgb, camera) >= MIN_LINING else "unknown"


def lining_share(rgb: np.ndarray, camera: PinholeCamera) -> float:
    """The share of the base's window (its projected box) showing the teal base."""
    r0, r1, c0, c1 = base_window(camera)
    return float(lining_mask(rgb[r0:r1, c0:c1]).mean())
