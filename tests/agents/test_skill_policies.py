"""The pluggable Pick policy: what it sees, the scripted Pick behind those inputs, and a
TorchScript module in the loop."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest

from agents.learn.dataset import read_samples
from agents.learn.episodes import pick_episode
from agents.retriever0 import POLICY_NODE, build
from agents.skill_features import SCENE_NAMES, STATE_NAMES, facts_of, sensors
from agents.skill_policies import load_skill_policy
from agents.skills import pick_start
from agents.world import Layout, Sim

PICK_FACTS = ("robot", "robot_vel", "command", "tcp", "bottle_pos", "bottle_upright", "held", "grasped", "drawers",
              "handles", "bottle_location")


@pytest.mark.parametrize("seed", [0, 4])
def test_the_policy_inputs_tell_the_facts_the_scripted_pick_reads(seed):
    with Sim(Layout.from_seed(seed)) as sim:
        openings, command = pick_start(sim.layout)
        sim.set_openings(openings)
        sim.set_robot(command)
        sim.advance(0.5)
        facts = sim.observe()
        state, scene = sensors(facts)
        assert state.shape == (len(STATE_NAMES),) and scene.shape == (len(SCENE_NAMES),)
        rebuilt = facts_of(1.5, state, scene)
    assert rebuilt["t"] == 1.5 and rebuilt["bottle_location"] == sim.layout.target_drawer
    for key in PICK_FACTS:
        want, got = facts[key], rebuilt[key]
        if isinstance(want, dict):
            assert want.keys() == got.keys(), key
            for k in want:
                np.testing.assert_allclose(got[k], want[k], atol=1e-12, err_msg=f"{key}[{k}]")
        elif isinstance(want, str):
            assert got == want, key
        else:
            np.testing.assert_allclose(np.asarray(got, float), np.asarray(want, float), atol=1e-12, err_msg=key)


def test_a_policy_is_given_a_vector_of_the_wrong_length_and_says_so():
    with pytest.raises(ValueError, match="a skill's state has 18 values and its scene 10"):
        facts_of(0.0, np.zeros(17), np.zeros(10))


def test_the_scripted_pick_behind_a_policys_inputs_sends_the_commands_the_skill_flow_sends():
    """The slot is interchangeable: the pick_policy flow running the scripted Pick on its inputs
    drives the robot exactly as the skill flow's own Pick does."""
    commands = {}
    for policy in (None, "scripted"):
        trace = build(seed=2, episode="pick", skill_policy=policy).run(duration=30.0, backend="inproc")
        commands[policy] = [e.value.u for e in trace.events_of("controller", "command")]
        assert [e.value for e in trace.events_of("skill", "progress")][-1].status == "done"
    chunks = trace.events_of(POLICY_NODE, "action")
    assert chunks and not trace.events_of("skill", "chunk")     # Pick's chunks came from the policy flow alone
    assert len(commands[None]) == len(commands["scripted"])
    assert all(np.array_equal(a, b) for a, b in zip(commands[None], commands["scripted"]))


def test_a_torchscript_module_in_the_pick_slot_drives_the_robot(tmp_path):
    pytest.importorskip("torch")
    from tests.agents.replay_policy import save_replay
    scripted = pick_episode(3, "scripted", log=str(tmp_path / "scripted.mcap"))
    logged = save_replay(tmp_path / "scripted.mcap", tmp_path / "replay.pt")
    outcome = pick_episode(3, str(tmp_path / "replay.pt"), log=str(tmp_path / "replayed.mcap"))
    assert scripted.success and outcome.success and outcome.seconds == scripted.seconds
    _, _, replayed = read_samples(tmp_path / "replayed.mcap")
    assert len(replayed) == len(logged) and all(np.array_equal(a, b) for a, b in zip(replayed, logged))


def test_a_policy_module_of_the_wrong_shape_or_kind_is_refused_with_the_reason(tmp_path):
    torch = pytest.importorskip("torch")

    class Wrong(torch.nn.Module):
        def forward(self, state: torch.Tensor, scene: torch.Tensor, wrist: torch.Tensor) -> torch.Tensor:
            return torch.zeros(1, 4)

    torch.jit.script(Wrong()).save(str(tmp_path / "wrong.pt"))
    (tmp_path / "notes.pt").write_text("not a module")
    from agents.skill_policies import SkillObservation
    seen = SkillObservation(0.0, "Pick(spice)", np.zeros(18), np.zeros(10), np.zeros((64, 64, 3), np.uint8))
    with pytest.raises(ValueError, match=r"returned shape \(1, 4\): expected \(1, steps, 5\)"):
        load_skill_policy(str(tmp_path / "wrong.pt")).act(seen, 150, 200.0)
    with pytest.raises(ValueError, match="not a TorchScript module torch.jit.load can read"):
        load_skill_policy(str(tmp_path / "notes.pt"))
    with pytest.raises(ValueError, match="no such file"):
        load_skill_policy(str(tmp_path / "absent.pt"))


def test_retriever_demo_runs_the_task_with_a_policy_module_in_the_pick_slot(tmp_path):
    pytest.importorskip("torch")
    from tests.agents.replay_policy import save_replay
    build(seed=2, drawer="TL", skill_policy="scripted").run(duration=70.0, backend="inproc",
                                                            log=str(tmp_path / "scripted.mcap"))
    logged = save_replay(tmp_path / "scripted.mcap", tmp_path / "replay.pt")
    done = subprocess.run([sys.executable, "-m", "retriever", "demo", "--backend", "inproc", "--drawer", "TL", "--seed",
                           "2", "--skill-policy", "replay.pt", "--out", "pictures"], capture_output=True, text=True,
                          cwd=tmp_path, timeout=300)
    assert done.returncode == 0, done.stdout + done.stderr
    trace = "skill trace: OpenDrawer(TL-H) → InspectDrawer(TL) → Pick(spice) → Season(food) → CloseDrawer(TL-H)"
    assert trace in done.stdout and "task progress: 100%" in done.stdout, done.stdout
    _, _, replayed = read_samples(tmp_path / "run.mcap")
    assert len(replayed) == len(logged) and all(np.array_equal(a, b) for a, b in zip(replayed, logged))
