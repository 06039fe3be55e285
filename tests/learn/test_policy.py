"""Learned policies as flows (issue 36, section 2): a real LeRobot ACT checkpoint saved with
``save_pretrained`` and loaded back from its directory, a plain torch module from safetensors;
replay bit for bit on the CPU, or from the log with replay="log"."""

from __future__ import annotations

import os
import shutil
import tempfile

import numpy as np
import pytest

torch = pytest.importorskip("torch", reason="policy flows run torch models (the retriever[lerobot] extra)")
pytest.importorskip("lerobot", reason="LeRobotPolicy loads LeRobot checkpoints (the retriever[lerobot] extra)")

from retriever.flow.core import settings_of
from retriever import ActionChunking, Latest, Pipeline, Rate, SetupError, read_log  # noqa: E402
from retriever.flow.core import set_up, tear_down  # noqa: E402
from retriever.learn import LeRobotPolicy  # noqa: E402
from retriever.replay import replay  # noqa: E402
from tests.learn.policies import (  # noqa: E402
    ACTION_DIM, CHUNK, ActPick, Camera, Chunker, Player, act_checkpoint, rows_checkpoint,
)
from tests.log.helpers import cli  # noqa: E402


@pytest.fixture(scope="module")
def checkpoint(tmp_path_factory):
    return act_checkpoint(tmp_path_factory.mktemp("act") / "ckpt")


@pytest.fixture(autouse=True)
def offline(monkeypatch):
    """Nothing may reach a hub: the offline switch on, and every download function LeRobot
    imported made to fail the test if called."""
    monkeypatch.setenv("HF_HUB_OFFLINE", "1")
    import lerobot.configs.policies
    import lerobot.policies.pretrained
    import lerobot.processor.pipeline

    def no_download(*args, **kwargs):
        raise AssertionError(f"hf_hub_download{args} was called")

    for module in (lerobot.configs.policies, lerobot.policies.pretrained, lerobot.processor.pipeline):
        monkeypatch.setattr(module, "hf_hub_download", no_download)


def pick_pipeline(path, **options):
    with Pipeline("pick") as pipe:
        camera = Camera().named("camera") @ Rate(hz=10)
        policy = ActPick(str(path), **options).named("policy").configure(latency=0.05) @ Rate(hz=5)
        player = Player().named("player") @ Rate(hz=50)
        camera.then(policy, sync=Latest())
        port = "chunk" if options.get("output", "chunk") == "chunk" else "action"
        policy.then(player, sync=ActionChunking(control_hz=50) if port == "chunk" else Latest(), map={port: "action"})
    return pipe


def reference_chunk(path, image, state):
    """What LeRobot itself makes of one observation: its own loader, processors and call."""
    from lerobot.policies.act.modeling_act import ACTPolicy
    from lerobot.processor import PolicyProcessorPipeline
    from lerobot.processor.converters import policy_action_to_transition, transition_to_policy_action

    with tempfile.TemporaryDirectory() as folder:  # its config load leaves a temporary copy of the config
        before, tempfile.tempdir = tempfile.tempdir, folder
        try:
            policy = ACTPolicy.from_pretrained(path).eval()
        finally:
            tempfile.tempdir = before
    pre = PolicyProcessorPipeline.from_pretrained(path, config_filename="policy_preprocessor.json")
    post = PolicyProcessorPipeline.from_pretrained(path, config_filename="policy_postprocessor.json",
                                                   to_transition=policy_action_to_transition,
                                                   to_output=transition_to_policy_action)
    observation = {"observation.state": torch.tensor(state, dtype=torch.float32),
                   "observation.images.image": torch.tensor(image).permute(2, 0, 1).float() / 255}
    with torch.no_grad():
        return post(policy.predict_action_chunk(pre(observation)))[0].numpy()


