"""Is the spice in the drawer just inspected? Colour segmentation of the head camera's image,
standing in for the belief VLM (Retriever-0's BeliefUpdater calls :func:`inspect`).

The bottle is the only orange thing in the world (hue 20°), so an HSV threshold finds it. The
drawer's interior is projected into the image with the head camera's intrinsics and extrinsics
read from the MuJoCo model; the orange blob's centroid is cast back into the drawer (at the
height of a standing bottle's visible upper part) to tell which drawer it stands in:

    rgb ──HSV──▶ bottle mask ──in the drawer's projected box?──▶ centroid ──ray──▶ inside the drawer? ──▶ yes
                                   (too few pixels) ──▶ no        drawer not open enough to see into ──▶ unknown
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from .world import (
    BOTTLE_HALF_HEIGHT, CLOSED_OPENING, FLOOR_Z, INTERIOR_BACK, INTERIOR_FRONT, INTERIOR_HALF_WIDTH,
    check_drawer, drawer_above, drawer_origin,
)

# HSV thresholds from notes/mujoco-world.md §4 (hue in degrees; saturation and value in 0..1).
HUE_MAX, HUE_WRAP, SAT_MIN, VAL_MIN = 28.0, 350.0, 0.45, 0.10
MIN_PIXELS = 2          # fewer orange pixels than this in the drawer's box: no bottle there
# How far a drawer must be open before the head camera sees a bottle wherever it may stand in
# it (7.5-12 cm behind the front wall, ±7 cm sideways): at 0.15 m at least 9 of its orange pixels
# show at 96x128 (measured against segmentation renders, both rows). A bottom drawer also needs
# the drawer above it shut: that one's floor would hide it.
OPEN_TO_SEE = 0.15
SEEN_HEIGHT = 1.3 * BOTTLE_HALF_HEIGHT      # above the floor: the middle of what the camera sees of a bottle


def hsv(rgb: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Hue (degrees), saturation and value (0..1) of each pixel of an RGB uint8 image (float32 H×W each)."""
    x = np.asarray(rgb, dtype=np.float32) / 255.0
    r, g, b = x[..., 0], x[..., 1], x[..., 2]
    top = np.maximum(np.maximum(r, g), b)
    span = top - np.minimum(np.minimum(r, g), b)
    sat = np.where(top > 0, span / np.maximum(top, 1e-6), 0.0)
    safe = np.maximum(span, 1e-6)
    hue = np.where(top == r, ((g - b) / safe) % 6.0,
                   np.where(top == g, (b - r) / safe + 2.0, (r - g) / safe + 4.0)) * 60.0
    return hue, sat, top


def bottle_mask(rgb: np.ndarray) -> np.ndarray:
    """Pixels of the bottle's orange (bool H×W) from an RGB uint8 image (greys have no hue:
    ``SAT_MIN`` keeps them out)."""
    hue, sat, val = hsv(rgb)
    orange = (hue <= HUE_MAX) | (hue >= HUE_WRAP)
    return orange & (sat >= SAT_MIN) & (val >= VAL_MIN)


@dataclass(frozen=True)
class PinholeCamera:
    """A MuJoCo camera as a pinhole: it looks along its −z axis, x right, y up."""
    position: np.ndarray    # world
    axes: np.ndarray        # 3×3, columns: the camera's x, y, z in world coordinates
    focal: float            # pixels
    height: int
    width: int

    def project(self, points) -> np.ndarray:
        """(N, 3) world points → (N, 2) image coordinates (column, row), pixel centres at +0.5."""
        p = (np.atleast_2d(np.asarray(points, dtype=np.float64)) - self.position) @ self.axes
        depth = -p[:, 2]
        return np.stack([self.width / 2 + self.focal * p[:, 0] / depth,
                         self.height / 2 - self.focal * p[:, 1] / depth], axis=1)

    def ray(self, column: float, row: float) -> np.ndarray:
        """The world direction of the ray through image point (column, row)."""
        d = np.array([(column - self.width / 2) / self.focal, -(row - self.height / 2) / self.focal, -1.0])
        return self.axes @ d

    def point_at_height(self, column: float, row: float, z: float) -> np.ndarray | None:
        """Where the ray through (column, row) comes down to height ``z`` (None if it does not go down)."""
        d = self.ray(column, row)
        if d[2] >= 0:
            return None
        return self.position + d * (z - self.position[2]) / d[2]

    def box(self, points) -> tuple[int, int, int, int]:
        """Image rows and columns (r0, r1, c0, c1; half-open, clipped to the image) covering the
        projections of world ``points``."""
        uv = self.project(points)
        c0, r0 = np.floor(uv.min(axis=0)).astype(int)
        c1, r1 = np.ceil(uv.max(axis=0)).astype(int)
        return max(r0, 0), min(r1, self.height), max(c0, 0), min(c1, self.width)


