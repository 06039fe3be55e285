"""The bag world and its skills, run the way Retriever-0 runs skills (a chunk every 0.5 s that
applies 0.2 s later, played by a rate-limited 200 Hz controller): the flex bag itself (a
trilinear flexcomp whose mouth widens only while held and springs back), OpenBag → InspectBag →
Pick → Extract, the failures the skills must report, determinism, and ``inspect_bag`` checked
against segmentation renders."""

import hashlib
import json
from dataclasses import replace
from itertools import pairwise

import numpy as np
import pytest

from agents.bag_perception import MIN_LINING, inspect_bag, lining_share, target_mask
from agents.bag_skills import BAG_SKILLS, BAG_TRACE, make_bag_skill
from agents.bag_world import (
    OPENED, SPOT_POS, TARGET_HALF_HEIGHT, TARGET_RADIUS, TOP_NODES, BagLayout, BagSim, build_bag_mjcf,
)
from agents.perception import head_camera
from agents.robot import COMMAND_HIGH, FINGER_OPEN, HOME, NU
from agents.sim import TIMESTEP
from agents.skills import command_at, run_skills, tcp_of

SEEDS = range(12)
EPISODE_LIMIT = 25.0        # simulated seconds for OpenBag → InspectBag → Pick → Extract (about 13)
H, W = 96, 128
FINGER_THICKNESS = 0.008


def _table(label: str, runs) -> str:
    return f"{label:>8} " + " ".join(f"{r.skill}={r.status}:{r.seconds:.1f}s" for r in runs)


def _episode(seed: int) -> dict:
    """The whole trace, with the head camera's verdict on the bag before it (shut), when Pick
    starts (after InspectBag) and at the end (the target on the tray)."""
    verdicts = {}

    def look(sim, i, t):
        if i == 2 and "inspected" not in verdicts:
            verdicts["inspected"] = inspect_bag(sim.render("head", H, W), sim)

    with BagSim(BagLayout.from_seed(seed)) as sim:
        verdicts["shut"] = inspect_bag(sim.render("head", H, W), sim)
        runs = run_skills(sim, BAG_TRACE, on_tick=look, make=make_bag_skill)
        verdicts["end"] = inspect_bag(sim.render("head", H, W), sim)
        return {"runs": runs, "obs": sim.observe(), "verdicts": verdicts}


@pytest.fixture(scope="module")
def episodes():
    return {seed: _episode(seed) for seed in SEEDS}


def _succeeded(e) -> bool:
    return (len(e["runs"]) == len(BAG_TRACE) and all(r.status == "done" for r in e["runs"])
            and e["obs"]["extracted"])


# -- the scene ----------------------------------------------------------------------------------
def test_a_layout_is_a_pure_function_of_its_seed():
    assert BagLayout.from_seed(5) == BagLayout.from_seed(5)
    assert BagLayout.from_seed(5) != BagLayout.from_seed(6)
    layouts = [BagLayout.from_seed(s) for s in range(40)]
    assert len({lay.target_offset for lay in layouts}) == 40
    assert {len(lay.distractors) for lay in layouts} == {0, 1, 2, 3}


def test_the_bag_world_drives_the_same_robot_as_the_drawer_world():
    with BagSim(BagLayout.from_seed(0)) as sim:
        obs = sim.observe()
        np.testing.assert_allclose(obs["robot"], HOME, atol=1e-9)
        assert obs["command"] == HOME.tolist() and obs["t"] == 0.0
        sim.command(COMMAND_HIGH + 10.0)
        assert sim.observe()["command"] == COMMAND_HIGH.tolist()
        assert sim.model.nu == NU + 1                           # x y z pitch, two fingers
        for _ in range(100):
            sim.advance(0.005)                                  # one 200 Hz tick
        assert sim.time == 100 * round(0.005 / TIMESTEP) * TIMESTEP
        with pytest.raises(ValueError, match="multiple of the"):
            sim.advance(0.003)