def test_act_checkpoint_runs_as_a_flow_and_replays_bit_for_bit(tmp_path, checkpoint):
    pipe = pick_pipeline(checkpoint)
    pipe.run(duration=2.0, log=tmp_path / "run.mcap")
    log = read_log(tmp_path / "run.mcap")
    chunks = [e for e in log.iter_events() if e.node == "policy" and e.port == "chunk"]
    assert len(chunks) == 9  # 5 Hz for 2 s; the first tick comes before the camera's first frame
    first = log.value(chunks[0])
    assert first.shape == (CHUNK, ACTION_DIM) and first.dtype == np.float32
    # the observation the flow built is the one LeRobot builds from the same values
    record = next(s for s in log.iter_steps() if s.node == "policy" and s.produced)
    events = {e.id: e for e in log.iter_events()}
    image, state = (log.value(events[record.consumed[port][0]]) for port in ("image", "state"))
    np.testing.assert_allclose(first, reference_chunk(checkpoint, image, state), rtol=1e-5, atol=1e-6)
    # the player played its rows
    assert any(np.array_equal(log.value(e), first[0]) for e in log.iter_events() if e.node == "player")

    report = replay(log)  # rebuilt from the IR, set up afresh, re-run
    assert report.identical, report.divergences[:1]
    assert report.nodes["policy"].replayed == 10 and report.nodes["policy"].identical == 10
    result = cli("replay", tmp_path / "run.mcap")  # in another process
    assert result.returncode == 0, result.stdout + result.stderr


def test_select_action_emits_one_row_per_tick(tmp_path, checkpoint):
    pipe = pick_pipeline(checkpoint, output="action")
    pipe.run(duration=1.0, log=tmp_path / "run.mcap")
    log = read_log(tmp_path / "run.mcap")
    actions = [log.value(e) for e in log.iter_events() if e.node == "policy"]
    assert len(actions) == 4 and all(a.shape == (ACTION_DIM,) for a in actions)
    assert replay(log).identical


@pytest.mark.parametrize("mode", ["rerun", "log"])
def test_replay_from_the_log_needs_no_checkpoint(tmp_path, checkpoint, mode):
    """replay="log": the replay takes the policy's chunks from the log, never loads the model
    (the checkpoint may be gone) and checks the player downstream; re-run, it needs the model."""
    path = shutil.copytree(checkpoint, tmp_path / "ckpt")
    pipe = pick_pipeline(path)
    pipe.flows[1].configure(replay=mode)
    pipe.run(duration=1.0, log=tmp_path / "run.mcap")
    shutil.rmtree(path)
    log = read_log(tmp_path / "run.mcap")
    if mode == "log":
        report = replay(log)
        assert report.identical and report.nodes["policy"].from_log and report.nodes["player"].identical > 0
    else:
        with pytest.raises(SetupError, match="is not a local checkpoint directory"):
            replay(log)


def test_cuda_declares_replay_from_the_log_and_says_when_there_is_none(checkpoint):
    policy = ActPick(str(checkpoint), device="cuda")
    assert settings_of(policy).replay == "log"
    if torch.cuda.is_available():
        pytest.skip("this machine has CUDA")
    with pytest.raises(RuntimeError, match=r"device='cuda', but torch .* finds no CUDA device .*\n"
                                           r"    hint: device='cpu'"):
        set_up(policy)


def test_no_hub_path_and_no_class_named_by_a_checkpoint(tmp_path, checkpoint, monkeypatch):
    monkeypatch.delenv("HF_HUB_OFFLINE")
    set_up(ActPick(str(checkpoint)))  # with every download function failing the test (the fixture)
    assert os.environ["HF_HUB_OFFLINE"] == "1"
    with pytest.raises(FileNotFoundError, match="'lerobot/act_aloha_sim' is not a local checkpoint directory "
                                                r"\(nothing is fetched from a hub\)"):
        set_up(ActPick("lerobot/act_aloha_sim"))
    path = shutil.copytree(checkpoint, tmp_path / "ckpt")
    doc = (path / "policy_preprocessor.json").read_text()
    (path / "policy_preprocessor.json").write_text(doc.replace('"registry_name": "to_batch_processor"',
                                                               '"class": "os.system"'))
    with pytest.raises(ValueError, match="step 1, names no registered LeRobot processor step"):
        set_up(ActPick(str(path)))


