"""The scripted skills (the VLA stand-in), run the way Retriever-0 runs them: a chunk every 0.5 s
that applies 0.2 s later, played by a rate-limited 200 Hz controller (``run_skills``)."""

from itertools import pairwise

import numpy as np
import pytest

from agents.mjcf import TABLE_TOP
from agents.skills import SET_DOWN, SKILLS, Z_SAFE, make_skill, paper_trace, run_skills
from agents.world import BOTTLE_HALF_HEIGHT, DRAWERS, HOME, NU, Layout, Sim

TR_SEEDS = range(12)
EPISODE_LIMIT = 60.0        # simulated seconds for the whole trace
SKILL_LIMIT = 8.0           # simulated seconds for any one skill (most take 2.5-6.5)


def _episode(seed: int, target: str, **timing) -> tuple[list, dict]:
    with Sim(Layout.from_seed(seed, target)) as sim:
        runs = run_skills(sim, paper_trace(target), **timing)
        return runs, sim.observe()


def _succeeded(runs, obs) -> bool:
    return (len(runs) == len(paper_trace("TR")) and all(r.status == "done" for r in runs)
            and obs["seasoned"] and obs["drawers_closed"] and obs["bottle_location"] == "table")


def _table(label: str, runs) -> str:
    return f"{label:>8} " + " ".join(f"{r.skill}={r.status}:{r.seconds:.1f}s" for r in runs)


@pytest.fixture(scope="module")
def tr_episodes():
    return {seed: _episode(seed, "TR") for seed in TR_SEEDS}


def test_the_papers_trace_succeeds_for_a_spice_in_TR(tr_episodes):
    ok = [seed for seed, (runs, obs) in tr_episodes.items() if _succeeded(runs, obs)]
    for seed, (runs, _) in tr_episodes.items():
        print(_table(f"seed {seed}", runs))
    print(f"TR: {len(ok)}/{len(TR_SEEDS)} episodes succeeded")
    assert len(ok) >= 11, [_table(f"seed {s}", tr_episodes[s][0]) for s in TR_SEEDS if s not in ok]


def test_every_skill_takes_a_few_seconds_and_the_episode_under_a_minute(tr_episodes):
    for runs, _ in tr_episodes.values():
        assert all(1.0 <= r.seconds <= SKILL_LIMIT for r in runs), _table("", runs)
        assert sum(r.seconds for r in runs) < EPISODE_LIMIT


@pytest.mark.parametrize("target", DRAWERS)
@pytest.mark.parametrize("seed", [20, 21])
def test_the_trace_succeeds_for_a_spice_in_any_drawer(target, seed):
    runs, obs = _episode(seed, target)
    print(_table(f"{target} {seed}", runs))
    assert _succeeded(runs, obs), _table(target, runs)


def test_the_trace_survives_a_slower_policy_and_progress_hand_off():
    runs, obs = _episode(3, "BR", latency=0.3, obs_delay=0.2, handoff="progress")
    assert all(r.status in ("done", "handed off") for r in runs) and obs["seasoned"] and obs["drawers_closed"]


def test_progress_rises_monotonically_and_ends_done_at_one(tr_episodes):
    runs, _ = tr_episodes[0]
    for run in runs:
        ps = [p for _, p, _, _ in run.trace]
        assert all(b >= a for a, b in pairwise(ps)), run.skill
        assert ps[-1] == 1.0 and run.trace[-1][2] == "done"
        assert max(p for p in ps[:-1]) < 1.0
        if run.skill.startswith("InspectDrawer"):          # no hand-off before the picture exists
            assert max(ps[:-1]) < 0.9
        else:
            assert any(0.9 <= p < 1.0 for p in ps) or len(ps) <= 3, run.skill


def test_unknown_skills_and_arguments_name_the_valid_ones():
    with pytest.raises(ValueError, match="unknown skill 'Fly': expected one of OpenDrawer, InspectDrawer"):
        make_skill("Fly", "TL")
    with pytest.raises(ValueError, match=r"OpenDrawer\('TL'\): unknown argument, expected one of TL-H, TR-H"):
        make_skill("OpenDrawer", "TL")
    for name in SKILLS:
        make_skill(name, {"OpenDrawer": "BR-H", "CloseDrawer": "BR-H", "InspectDrawer": "BR"}.get(name, {
            "Pick": "spice", "PlaceBack": "spice", "Season": "food"}.get(name)))


def test_chunks_are_absolute_targets_that_join_up_between_calls():
    with Sim(Layout.from_seed(0, "TL")) as sim:
        skill = make_skill("OpenDrawer", "TL-H")
        first = skill.act(sim.observe(), 150, 200.0)
        assert first.actions.shape == (150, NU) and first.actions.dtype == np.float64
        np.testing.assert_allclose(first.actions[0], HOME, atol=1e-9)     # it starts where the robot is
        for row in first.actions[:100]:
            sim.command(row)
            sim.advance(0.005)
        second = skill.act(sim.observe(), 150, 200.0)
        np.testing.assert_allclose(second.actions[:50], first.actions[100:], atol=1e-9)