def test_the_model_uses_radians_and_the_fast_render_settings():
    layout = BagLayout.from_seed(0)
    xml = build_bag_mjcf(layout)
    assert '<compiler angle="radian"' in xml and 'castshadow="false"' in xml
    with BagSim(layout) as sim:
        q = sim.model.vis.quality
        assert (q.offsamples, q.numslices, q.numstacks, q.numquads) == (0, 16, 8, 1)
        assert set(sim.model.site_group) == {4}
        for camera, (h, w) in (("head", (H, W)), ("wrist", (64, 64))):
            image = sim.render(camera, h, w)
            assert image.shape == (h, w, 3) and image.dtype == np.uint8 and image.std() > 5


def test_the_bag_starts_shut_with_the_target_hidden_in_it():
    with BagSim(BagLayout.from_seed(1)) as sim:
        sim.advance(0.5)                                # the paper settles under its own weight
        obs = sim.observe()
        assert obs["object_location"] == "bag" and obs["bag_opening"] == pytest.approx(0.054, abs=0.002)
        assert not (obs["bag_opened"] or obs["grasped"] or obs["extracted"]) and obs["held"] == ""
        seg = sim.render_segmentation("head", H, W)
        assert not np.isin(seg, [sim.model.geom("target").id]).any()
        assert inspect_bag(sim.render("head", H, W), sim) == "unknown"


# -- the flex -------------------------------------------------------------------------------------
def test_the_bag_is_a_trilinear_flex_pinned_at_the_bottom():
    xml = build_bag_mjcf(BagLayout.from_seed(0))
    assert 'dof="trilinear"' in xml and 'elastic2d="stretch"' in xml and '<pin id="0 2 4 6"/>' in xml
    assert 'integrator="discrete"' in xml
    with BagSim(BagLayout.from_seed(0)) as sim:
        m = sim.model
        assert m.nflex == 1 and m.flex_nodenum[0] == 8 and m.flex_cellnum.tolist() == [[1, 1, 1]]
        assert m.flex_dim[0] == 2 and m.flex_vertnum[0] > 100       # collisions on the full mesh
        nodes = [m.body(b).name for b in m.flex_nodebodyid]
        assert nodes.count("bag") == 4                                # the bottom four, pinned
        free = sorted(set(nodes) - {"bag"})
        assert free == sorted(b for side in TOP_NODES.values() for b in side)
        assert all(m.body_jntnum[m.body(b).id] == 3 for b in free)    # three slides each: 12 dofs
        assert m.body("bag").jntnum == 0                              # the pinned ones do not move


def _hold_open(sim):
    """OpenBag, then the observation: the fingers hold the mouth spread and drawn open."""
    runs = run_skills(sim, BAG_TRACE[:1], make=make_bag_skill)
    assert [r.status for r in runs] == ["done"], runs[0].reason
    return sim.observe()


def _let_go(sim, seconds=1.5):
    """Close the fingers and take the hand straight up out of the bag, ramped (a jump tunnels)."""
    start = np.asarray(sim.observe()["command"])
    tcp = tcp_of(start)
    closed = np.concatenate([start[:4], [1.0]])
    up = command_at([tcp[0], tcp[1], tcp[2] + 0.15], 0.0, 1.0)
    steps = round(seconds / 0.005)
    for k in range(steps):
        f = min(1.0, 2.0 * (k + 1) / steps)
        g = max(0.0, 2.0 * (k + 1) / steps - 1.0)
        sim.command(start + (closed - start) * f + (up - closed) * g)
        sim.advance(0.005)
    sim.advance(0.5)
    return sim.observe()


