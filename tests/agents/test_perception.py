"""Perception: the orange mask, the head camera's projection, and ``inspect`` checked against
segmentation renders (ground truth) on random scenes at the agent's 96x128."""

import numpy as np
import pytest

from agents.perception import OPEN_TO_SEE, bottle_mask, can_see_into, head_camera, inspect
from agents.world import (
    BOTTLE_HALF_HEIGHT,
    DRAWERS,
    FLOOR_Z,
    HOME,
    INTERIOR_FRONT,
    Layout,
    Sim,
    drawer_above,
    drawer_origin,
)

H, W = 96, 128
SCENES_PER_DRAWER = 16


def _bottle_pixels(sim, seg) -> np.ndarray:
    return np.isin(seg, np.flatnonzero(sim.model.geom_bodyid == sim.model.body("spice").id))


def _scene(sim, rng, show_home: bool = False) -> dict:
    """Random openings (some shut), the bottle anywhere it may stand in its drawer, the robot
    parked somewhere beside the cabinet (where InspectDrawer leaves it). ``show_home``: the
    bottle's drawer open at least ``OPEN_TO_SEE`` and the one above it shut."""
    home = sim.layout.target_drawer
    openings = {d: 0.0 if rng.random() < 0.3 else float(rng.uniform(0.03, 0.27)) for d in DRAWERS}
    if show_home:
        openings[home] = float(rng.uniform(OPEN_TO_SEE, 0.27))
        if drawer_above(home):
            openings[drawer_above(home)] = 0.0
    sim.set_openings({d: 0.0 for d in DRAWERS})
    adr = sim.model.jnt_qposadr[sim.model.joint("spice").id]
    x, y = rng.uniform(-0.07, 0.07), rng.uniform(0.075, 0.12)
    sim.data.qpos[adr:adr + 3] = drawer_origin(home) + [x, INTERIOR_FRONT + y, FLOOR_Z + BOTTLE_HALF_HEIGHT + 5e-4]
    sim.data.qpos[adr + 3:adr + 7] = [1, 0, 0, 0]
    sim.set_openings(openings)
    side = rng.choice([-1.0, 1.0])
    sim.set_robot([side * rng.uniform(0.5, 0.6), rng.uniform(-0.25, 0.0), rng.uniform(0.9, 1.1), 0.0, rng.random()])
    return sim.observe()


@pytest.fixture(scope="module")
def scenes():
    """(drawer asked, verdict, bottle in that drawer, bottle pixels in the image, openings) for
    every drawer of 4 × SCENES_PER_DRAWER random scenes."""
    rng = np.random.default_rng(2026)
    rows = []
    for i, home in enumerate(DRAWERS):
        with Sim(Layout.from_seed(100 + i, home)) as sim:
            for k in range(SCENES_PER_DRAWER):
                obs = _scene(sim, rng, show_home=k % 3 == 0)
                rgb, seg = sim.render("head", H, W), sim.render_segmentation("head", H, W)
                visible = int(_bottle_pixels(sim, seg).sum())
                for asked in DRAWERS:
                    verdict = inspect(rgb, asked, obs["drawers"], sim)
                    rows.append((asked, verdict, obs["bottle_location"] == asked, visible, dict(obs["drawers"])))
    return rows


def test_inspect_is_right_on_every_decidable_scene(scenes):
    decided = [r for r in scenes if r[1] != "unknown"]
    wrong = [r for r in decided if r[1] != ("yes" if r[2] and r[3] > 0 else "no")]
    yes = sum(r[1] == "yes" for r in decided)
    print(f"{len(scenes) // 4} scenes, {len(scenes)} questions: {len(decided)} decidable "
          f"({yes} yes, {len(decided) - yes} no), {len(wrong)} wrong")
    assert not wrong
    assert yes >= 8 and len(decided) - yes >= 20
    assert {r[0] for r in decided if r[1] == "yes"} == set(DRAWERS)


def test_a_decidable_drawer_with_the_spice_always_shows_it(scenes):
    for asked, verdict, inside, visible, openings in scenes:
        if inside and verdict != "unknown":
            assert visible >= 5, (asked, openings)


def test_unknown_exactly_when_the_drawer_is_shut_too_far_or_hidden_by_the_one_above(scenes):
    for asked, verdict, _, _, openings in scenes:
        assert (verdict == "unknown") == (not can_see_into(asked, openings))
    assert not can_see_into("BL", {"BL": 0.27, "TL": 0.2})
    assert not can_see_into("TR", {"TR": OPEN_TO_SEE - 0.01})
    assert can_see_into("TR", {"TR": OPEN_TO_SEE, "BR": 0.27})


def test_the_mask_finds_the_bottle_and_nothing_else():
    rng = np.random.default_rng(1)
    with Sim(Layout.from_seed(7, "TL")) as sim:
        for _ in range(6):
            _scene(sim, rng)
            mask = bottle_mask(sim.render("head", H, W))
            truth = _bottle_pixels(sim, sim.render_segmentation("head", H, W))
            assert not (mask & ~truth).any()                  # no false positives
            if truth.sum() >= 10:
                assert mask.sum() >= 0.5 * truth.sum()        # the dark cap is the rest


def test_the_mask_thresholds_on_plain_colours():
    colours = {"bottle": (242, 89, 13), "table": (128, 128, 135), "drawer": (184, 194, 204),
               "green": (51, 166, 77), "blue": (51, 89, 217), "yellow": (230, 217, 38), "black": (5, 2, 1)}
    rgb = np.array([[c for c in colours.values()]], dtype=np.uint8)
    assert bottle_mask(rgb)[0].tolist() == [True] + [False] * (len(colours) - 1)


def test_the_projection_agrees_with_the_renderer():
    with Sim(Layout.from_seed(3, "TR")) as sim:
        sim.set_openings({"TR": 0.27})
        camera = head_camera(sim, H, W)
        rows, cols = np.nonzero(_bottle_pixels(sim, sim.render_segmentation("head", H, W)))
        centre = camera.project(sim.observe()["bottle_pos"])[0]
        assert np.hypot(cols.mean() + 0.5 - centre[0], rows.mean() + 0.5 - centre[1]) < 1.5


def test_inspect_without_a_sim_uses_the_worlds_camera_and_checks_the_drawer():
    with Sim(Layout.from_seed(0, "BR")) as sim:
        sim.set_openings({"BR": 0.27})
        sim.set_robot(HOME)
        rgb, openings = sim.render("head", H, W), sim.observe()["drawers"]
        assert inspect(rgb, "BR", openings) == inspect(rgb, "BR", openings, sim) == "yes"
        assert inspect(rgb, "TR", openings) == "unknown"
    with pytest.raises(ValueError, match="unknown drawer 'XX'"):
        inspect(rgb, "XX", openings)
