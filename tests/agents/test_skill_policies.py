"""The pluggable Pick policy: what it sees, the scripted Pick behind those inputs, and a
checkpoint run by a TorchPolicy flow (agents.flows.LearnedSkill) in the loop."""

from __future__ import annotations

import json

import numpy as np
import pytest

from agents import retriever0, skill_policies
from agents.flows import LearnedSkill
from agents.learn.episodes import pick_episode
from agents.messages import SkillCmd
from agents.retriever0 import POLICY_NODE, build
from agents.skill_features import SCENE_NAMES, STATE_NAMES, facts_of, sensors
from agents.skill_policies import CONFIG_FILE, KIND, WEIGHTS_FILE, check_skill_policy
from agents.skills import pick_start
from agents.world import Layout, Sim
from retriever import read_log

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


def _logged_ticks(path):
    """(state, scene, chunk) of each tick of the log's pick_policy flow that sent a chunk."""
    import agents.messages  # noqa: F401
    log = read_log(path)
    steps = [s for s in log.iter_steps() if s.node == POLICY_NODE and s.status == "ok" and s.produced]
    events = {e.id: e for e in log.iter_events()}
    return [(log.value(events[s.consumed["state"][0]]), log.value(events[s.consumed["scene"][0]]),
             log.value(events[s.produced[0]]).actions) for s in steps]


def _checkpoint(folder, tensors: dict) -> str:
    """A checkpoint directory: ``tensors`` as model.safetensors, and a Pick MLP's policy.json."""
    from safetensors.torch import save_file
    folder.mkdir()
    save_file(tensors, str(folder / WEIGHTS_FILE))
    (folder / CONFIG_FILE).write_text(json.dumps({"kind": KIND, "state_dim": 18, "scene_dim": 10, "steps": 150,
                                                  "nu": 5, "hidden": 8}))
    return str(folder)


class ReplayPick(LearnedSkill):
    """The learned-policy flow with a module that answers each tick with the logged chunk whose
    state and scene are nearest (its tensors the checkpoint's, loaded by TorchPolicy)."""

    def build(self):
        import torch
        from safetensors import safe_open

        class Replay(torch.nn.Module):
            def __init__(self, ticks: int):
                super().__init__()
                self.register_buffer("keys", torch.zeros(ticks, 28))
                self.register_buffer("chunks", torch.zeros(ticks, 150, 5))

            def forward(self, batch: dict) -> torch.Tensor:
                x = torch.cat([batch["observation.state"], batch["observation.environment_state"]], dim=1)
                return self.chunks[torch.argmin(((self.keys - x) ** 2).sum(dim=1))][None]

        with safe_open(f"{self.path}/{WEIGHTS_FILE}", "pt") as f:
            return Replay(f.get_slice("keys").get_shape()[0])


def test_a_torch_policy_checkpoint_in_the_pick_slot_drives_the_robot(tmp_path, monkeypatch):
    """A TorchPolicy flow in the Pick slot, its module replaying the scripted Pick's logged
    chunks: the same episode, the chunks sent those logged (as float32, the policy's floats)."""
    torch = pytest.importorskip("torch")
    scripted = pick_episode(3, "scripted", log=str(tmp_path / "scripted.mcap"))
    logged = _logged_ticks(tmp_path / "scripted.mcap")
    keys = np.stack([np.concatenate([state, scene]) for state, scene, _ in logged]).astype(np.float32)
    chunks = np.stack([chunk for _, _, chunk in logged]).astype(np.float32)
    path = _checkpoint(tmp_path / "replay", {"keys": torch.from_numpy(keys), "chunks": torch.from_numpy(chunks)})
    monkeypatch.setattr(retriever0, "LearnedSkill", ReplayPick)
    monkeypatch.setattr(skill_policies, "check_weights", lambda folder, config: None)     # not a Pick MLP's tensors
    outcome = pick_episode(3, path, log=str(tmp_path / "replayed.mcap"))
    assert scripted.success and outcome.success and outcome.seconds == scripted.seconds
    replayed = [chunk for _, _, chunk in _logged_ticks(tmp_path / "replayed.mcap")]
    assert len(replayed) == len(chunks) and all(np.array_equal(a, b) for a, b in zip(replayed, chunks))


def test_a_checkpoint_that_is_not_a_pick_policy_is_refused_with_the_reason(tmp_path):
    torch = pytest.importorskip("torch")
    (tmp_path / "empty").mkdir()
    with pytest.raises(ValueError, match="no such directory"):
        check_skill_policy(str(tmp_path / "absent"))
    with pytest.raises(ValueError, match="the directory holds no model.safetensors"):
        check_skill_policy(str(tmp_path / "empty"))
    path = _checkpoint(tmp_path / "wrong", {"keys": torch.zeros(1, 28)})
    for doc, message in [("not json", "policy.json is not readable JSON"),
                         ('{"kind": "os.system", "nu": 5}', "is no Pick policy's config"),
                         (json.dumps({"kind": KIND, "state_dim": 18, "scene_dim": 10, "steps": 150, "nu": 4,
                                      "hidden": 8}), "the robot has 5 actuators"),
                         (json.dumps({"kind": KIND, "state_dim": 18, "scene_dim": "10", "steps": 150, "nu": 5,
                                      "hidden": 8}), "scene_dim must be positive integers")]:
        (tmp_path / "wrong" / CONFIG_FILE).write_text(doc)
        with pytest.raises(ValueError, match=message):
            check_skill_policy(path)