def test_the_mouth_is_too_narrow_for_the_hand_until_widened_and_widens_only_while_held():
    """At rest the mouth (5.4 cm) is narrower than the open hand that must go around the target
    (9.6 cm across its fingers); spread inside, the fingers widen it past OPENED; let go of, the
    paper springs back (no plasticity: a trilinear flex's plastic strain stops near 0.35)."""
    with BagSim(BagLayout.from_seed(3)) as sim:
        rest = sim.observe()["bag_opening"]
        open_hand = 2 * FINGER_OPEN + 2 * FINGER_THICKNESS
        assert rest < open_hand - 0.04 and rest > 2 * TARGET_RADIUS
        held = _hold_open(sim)
        assert held["bag_opened"] and held["bag_opening"] >= OPENED > rest + 0.025
        assert held["held"] == "bag"                                  # both fingers on its walls
        assert held["bag_rim"]["near"] < sim.rim()["far"] - OPENED
        after = _let_go(sim)
        assert after["bag_opening"] == pytest.approx(rest, abs=0.003) and not after["bag_opened"]
        assert after["object_location"] == "bag"


def test_the_head_camera_sees_the_target_only_while_the_mouth_is_held_open():
    with BagSim(BagLayout.from_seed(6)) as sim:
        target = sim.model.geom("target").id

        def seen():
            return int((sim.render_segmentation("head", H, W) == target).sum())

        assert seen() == 0 and inspect_bag(sim.render("head", H, W), sim) == "unknown"
        _hold_open(sim)
        assert seen() >= 20 and inspect_bag(sim.render("head", H, W), sim) == "yes"
        _let_go(sim)
        assert seen() == 0 and inspect_bag(sim.render("head", H, W), sim) == "unknown"


def test_the_observation_is_plain_data():
    with BagSim(BagLayout.from_seed(0)) as sim:
        sim.advance(0.1)
        obs = sim.observe()
        arrays = {k: obs.pop(k) for k in ("qpos", "qvel", "robot")}
        assert all(isinstance(a, np.ndarray) and a.dtype == np.float64 for a in arrays.values())
        json.dumps(obs)


# -- the task -----------------------------------------------------------------------------------
def test_open_inspect_pick_extract_succeeds_on_most_seeds(episodes):
    ok = [seed for seed, e in episodes.items() if _succeeded(e)]
    for seed, e in episodes.items():
        print(_table(f"seed {seed}", e["runs"]), f"total {sum(r.seconds for r in e['runs']):.1f}s")
    per_skill = {name: np.mean([e["runs"][i].seconds for e in episodes.values() if len(e["runs"]) > i])
                 for i, (name, _) in enumerate(BAG_TRACE)}
    print(f"bag: {len(ok)}/{len(SEEDS)} episodes succeeded; mean seconds per skill "
          + ", ".join(f"{k} {v:.1f}" for k, v in per_skill.items()))
    assert len(ok) >= 11, [_table(f"seed {s}", episodes[s]["runs"]) for s in SEEDS if s not in ok]


def test_an_episode_takes_under_forty_simulated_seconds(episodes):
    for e in episodes.values():
        assert sum(r.seconds for r in e["runs"]) < EPISODE_LIMIT, _table("", e["runs"])


def test_the_target_is_seen_only_while_the_mouth_is_held_open(episodes):
    """Shut before OpenBag, seen while its fingers hold the mouth open, and shut again once the
    hand has taken the target out (the paper springs back: the camera cannot see in)."""
    for seed, e in episodes.items():
        assert e["verdicts"] == {"shut": "unknown", "inspected": "yes", "end": "unknown"}, seed
        assert e["obs"]["bag_opening"] < 0.06, seed


def test_progress_rises_monotonically_and_ends_done_at_one(episodes):
    for run in episodes[0]["runs"]:
        ps = [p for _, p, _, _ in run.trace]
        assert all(b >= a for a, b in pairwise(ps)), run.skill
        assert ps[-1] == 1.0 and run.trace[-1][2] == "done" and max(ps[:-1]) < 1.0
        if run.skill.startswith("InspectBag"):          # no hand-off before the picture exists
            assert max(ps[:-1]) < 0.9


def test_pick_before_open_bag_fails_and_leaves_the_bag_shut():
    with BagSim(BagLayout.from_seed(3)) as sim:
        runs = run_skills(sim, [("Pick", "target")], make=make_bag_skill)
        assert runs[0].status == "failed" and runs[0].progress < 0.9
        assert "the bag is shut" in runs[0].reason
        obs = sim.observe()
        assert not obs["grasped"] and obs["object_location"] == "bag" and not obs["bag_opened"]