def head_camera(model_or_sim, height: int, width: int, name: str = "head") -> PinholeCamera:
    """The fixed camera ``name`` of a model (or of a Sim's model) at a render size."""
    import mujoco
    model = getattr(model_or_sim, "model", model_or_sim)
    cid = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_CAMERA, name)
    if cid < 0:
        raise ValueError(f"the model has no camera {name!r}")
    fovy = np.deg2rad(model.cam_fovy[cid])
    return PinholeCamera(model.cam_pos[cid].copy(), model.cam_mat0[cid].reshape(3, 3).copy(),
                         (height / 2) / np.tan(fovy / 2), height, width)


@lru_cache(maxsize=8)
def _default_camera(height: int, width: int) -> PinholeCamera:
    """The head camera of the world model (it does not depend on the layout)."""
    from .world import Layout, Sim
    sim = Sim(Layout.from_seed(0))
    try:
        return head_camera(sim, height, width)
    finally:
        sim.close()


def can_see_into(drawer: str, openings: dict) -> bool:
    """Whether the head camera sees all of ``drawer``'s floor where the bottle could stand."""
    above = drawer_above(drawer)
    if above and openings.get(above, 0.0) >= CLOSED_OPENING:
        return False
    return openings.get(drawer, 0.0) >= OPEN_TO_SEE


def drawer_box(camera: PinholeCamera, drawer: str, opening: float) -> tuple[int, int, int, int]:
    """Image rows and columns (r0, r1, c0, c1; half-open) covering the drawer's inside, from the
    floor to a standing bottle's top (the part still in the cabinet shows cabinet, not orange)."""
    o = drawer_origin(drawer) - [0.0, opening, 0.0]
    corners = [o + [x, y, z] for x in (-INTERIOR_HALF_WIDTH, INTERIOR_HALF_WIDTH)
               for y in (INTERIOR_FRONT, INTERIOR_BACK) for z in (FLOOR_Z, FLOOR_Z + 2.4 * BOTTLE_HALF_HEIGHT)]
    return camera.box(corners)


def stands_in(camera: PinholeCamera, drawer: str, opening: float, column: float, row: float) -> bool:
    """Whether the ray through (column, row) meets the drawer's inside at a bottle's mid height."""
    o = drawer_origin(drawer) - [0.0, opening, 0.0]
    hit = camera.point_at_height(column, row, o[2] + FLOOR_Z + SEEN_HEIGHT)
    if hit is None:
        return False
    x, y = hit[0] - o[0], hit[1] - o[1]
    margin = 0.02
    return abs(x) < INTERIOR_HALF_WIDTH + margin and INTERIOR_FRONT - margin < y < INTERIOR_BACK + margin


def inspect(rgb: np.ndarray, drawer: str, openings: dict, sim=None) -> str:
    """``"yes"`` if the orange bottle stands in ``drawer``, ``"no"`` if the drawer is open enough
    to see into and no bottle is there, ``"unknown"`` if it is not (``openings``: metres per
    drawer, as in ``Sim.observe()["drawers"]``; ``sim``: a Sim or MjModel for the camera, else
    the world's default)."""
    check_drawer(drawer)
    if not can_see_into(drawer, openings):
        return "unknown"
    rgb = np.asarray(rgb)
    height, width = rgb.shape[:2]
    camera = head_camera(sim, height, width) if sim is not None else _default_camera(height, width)
    opening = float(openings[drawer])
    r0, r1, c0, c1 = drawer_box(camera, drawer, opening)
    mask = bottle_mask(rgb[r0:r1, c0:c1])
    rows, cols = np.nonzero(mask)
    if rows.size < MIN_PIXELS:
        return "no"
    column, row = cols.mean() + c0 + 0.5, rows.mean() + r0 + 0.5
    return "yes" if stands_in(camera, drawer, opening, column, row) else "no"