def test_a_policy_module_of_the_wrong_shape_is_refused_with_the_reason(tmp_path):
    torch = pytest.importorskip("torch")

    class Rows(torch.nn.Module):
        def __init__(self):
            super().__init__()
            self.layer = torch.nn.Linear(18, 4)

        def forward(self, batch: dict) -> torch.Tensor:
            return self.layer(batch["observation.state"])

    class Wrong(LearnedSkill):
        def build(self):
            return Rows()

    path = _checkpoint(tmp_path / "wrong", {"layer.weight": torch.zeros(4, 18), "layer.bias": torch.zeros(4)})
    policy = Wrong(path=path)
    policy.setup()
    with pytest.raises(ValueError, match=r"its model returned a chunk of shape \(1, 4\): expected \(steps, 5\)"):
        policy.step(SkillCmd(1, "Pick", "spice"), np.zeros(18), np.zeros(10))


def _mlp_checkpoint(folder, hidden: int = 8, **changes) -> str:
    """A Pick MLP's checkpoint of ``hidden`` units (its policy.json's other sizes the robot's),
    with ``changes`` to its tensors (None drops one)."""
    torch = pytest.importorskip("torch")
    from agents.learn.bc import make_module, save
    config = {"state_dim": 18, "scene_dim": 10, "steps": 150, "nu": 5, "hidden": hidden}
    save(make_module(config), config, folder)
    if changes:
        from safetensors.torch import load_file, save_file
        tensors = {**load_file(str(folder / WEIGHTS_FILE)), **changes}
        save_file({k: v for k, v in tensors.items() if v is not None}, str(folder / WEIGHTS_FILE))
    return str(folder)


def test_weights_that_do_not_fit_the_config_are_refused_before_anything_is_built(tmp_path):
    torch = pytest.importorskip("torch")
    check_skill_policy(_mlp_checkpoint(tmp_path / "good"))
    huge = _mlp_checkpoint(tmp_path / "huge")
    doc = json.loads((tmp_path / "huge" / CONFIG_FILE).read_text())
    (tmp_path / "huge" / CONFIG_FILE).write_text(json.dumps({**doc, "hidden": 65536}))
    for path, message in [(huge, "more than the 16777216 a Pick policy may have"),
                          (_mlp_checkpoint(tmp_path / "shape", **{"net.0.bias": torch.zeros(9)}),
                           r"net.0.bias has shape \(9,\), not \(8,\)"),
                          (_mlp_checkpoint(tmp_path / "extra", extra=torch.zeros(1)), "extra is not the module's"),
                          (_mlp_checkpoint(tmp_path / "missing", x_std=None), "x_std is missing")]:
        with pytest.raises(ValueError, match=message):
            check_skill_policy(path)
        with pytest.raises(ValueError, match=message):
            LearnedSkill(path=path).setup()


def test_a_policy_that_answers_nan_is_stopped_before_the_actuators(tmp_path):
    torch = pytest.importorskip("torch")
    path = _mlp_checkpoint(tmp_path / "nan", y_mean=torch.full((750,), float("nan")))
    policy = LearnedSkill(path=path)
    policy.setup()
    with pytest.raises(ValueError, match="not finite"):
        policy.step(SkillCmd(1, "Pick", "spice"), np.zeros(18), np.zeros(10))


def test_the_controller_refuses_a_target_that_is_not_finite():
    from agents.flows import Controller
    controller = Controller()
    controller.setup()
    first = controller.step(np.full(5, 0.1))["command"].u
    with pytest.raises(ValueError, match="not finite"):
        controller.step(np.array([0.1, np.nan, 0.1, 0.1, 0.1]))
    assert np.array_equal(controller.last, first)


def test_only_the_bare_word_scripted_is_the_scripted_policy(tmp_path, monkeypatch):
    from agents.command import _skill_policy
    monkeypatch.chdir(tmp_path)
    assert _skill_policy("scripted") == "scripted" and _skill_policy(None) is None
    assert _skill_policy("./scripted") == str(tmp_path / "scripted")
    with pytest.raises(ValueError, match="no such directory"):
        check_skill_policy(_skill_policy("./scripted"))


def test_a_lerobot_checkpoint_is_pointed_at_lerobot_policy(tmp_path):
    torch = pytest.importorskip("torch")
    from safetensors.torch import save_file
    (tmp_path / "act").mkdir()
    (tmp_path / "act" / "config.json").write_text('{"type": "act"}')
    save_file({"w": torch.zeros(1)}, str(tmp_path / "act" / WEIGHTS_FILE))
    with pytest.raises(ValueError, match="a LeRobot checkpoint .* agents.learn train; run a LeRobot policy as a "
                                         "retriever.learn.LeRobotPolicy flow"):
        check_skill_policy(str(tmp_path / "act"))