def test_open_bag_fails_when_the_mouth_does_not_widen():
    stiff = replace(BagLayout.from_seed(4), bag_young=100 * BagLayout.from_seed(4).bag_young)    # cardboard
    with BagSim(stiff) as sim:
        runs = run_skills(sim, [("OpenBag", "bag")], make=make_bag_skill)
        assert runs[0].status == "failed" and runs[0].progress < 0.9
        assert "the mouth did not widen" in runs[0].reason
        assert sim.observe()["bag_opening"] < OPENED


def test_extract_needs_the_target_in_hand():
    with BagSim(BagLayout.from_seed(0)) as sim:
        runs = run_skills(sim, [("OpenBag", "bag"), ("Extract", "target")], make=make_bag_skill)
        assert [r.status for r in runs] == ["done", "failed"]
        assert "does not hold the target" in runs[-1].reason


def test_a_slip_while_extracting_fails_the_skill():
    started = {}

    def slip_soon_after_extract_starts(sim, i, t):
        if i == 3:
            started.setdefault("t", t)
            if t - started["t"] >= 0.3 and not started.get("slipped"):
                started["slipped"] = True
                sim.slip()

    with BagSim(BagLayout.from_seed(2)) as sim:
        runs = run_skills(sim, BAG_TRACE, on_tick=slip_soon_after_extract_starts, make=make_bag_skill)
        assert [r.status for r in runs] == ["done", "done", "done", "failed"]
        assert "slipped" in runs[-1].reason and runs[-1].progress < 0.9
        assert not sim.observe()["extracted"]


def test_unknown_skills_and_arguments_name_the_valid_ones():
    with pytest.raises(ValueError, match="unknown bag skill 'Fly': expected one of OpenBag, InspectBag, Pick, Extract"):
        make_bag_skill("Fly", "bag")
    with pytest.raises(ValueError, match=r"Pick\('spice'\): unknown argument, expected one of target"):
        make_bag_skill("Pick", "spice")
    for name, arg in BAG_TRACE:
        assert make_bag_skill(name, arg).name in BAG_SKILLS


# -- determinism --------------------------------------------------------------------------------
def _hashed_run(seed: int) -> tuple[str, list]:
    digest = hashlib.sha256()

    def on_tick(sim, i, t):
        digest.update(sim.data.qpos.tobytes())
        digest.update(json.dumps({k: v for k, v in sim.observe().items()
                                  if k not in ("qpos", "qvel", "robot")}).encode())

    with BagSim(BagLayout.from_seed(seed)) as sim:
        runs = run_skills(sim, BAG_TRACE[:3], on_tick=on_tick, make=make_bag_skill)
    return digest.hexdigest(), [(r.skill, r.status, r.seconds) for r in runs]


def test_the_same_layout_and_commands_give_bitwise_identical_observations():
    first, second = _hashed_run(7), _hashed_run(7)
    assert first == second and [status for _, status, _ in first[1]] == ["done"] * 3
    assert _hashed_run(8)[0] != first[0]


def test_load_qpos_rebuilds_another_worlds_scene_for_a_camera():
    layout = BagLayout.from_seed(2)
    with BagSim(layout) as sim, BagSim(layout) as camera:
        run_skills(sim, BAG_TRACE[:1], make=make_bag_skill)
        camera.load_qpos(sim.observe()["qpos"])
        assert np.array_equal(camera.render("head", H, W), sim.render("head", H, W))
        assert camera.observe()["bag_opening"] == sim.observe()["bag_opening"]