def test_the_observation_must_match_the_checkpoints_features(checkpoint):
    class Wrong(ActPick):
        def step(self, wrist_image: np.ndarray | None = None, state: np.ndarray | None = None):
            return self.act(wrist_image=wrist_image, state=state)

    image, state = np.zeros((24, 32, 3), np.uint8), np.zeros(3)
    wrong = Wrong(str(checkpoint))
    set_up(wrong)
    with pytest.raises(ValueError, match=r"(?s)does not fit the checkpoint's input features .*the policy takes "
                                         r"'observation.images.image', which the observation has no feature for.*"
                                         r"'wrist_image' gives feature 'observation.images.wrist_image', which the"):
        wrong.act(wrist_image=image, state=state)
    renamed = Wrong(str(checkpoint), features={"wrist_image": "observation.images.image"})
    set_up(renamed)
    assert renamed.act(wrist_image=image, state=state)["chunk"].shape == (CHUNK, ACTION_DIM)
    with pytest.raises(ValueError, match=r"'state' gives feature 'observation.state' the shape \(4,\); the "
                                         r"policy was trained on \(3,\)"):
        renamed.act(wrist_image=image, state=np.zeros(4))
    tear_down(renamed)
    assert "model" not in renamed.__dict__
    with pytest.raises(RuntimeError, match="no model loaded: setup\\(\\) has not run"):
        renamed.act(wrist_image=image, state=state)


def test_checkpoint_without_processors_feeds_raw_features(tmp_path):
    path = act_checkpoint(tmp_path / "raw", processors=False)
    policy = ActPick(str(path))
    set_up(policy)
    assert policy.preprocess is None
    assert policy.act(image=np.zeros((24, 32, 3), np.uint8), state=np.zeros(3))["chunk"].shape == (CHUNK, ACTION_DIM)


def test_parameters_are_checked():
    with pytest.raises(ValueError, match=r"(?s)device='tpu' must be 'cpu', 'cuda' or 'cuda:N'.*output='rows' must be"
                                         r".*threads=0 must be an integer >= 1"):
        ActPick("x", device="tpu", output="rows", threads=0)
    with pytest.raises(ValueError, match="rtc=True needs control_hz"):
        ActPick("x", rtc=True)


def test_plain_torch_module_from_safetensors(tmp_path):
    path = rows_checkpoint(tmp_path / "rows")
    policy = Chunker(str(path), steps=4)
    set_up(policy)
    out = policy.act(state=np.array([2.0]))
    np.testing.assert_array_equal(out["chunk"], [[2000], [2001], [2002], [2003]])
    (path / "model.safetensors").unlink()
    with pytest.raises(FileNotFoundError, match="holds no model.safetensors"):
        set_up(Chunker(str(path)))
    from safetensors.torch import save_file
    save_file({"other": torch.zeros(1)}, str(path / "model.safetensors"))
    with pytest.raises(RuntimeError, match="Missing key"):
        set_up(Chunker(str(path)))


def test_rtc_preconditions_are_checked(tmp_path):
    path = str(rows_checkpoint(tmp_path / "rows"))

    class Strict(Chunker):
        def step(self, state: np.ndarray):
            return self.act(state=state)

    with Pipeline("p"):
        flow = Strict(path, rtc=True, control_hz=50) @ Rate(hz=5)
    with pytest.raises(ValueError, match=r"(?s)port\(s\) state have no default.*on_overrun='skip' skips ticks"):
        set_up(flow)


def test_rtc_hands_the_module_the_rows_it_made(tmp_path):
    """prev_chunk_left_over is the leftover's rows as the module made them (with rtc, the chunk
    is emitted from row `delay` on); inference_delay its delay."""
    from tests.learn.policies import Counter

    with Pipeline("rtc") as pipe:
        source = Counter() @ Rate(hz=10)
        policy = Chunker(str(rows_checkpoint(tmp_path / "rows")), steps=30, rtc=True, control_hz=50) \
            .named("policy").configure(latency=0.07, on_overrun="catch_up") @ Rate(hz=3)
        source.then(policy, sync=Latest())
        policy.then(Player() @ Rate(hz=50), sync=ActionChunking(control_hz=50), map={"chunk": "action"})
    pipe.run(duration=2.0)
    calls = policy.model.leftovers
    assert calls[0] == (None, 4)
    chunks = pipe.trace.values_of("policy", "chunk")
    for (rows, delay), previous, made in zip(calls[1:], chunks, calls[1:]):
        assert rows is not None and delay == made[1]
        # the leftover's first row is a row of the previous chunk, and the rest follow it
        start = int(np.flatnonzero(previous[:, 0] == rows[0, 0].item())[0])
        np.testing.assert_array_equal(rows.numpy(), previous[start:start + len(rows)])