def test_after_done_the_skill_stays_done_and_holds_still():
    with Sim(Layout.from_seed(0, "TR")) as sim:
        runs = run_skills(sim, [("InspectDrawer", "TR")])
        assert runs[0].status == "done"
        skill = make_skill("InspectDrawer", "TR")
        outs = []
        for _ in range(12):
            outs.append(skill.act(sim.observe(), 100, 200.0))
            for row in outs[-1].actions:
                sim.command(row)
                sim.advance(0.005)
        assert outs[-1].status == outs[-2].status == "done" and outs[-1].progress == 1.0
        assert np.array_equal(outs[-1].actions, outs[-2].actions)
        assert np.ptp(outs[-1].actions, axis=0).max() == 0.0


def test_a_slip_while_seasoning_fails_the_skill():
    started = {}

    def slip_a_second_into_season(sim, i, t):
        if i == 2:
            started.setdefault("t", t)
            if t - started["t"] >= 1.0 and not started.get("slipped"):
                started["slipped"] = True
                sim.slip()

    with Sim(Layout.from_seed(2, "TR")) as sim:
        runs = run_skills(sim, [("OpenDrawer", "TR-H"), ("Pick", "spice"), ("Season", "food")],
                          on_tick=slip_a_second_into_season)
        assert [r.status for r in runs] == ["done", "done", "failed"]
        assert "slipped" in runs[-1].reason and runs[-1].progress < 0.9
        assert not sim.observe()["seasoned"]


def test_pick_fails_when_the_spice_is_not_in_the_open_drawer():
    with Sim(Layout.from_seed(3, "TR")) as sim:
        runs = run_skills(sim, [("OpenDrawer", "TL-H"), ("Pick", "spice")])
        assert runs[-1].status == "failed" and runs[-1].progress < 0.9
        assert "TR is open 0.00 m" in runs[-1].reason
        assert not sim.observe()["grasped"]


def test_pick_fails_when_the_open_drawer_above_blocks_the_way_down():
    with Sim(Layout.from_seed(3, "BR")) as sim:
        runs = run_skills(sim, [("OpenDrawer", "TR-H"), ("OpenDrawer", "BR-H"), ("Pick", "spice")])
        assert [r.status for r in runs] == ["done", "done", "failed"]
        assert "TR is open above BR" in runs[-1].reason


def test_season_needs_the_spice_in_hand():
    with Sim(Layout.from_seed(0, "TR")) as sim:
        runs = run_skills(sim, [("Season", "food")])
        assert runs[0].status == "failed" and "does not hold the spice" in runs[0].reason


def test_place_back_returns_the_spice_to_its_drawer_from_the_hand_or_the_table():
    with Sim(Layout.from_seed(1, "BL")) as sim:
        runs = run_skills(sim, [("OpenDrawer", "BL-H"), ("Pick", "spice"), ("PlaceBack", "spice")])
        assert [r.status for r in runs] == ["done"] * 3
        obs = sim.observe()
        assert obs["bottle_location"] == "BL" and obs["held"] == "" and obs["bottle_upright"] > 0.99
        runs = run_skills(sim, [("Pick", "spice"), ("Season", "food"), ("PlaceBack", "spice"),
                                ("CloseDrawer", "BL-H")])
        assert [r.status for r in runs] == ["done"] * 4
        obs = sim.observe()
        assert obs["bottle_location"] == "BL" and obs["drawers_closed"] and obs["seasoned"]


def _spice_beside_the_plate(sim) -> None:
    """The scene Season leaves: the bottle standing where it sets it down, its drawer open."""
    sim.set_openings({sim.layout.target_drawer: 0.27})
    adr = sim.model.jnt_qposadr[sim.model.joint("spice").id]
    qpos = sim.data.qpos.copy()
    qpos[adr:adr + 7] = [*SET_DOWN, TABLE_TOP + BOTTLE_HALF_HEIGHT + 0.0005, 1.0, 0.0, 0.0, 0.0]
    sim.load_qpos(qpos)


def test_a_bottle_that_slipped_onto_the_table_is_not_taken_for_set_down():
    # PlaceBack lowers the bottle onto a drawer's floor, and the table is lower. A bottle that
    # slips as the hand sets off lands standing on the table before the skill looks again; were
    # standing low enough all it took, the skill would let go of nothing and reach p = 0.99 (a
    # hand-off) before its post-condition failed.
    slipped = {}

    def slip_right_after_the_lift(sim, i, t):
        # one tick after the policy call (every 100 ticks) that saw the bottle lifted
        if slipped or round(t / 0.005) % 100 != 1:
            return
        obs = sim.observe()
        if obs["grasped"] and obs["tcp"][2] > Z_SAFE - 0.015:
            slipped["t"] = t
            sim.slip()

    with Sim(Layout.from_seed(0, "TR")) as sim:
        _spice_beside_the_plate(sim)
        runs = run_skills(sim, [("PlaceBack", "spice")], on_tick=slip_right_after_the_lift)
        sim.advance(1.0)
        obs = sim.observe()
    assert slipped and obs["bottle_location"] == "table" and obs["bottle_upright"] > 0.95
    assert runs[0].status == "failed" and "slipped" in runs[0].reason and runs[0].progress < 0.9
    assert "let go" not in {phase for _, _, _, phase in runs[0].trace}
