"""The drawer world: layouts, the model, stepping, observing, rendering, determinism."""

import hashlib
import json

import numpy as np
import pytest

from agents.skills import run_skills
from agents.world import (
    ACTUATORS,
    COMMAND_HIGH,
    COMMAND_LOW,
    DRAWERS,
    HOME,
    MAX_SPEED,
    NU,
    TIMESTEP,
    Layout,
    Sim,
    build_mjcf,
)


@pytest.fixture
def sim():
    s = Sim(Layout.from_seed(0, "TR"))
    yield s
    s.close()


def test_the_command_vector_has_one_limit_and_speed_per_actuator():
    assert ACTUATORS == ("x", "y", "z", "pitch", "grip") and NU == 5
    for a in (COMMAND_LOW, COMMAND_HIGH, MAX_SPEED, HOME):
        assert a.shape == (NU,)
    assert np.all(COMMAND_LOW < COMMAND_HIGH) and np.all(MAX_SPEED > 0)
    assert np.all(COMMAND_LOW <= HOME) and np.all(HOME <= COMMAND_HIGH)
    assert (COMMAND_LOW[4], COMMAND_HIGH[4]) == (0.0, 1.0)


def test_a_layout_is_a_pure_function_of_its_seed():
    assert Layout.from_seed(5) == Layout.from_seed(5)
    assert Layout.from_seed(5) != Layout.from_seed(6)
    assert {Layout.from_seed(s).target_drawer for s in range(40)} == set(DRAWERS)


def test_naming_the_drawer_keeps_the_rest_of_the_seeds_draws():
    a, b = Layout.from_seed(3, "TL"), Layout.from_seed(3, "BR")
    assert (a.target_drawer, b.target_drawer) == ("TL", "BR")
    assert a.bottle_offset == b.bottle_offset and a.bottle_mass == b.bottle_mass
    assert all(d.drawer != a.target_drawer for d in a.distractors)


def test_an_unknown_drawer_is_refused_with_the_valid_names():
    with pytest.raises(ValueError, match="unknown drawer 'XX': expected one of TL, TR, BL, BR"):
        Layout.from_seed(0, "XX")


def test_the_model_uses_radians_and_the_fast_render_settings(sim):
    xml = build_mjcf(sim.layout)
    assert '<compiler angle="radian"' in xml and 'castshadow="false"' in xml
    m = sim.model
    assert (m.vis.quality.offsamples, m.vis.quality.numslices, m.vis.quality.numstacks,
            m.vis.quality.numquads) == (0, 16, 8, 1)
    assert m.opt.timestep == TIMESTEP and round(0.005 / TIMESTEP) * TIMESTEP == pytest.approx(0.005, abs=1e-12)
    pitch = m.joint("pitch")
    assert pitch.range[1] == pytest.approx(2.8)               # radians, not 2.8°
    assert set(m.site_group) == {4}                            # sites stay out of the cameras
    assert m.geom("floor").size[2] == 1.0


def test_the_robot_starts_at_home_and_everything_is_shut(sim):
    obs = sim.observe()
    assert obs["t"] == 0.0
    np.testing.assert_allclose(obs["robot"], HOME, atol=1e-9)
    assert obs["command"] == HOME.tolist()
    assert obs["drawers_closed"] and not obs["grasped"] and not obs["seasoned"]
    assert obs["bottle_location"] == obs["bottle_home"] == "TR"
    assert set(obs["drawers"]) == set(DRAWERS) and set(obs["handles"]) == {f"{d}-H" for d in DRAWERS}


def test_advance_steps_whole_physics_steps_and_counts_time_exactly(sim):
    for _ in range(200):
        sim.advance(0.005)                                     # one 200 Hz tick
    assert sim.time == 200 * round(0.005 / TIMESTEP) * TIMESTEP
    assert sim.observe()["t"] == sim.time
    sim.advance(0.0)
    with pytest.raises(ValueError, match="multiple of the"):
        sim.advance(0.003)


def test_commands_are_clipped_to_the_limits(sim):
    sim.command(COMMAND_HIGH + 10.0)
    assert sim.observe()["command"] == COMMAND_HIGH.tolist()


def test_the_observation_is_plain_data(sim):
    sim.advance(0.1)
    obs = sim.observe()
    arrays = {k: obs.pop(k) for k in ("qpos", "qvel", "robot")}
    assert all(isinstance(a, np.ndarray) and a.dtype == np.float64 for a in arrays.values())
    assert arrays["robot"].shape == (NU,)
    json.dumps(obs)                                            # nothing else needs a codec


def _hashed_run(seed: int) -> tuple[str, list]:
    digest = hashlib.sha256()

    def on_tick(sim, i, t):
        digest.update(sim.data.qpos.tobytes())

    with Sim(Layout.from_seed(seed, "TR")) as s:
        runs = run_skills(s, [("OpenDrawer", "TR-H"), ("Pick", "spice")], on_tick=on_tick)
    return digest.hexdigest(), [(r.skill, r.status, r.seconds) for r in runs]


def test_the_same_layout_and_commands_give_bitwise_identical_states():
    first, second = _hashed_run(4), _hashed_run(4)
    assert first == second
    assert [status for _, status, _ in first[1]] == ["done", "done"]
    assert _hashed_run(5)[0] != first[0]


def test_load_qpos_rebuilds_another_worlds_scene_for_a_camera():
    layout = Layout.from_seed(2, "BL")
    with Sim(layout) as world, Sim(layout) as camera:
        run_skills(world, [("OpenDrawer", "BL-H")])
        camera.load_qpos(world.observe()["qpos"])
        assert np.array_equal(camera.render("head", 96, 128), world.render("head", 96, 128))
        assert camera.observe()["drawers"] == world.observe()["drawers"]


def test_both_cameras_render_uint8_rgb(sim):
    for camera, (h, w) in (("head", (96, 128)), ("wrist", (64, 64))):
        image = sim.render(camera, h, w)
        assert image.shape == (h, w, 3) and image.dtype == np.uint8 and image.std() > 5
    assert sim.render_segmentation("head", 96, 128).shape == (96, 128)


def test_a_slip_drops_the_bottle_out_of_the_closed_hand_and_then_it_collides_again():
    with Sim(Layout.from_seed(1, "TR")) as s:
        run_skills(s, [("OpenDrawer", "TR-H"), ("Pick", "spice")])
        assert s.observe()["grasped"]
        bits = s.model.geom_contype.copy()
        s.slip()
        for _ in range(200):
            s.advance(0.005)
        obs = s.observe()
        assert not obs["grasped"] and obs["held"] == ""
        assert np.linalg.norm(np.subtract(obs["bottle_pos"], obs["tcp"])) > 0.1
        assert obs["bottle_location"] in ("TR", "table", "floor")
        assert np.array_equal(s.model.geom_contype, bits)     # the bottle touches the gripper again
