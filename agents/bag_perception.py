"""Is the target in the bag? Colour segmentation of the head camera's image, standing in for the
belief VLM in the bag world (as :mod:`agents.perception` does for the drawers).

Two colours nothing else in the world has: the target's magenta, and the teal lining of the
bag's inner faces. The target is looked for in the bag's projected box; if it is not there,
the lining tells whether the camera could have seen it: where a target standing anywhere in
the bag would show its top, an open bag shows the lining behind it, a shut one the flaps.

    rgb ──HSV──▶ magenta in the bag's box? ──centroid's ray lands inside the bag?──▶ yes
                     │ (too few pixels)
                     └─▶ lining where the target's top would be? ──▶ no     (flaps there) ──▶ unknown
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np

from .bag_world import (
    BAG_CENTRE, BAG_FLOOR, BAG_INNER, BAG_RIM, BAG_WALL, TARGET_HALF_HEIGHT, TARGET_OFFSET, TARGET_RADIUS,
)
from .perception import PinholeCamera, head_camera, hsv

# HSV thresholds (hue in degrees; saturation and value in 0..1). The target is 315-330°, the
# lining 180°; the nearest other hues are the blue distractor's 226° and the kraft paper's 34°.
TARGET_HUES, LINING_HUES = (295.0, 345.0), (165.0, 195.0)
SAT_MIN, VAL_MIN = 0.45, 0.10
MIN_TARGET = 3          # magenta pixels in the bag's box for a "yes"
# The share of the target's window that must show lining for a "no". At 96x128, over random
# flap angles: a shut bag shows at most 0.29 (the slit), an opened one without the target at
# least 0.71.
MIN_LINING = 0.5
SEEN_HEIGHT = 1.5 * TARGET_HALF_HEIGHT    # above the floor: the middle of what the camera sees of the target


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
    """Image rows and columns (r0, r1, c0, c1; half-open) covering the bag, walls included."""
    (cx, cy), (ix, iy), w = BAG_CENTRE, BAG_INNER, BAG_WALL
    corners = [(cx + sx * (ix + w), cy + sy * (iy + w), z) for sx in (-1, 1) for sy in (-1, 1)
               for z in (BAG_FLOOR, BAG_RIM)]
    return camera.box(corners)


def target_window(camera: PinholeCamera) -> tuple[int, int, int, int]:
    """Image rows and columns (r0, r1, c0, c1) where the top of a target standing anywhere it
    may stand in the bag shows."""
    (cx, cy), z = BAG_CENTRE, BAG_FLOOR + 2 * TARGET_HALF_HEIGHT
    reach = np.add(TARGET_OFFSET, TARGET_RADIUS)
    corners = [(cx + sx * reach[0], cy + sy * reach[1], z) for sx in (-1, 1) for sy in (-1, 1)]
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
    into the bag and the target is not there, ``"unknown"`` if the mouth is too narrow to see
    into (``sim``: a BagSim or MjModel for the camera, else the bag world's default)."""
    rgb = np.asarray(rgb)
    height, width = rgb.shape[:2]
    camera = head_camera(sim, height, width) if sim is not None else _default_camera(height, width)
    r0, r1, c0, c1 = bag_box(camera)
    rows, cols = np.nonzero(target_mask(rgb[r0:r1, c0:c1]))
    if rows.size >= MIN_TARGET and in_bag(camera, cols.mean() + c0 + 0.5, rows.mean() + r0 + 0.5):
        return "yes"
    return "no" if lining_share(rgb, camera) >= MIN_LINING else "unknown"


def lining_share(rgb: np.ndarray, camera: PinholeCamera) -> float:
    """The share of the target's window showing the bag's lining."""
    r0, r1, c0, c1 = target_window(camera)
    return float(lining_mask(rgb[r0:r1, c0:c1]).mean())