# -- perception ---------------------------------------------------------------------------------
def _shape_mouth(sim, qpos, widen: float, draw: float) -> None:
    """Put the top nodes where a mouth ``widen`` wider than at rest and drawn ``draw`` towards the
    robot has them (qpos holds each free node's x, y, z slide)."""
    m = sim.model
    for side, bodies in TOP_NODES.items():
        dy = (-widen / 2 if side == "near" else widen / 2) - draw
        for b in bodies:
            y = m.body_jntadr[m.body(b).id] + 1
            qpos[m.jnt_qposadr[y]] = dy


def _scenes(rng, seeds=range(3), per_seed=16) -> list:
    """(verdict, target in the bag, its pixels, opening, base share) over random mouth shapes,
    the target in the bag or on the spot."""
    rows = []
    for seed in seeds:
        with BagSim(BagLayout.from_seed(seed)) as sim:
            adr = sim.model.jnt_qposadr[sim.model.joint("target").id]
            target = sim.model.geom("target").id
            for k in range(per_seed):
                qpos = sim.data.qpos.copy()
                _shape_mouth(sim, qpos, rng.uniform(0.0, 0.05), rng.uniform(0.0, 0.05))
                if k % 2:
                    qpos[adr:adr + 3] = SPOT_POS + [0.0, 0.0, TARGET_HALF_HEIGHT]
                else:
                    qpos[adr:adr + 3] = sim.model.qpos0[adr:adr + 3]
                sim.load_qpos(qpos)
                obs, rgb = sim.observe(), sim.render("head", H, W)
                visible = int((sim.render_segmentation("head", H, W) == target).sum())
                rows.append((inspect_bag(rgb, sim), obs["object_location"] == "bag", visible, obs["bag_opening"],
                             lining_share(rgb, head_camera(sim, H, W))))
    return rows


def test_inspect_bag_is_never_wrong_over_random_mouth_shapes():
    rows = _scenes(np.random.default_rng(2026))
    for verdict, inside, visible, opening, share in rows:
        if verdict == "yes":
            assert inside and visible > 0
        if verdict == "no":
            assert not inside and share >= MIN_LINING
        if inside and visible >= 10:
            assert verdict == "yes", (opening, visible)
    print(f"{len(rows)} scenes: {sum(r[0] == 'yes' for r in rows)} yes, {sum(r[0] == 'no' for r in rows)} no")
    assert sum(r[0] == "yes" for r in rows) >= 12 and sum(r[0] == "unknown" for r in rows) >= 12


def test_a_mouth_held_open_on_an_empty_bag_shows_the_base_and_says_no():
    for seed in (0, 5):
        with BagSim(BagLayout.from_seed(seed)) as sim:
            adr = sim.model.jnt_qposadr[sim.model.joint("target").id]
            sim.data.qpos[adr:adr + 3] = SPOT_POS + [0.0, 0.0, TARGET_HALF_HEIGHT]    # not in the bag
            sim.load_qpos(sim.data.qpos)
            assert inspect_bag(sim.render("head", H, W), sim) == "unknown"
            _hold_open(sim)
            rgb = sim.render("head", H, W)
            assert lining_share(rgb, head_camera(sim, H, W)) >= MIN_LINING
            assert inspect_bag(rgb, sim) == "no"


def test_inspect_bag_without_a_sim_uses_the_bag_worlds_camera():
    with BagSim(BagLayout.from_seed(5)) as sim:
        shut = sim.render("head", H, W)
        run_skills(sim, BAG_TRACE[:2], make=make_bag_skill)
        opened = sim.render("head", H, W)
        assert inspect_bag(shut) == inspect_bag(shut, sim) == "unknown"
        assert inspect_bag(opened) == inspect_bag(opened, sim) == "yes"


def test_the_target_mask_thresholds_on_plain_colours():
    colours = {"target": (219, 38, 150), "kraft": (199, 158, 107), "lining": (26, 140, 140), "table": (128, 128, 135),
               "green": (51, 166, 77), "blue": (51, 89, 217), "yellow": (230, 217, 38), "orange": (242, 115, 26)}
    rgb = np.array([[c for c in colours.values()]], dtype=np.uint8)
    assert target_mask(rgb)[0].tolist() == [True] + [False] * (len(colours) - 1)