def test_sampling_policy_replays_bit_for_bit(tmp_path):
    """A model that samples (diffusion's noise) draws from torch's generator seeded per call with
    seed + its count: the replay, in a process whose generator is elsewhere, draws the same."""
    from safetensors.torch import save_file

    from tests.learn.policies import Counter, NoisyPolicy, noisy_module

    (tmp_path / "noisy").mkdir()
    save_file(noisy_module().state_dict(), str(tmp_path / "noisy" / "model.safetensors"))
    with Pipeline("noisy") as pipe:
        policy = NoisyPolicy(str(tmp_path / "noisy"), seed=7).named("policy") @ Rate(hz=10)
        (Counter() @ Rate(hz=10)).then(policy, sync=Latest())
    pipe.run(duration=1.0, log=tmp_path / "run.mcap")
    chunks = pipe.trace.values_of("policy", "chunk")
    assert len(chunks) == 9 and len({c.tobytes() for c in chunks}) == 9
    torch.manual_seed(12345)
    report = replay(read_log(tmp_path / "run.mcap"))
    assert report.identical and report.nodes["policy"].identical == 10, report.divergences[:1]


def test_a_step_may_take_its_messages_apart(checkpoint):
    """observation = (...): act() takes other names than the step's ports; here a camera frame's
    image and a robot message's field."""
    from tests.learn.test_features import Frame, Joint

    class FromMessages(LeRobotPolicy):
        observation = ("image", "state")

        def step(self, frame: Frame | None = None, joint: Joint | None = None):
            return self.act(image=None if frame is None else frame.rgb, state=None if joint is None else joint.qd)

    policy = FromMessages(str(checkpoint))
    set_up(policy)
    frame = Frame("head", 0.0, np.zeros((24, 32, 3), np.uint8))
    out = policy.step(frame=frame, joint=Joint("elbow", 0.1, np.zeros(3), False))
    assert out["chunk"].shape == (CHUNK, ACTION_DIM)
    assert policy.observed.keys == {"image": "observation.images.image", "state": "observation.state"}
    assert policy.step(frame=frame) is None
    with pytest.raises(ValueError, match=r"FromMessages.act\(\) takes image, state; got image\n    hint: name act"):
        policy.act(image=frame)


def test_offline_is_real_when_huggingface_hub_was_imported_first(checkpoint, monkeypatch):
    """huggingface_hub reads HF_HUB_OFFLINE at its import: setting the environment after it is
    imported changes nothing, so the load turns its own switch on and remakes its sessions."""
    import huggingface_hub
    from huggingface_hub.errors import OfflineModeIsEnabled
    from huggingface_hub.utils import get_session, reset_sessions

    monkeypatch.delenv("HF_HUB_OFFLINE")
    monkeypatch.setattr(huggingface_hub.constants, "HF_HUB_OFFLINE", False)  # as if imported online
    reset_sessions()
    set_up(ActPick(str(checkpoint)))
    assert huggingface_hub.constants.HF_HUB_OFFLINE is True
    with pytest.raises(OfflineModeIsEnabled):  # refused before any connection is tried
        get_session().get("https://huggingface.co/api/models/lerobot/act_aloha_sim")


def test_a_config_lerobot_cannot_read_names_the_flow_and_the_path(tmp_path, checkpoint):
    import json

    path = shutil.copytree(checkpoint, tmp_path / "ckpt")
    config = json.loads((path / "config.json").read_text())
    (path / "config.json").write_text(json.dumps({**config, "type": "evil"}))
    with pytest.raises(ValueError, match=rf"ActPick: {path / 'config.json'} is no LeRobot policy config that this "
                                         r"lerobot reads \(DecodingError(.|\n)*hint: give the directory"):
        set_up(ActPick(str(path)))


def test_loading_a_checkpoint_leaves_no_temporary_file(tmp_path, checkpoint, monkeypatch):
    """LeRobot's PreTrainedConfig.from_pretrained writes a temporary file it never removes; a
    policy flow's load removes it (a run's workers would otherwise leave one in /tmp each load)."""
    import tempfile

    temporary = tmp_path / "tmp"
    temporary.mkdir()
    monkeypatch.setattr(tempfile, "tempdir", str(temporary))
    policy = ActPick(str(checkpoint))
    set_up(policy)
    tear_down(policy)
    assert sorted(p.name for p in temporary.iterdir()) == []
    assert tempfile.gettempdir() == str(temporary)