def test_a_policy_trained_on_other_features_is_refused_before_anything_starts(tmp_path):
    """Sizes that fit its own weights but not the robot's vectors: refused by the check, not by
    a tensor-size error at Pick's first tick."""
    pytest.importorskip("torch")
    from agents.learn.bc import make_module, save
    for name, sizes in [("state20", {"state_dim": 20, "scene_dim": 10}), ("scene8", {"state_dim": 18, "scene_dim": 8})]:
        config = {**sizes, "steps": 150, "nu": 5, "hidden": 8}
        save(make_module(config), config, tmp_path / name)
        with pytest.raises(ValueError, match="its state 18 values and its scene 10 .* trained on other features"):
            check_skill_policy(str(tmp_path / name))


def test_weights_that_are_not_finite_or_not_floats_are_refused_before_anything_starts(tmp_path):
    torch = pytest.importorskip("torch")
    nan = _mlp_checkpoint(tmp_path / "nan", y_mean=torch.full((750,), float("nan")))
    with pytest.raises(ValueError, match=r"y_mean holds 750 value\(s\) that are not finite"):
        check_skill_policy(nan)
    inf = _mlp_checkpoint(tmp_path / "inf", **{"net.0.bias": torch.tensor([float("inf")] + [0.0] * 7)})
    with pytest.raises(ValueError, match=r"net.0.bias holds 1 value\(s\) that are not finite"):
        check_skill_policy(inf)
    ints = _mlp_checkpoint(tmp_path / "ints", x_std=torch.ones(28, dtype=torch.int8))
    with pytest.raises(ValueError, match="x_std is I8, not a float tensor"):
        check_skill_policy(ints)
    check_skill_policy(_mlp_checkpoint(tmp_path / "f64", x_std=torch.ones(28, dtype=torch.float64)))


def test_without_torch_a_checkpoint_is_refused_with_the_extra_to_install(tmp_path, monkeypatch):
    import importlib.util
    path = _mlp_checkpoint(tmp_path / "good")
    real = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec", lambda name, *a: None if name == "torch" else real(name, *a))
    with pytest.raises(ValueError, match=r"needs torch, which cannot be imported here\n.*retriever-robotics\[lerobot\]"):
        check_skill_policy(path)


def test_a_demo_whose_policy_setup_fails_leaves_no_log_and_says_so(tmp_path, monkeypatch, capsys):
    """The checkpoint passed the check, then its setup() failed (it changed, a library broke):
    the run did not start, so neither its log nor an empty pictures folder is left."""
    import typer

    from agents import command

    def broken(self):
        raise RuntimeError("the checkpoint changed under it")

    path = _mlp_checkpoint(tmp_path / "policy")
    monkeypatch.setattr(LearnedSkill, "setup", broken)
    monkeypatch.setattr(command.cli, "stop_on_signals", lambda: None)    # the test process keeps its handlers
    with pytest.raises(typer.Exit):
        command.demo(backend="inproc", seed=2, drawer="TL", duration=20.0, skill_policy=path,
                     log=tmp_path / "run.mcap", out=tmp_path / "pictures")
    err = capsys.readouterr().err
    assert "pick_policy.setup() raised RuntimeError: the checkpoint changed under it" in err, err
    assert "no log is left: the run did not start" in err, err
    assert not (tmp_path / "run.mcap").exists() and not (tmp_path / "pictures").exists()


def test_a_save_that_fails_leaves_the_checkpoint_that_was_there(tmp_path, monkeypatch):
    """train --force over a checkpoint, its save failing after the weights are written: the old
    weights and config stay together (new weights with the old config would pass the check)."""
    pytest.importorskip("torch")
    from agents.learn import bc
    path = _mlp_checkpoint(tmp_path / "policy")
    before = {name: (tmp_path / "policy" / name).read_bytes() for name in (WEIGHTS_FILE, CONFIG_FILE)}
    config = {"state_dim": 18, "scene_dim": 10, "steps": 150, "nu": 5, "hidden": 8}

    def full_disk(*args, **kwargs):
        raise OSError(28, "No space left on device")
    monkeypatch.setattr(bc.json, "dumps", full_disk)
    with pytest.raises(OSError, match="No space left"):
        bc.save(bc.make_module(config), config, path)
    after = {p.name: p.read_bytes() for p in (tmp_path / "policy").iterdir()}
    assert after == before


def test_a_config_too_large_to_be_a_pick_policys_is_not_read(tmp_path):
    path = _mlp_checkpoint(tmp_path / "big")
    doc = json.loads((tmp_path / "big" / CONFIG_FILE).read_text())
    (tmp_path / "big" / CONFIG_FILE).write_text(json.dumps({**doc, "padding": "x" * (1 << 20)}))
    with pytest.raises(ValueError, match=r"policy.json is 10\d{5} bytes; a Pick policy's config is a few hundred"):
        check_skill_policy(path)
