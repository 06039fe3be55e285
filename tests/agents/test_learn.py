"""python -m agents.learn: the loop on Retriever-0's Pick: collecting episodes into logs, exporting
them as a dataset (retriever log export, LeRobot's own writer and loader), training a small policy
into a safetensors checkpoint, running it as a TorchPolicy flow in the Pick slot (inproc, the demo,
real time on zenoh with an identical replay), and evaluating it against the scripted Pick."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

from agents.learn.episodes import parse_seeds
from agents.retriever0 import POLICY_NODE, build
from retriever import read_log
from retriever.replay import replay

pytest.importorskip("torch")
pytest.importorskip("lerobot")


def learn(*args, cwd, timeout=600):
    return subprocess.run([sys.executable, "-m", "agents.learn", *args], capture_output=True, text=True, cwd=cwd,
                          timeout=timeout)


@pytest.fixture(scope="module")
def loop(tmp_path_factory):
    """The whole loop, small: 2 episodes collected, a few epochs trained, 1 held-out seed."""
    folder = tmp_path_factory.mktemp("loop")
    done = learn("all", "--episodes", "2", "--train-seeds", "5:9", "--eval-seeds", "4:5", "--minutes", "1",
                 "--max-epochs", "3", "-o", "run", "--results", "results", cwd=folder)
    assert done.returncode == 0, done.stdout + done.stderr
    return folder, done


def test_the_loop_collects_one_log_per_seed_and_says_how_long_each_took(loop):
    folder, done = loop
    logs = folder / "run" / "logs"
    assert sorted(p.name for p in logs.glob("*.mcap")) == ["pick-seed00005.mcap", "pick-seed00006.mcap"]
    assert "2 episodes in run/logs: 2 succeeded;" in done.stdout and "s wall per episode" in done.stdout, done.stdout
    rows = json.loads((logs / "episodes.json").read_text())
    assert [(r["seed"], r["success"], r["detail"]) for r in rows] == [(5, True, "done"), (6, True, "done")]
    assert {r["drawer"] for r in rows} <= {"TL", "TR", "BL", "BR"} and all(r["wall"] > 0 for r in rows)


def test_collect_keeps_existing_logs_unless_forced(loop):
    folder, _ = loop
    before = (folder / "run" / "logs" / "pick-seed00005.mcap").read_bytes()
    done = learn("collect", "--episodes", "1", "--seeds", "5:6", "-o", "run/logs", cwd=folder)
    assert done.returncode == 2 and "pick-seed00005.mcap already exists" in done.stderr and "--force" in done.stderr
    assert (folder / "run" / "logs" / "pick-seed00005.mcap").read_bytes() == before


def test_the_dataset_is_the_export_of_the_policy_flows_ticks_and_loads_with_lerobot(loop):
    """Frame k of episode e holds what pick_policy consumed on state and scene at its k-th
    tick with a chunk, and the chunk it sent (the step records name the events)."""
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    import agents.messages  # noqa: F401
    folder, _ = loop
    dataset = LeRobotDataset("retriever/dataset", root=folder / "run" / "dataset")
    assert {"observation.state", "observation.environment_state", "observation.images.wrist",
            "action"} <= set(dataset.features) and dataset.meta.total_episodes == 2
    log = read_log(folder / "run" / "logs" / "pick-seed00005.mcap")
    steps = [s for s in log.iter_steps() if s.node == POLICY_NODE and s.status == "ok" and s.produced]
    assert steps and all({"skill", "state", "scene", "wrist"} == set(s.consumed) for s in steps)
    events = {e.id: e for e in log.iter_events()}
    frames = [dataset[i] for i in range(len(dataset)) if int(dataset[i]["episode_index"]) == 0]
    assert len(frames) == len(steps)
    for frame, step in zip(frames, steps):
        (chunk,) = step.produced
        np.testing.assert_array_equal(frame["action"].numpy(),
                                      log.value(events[chunk]).actions.reshape(-1).astype(np.float32))
        np.testing.assert_array_equal(frame["observation.state"].numpy(),
                                      log.value(events[step.consumed["state"][0]]).astype(np.float32))
        assert frame["task"] == "Pick(spice)"


def test_the_npz_export_gives_the_training_the_same_samples(loop, tmp_path):
    from agents.learn.dataset import export, load_dataset
    folder, _ = loop
    logs = sorted((folder / "run" / "logs").glob("*.mcap"))
    export(logs, tmp_path / "npz", format="npz")
    npz, lerobot = load_dataset(tmp_path / "npz"), load_dataset(folder / "run" / "dataset")
    assert npz.action.shape == lerobot.action.shape and npz.action.shape[1:] == (150, 5)
    for name in ("state", "scene", "action"):
        np.testing.assert_array_equal(getattr(npz, name).astype(np.float32), getattr(lerobot, name), err_msg=name)
    assert list(npz.episode) == list(lerobot.episode)


def test_the_checkpoint_is_safetensors_and_json_and_runs_as_a_torch_policy(loop):
    from agents.flows import LearnedSkill
    from agents.messages import SkillCmd
    from retriever.learn import TorchPolicy
    folder, _ = loop
    checkpoint = folder / "run" / "policy"
    assert sorted(p.name for p in checkpoint.iterdir()) == ["model.safetensors", "policy.json"]
    config = json.loads((checkpoint / "policy.json").read_text())
    assert config["kind"] == "agents.learn.bc.PickMLP" and config["training"]["epochs"] == 3
    policy = LearnedSkill(str(checkpoint))
    assert isinstance(policy, TorchPolicy)
    policy.setup()
    out = policy.step(SkillCmd(1, "Pick", "spice"), np.zeros(18), np.zeros(10))
    again = policy.step(SkillCmd(1, "Pick", "spice"), np.zeros(18), np.zeros(10))
    assert out["action"].actions.shape == (150, 5) and out["action"].actions.dtype == np.float64
    assert np.array_equal(out["action"].actions, again["action"].actions)
    assert policy.step(SkillCmd(2, "Season", "food"), np.zeros(18), np.zeros(10)) == {}
    policy.teardown()


def test_the_loop_evaluates_the_learned_and_the_scripted_pick_and_writes_results_and_a_plot(loop):
    folder, done = loop
    results = json.loads((folder / "results" / "results.json").read_text())
    assert (folder / "results" / "learning_loop.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert results["command"].startswith("python -m agents.learn all --episodes 2 --train-seeds 5:9")
    assert results["collected"]["episodes"] == 2 and results["dataset"]["logs"] == 2
    assert results["dataset"]["frames"] > 0 and results["dataset"]["bytes"] > 0
    assert results["training"]["epochs"] == 3 and len(results["training"]["loss_per_epoch"]) == 3
    evaluation = results["evaluation"]
    assert evaluation["seeds"] == "4:5" and evaluation["learned"]["policy"].endswith("policy")
    scripted = evaluation["scripted"]
    assert scripted["skill"]["success_mean"] == 1.0 and scripted["task"]["success_mean"] == 1.0, scripted
    for what in ("skill", "task"):
        (episode,) = evaluation["learned"][what]["episodes"]
        assert episode["seed"] == 4 and evaluation["learned"][what]["success_mean"] == float(episode["success"])
    assert "task: success 1.00 ± 0.00 over 1 seeds (1/1)" in done.stdout, done.stdout


def test_retriever_demo_runs_the_learned_policy_in_the_pick_slot(loop):
    folder, _ = loop
    done = subprocess.run([sys.executable, "-m", "retriever", "demo", "--backend", "inproc", "--drawer", "TL", "--seed",
                           "2", "--duration", "40", "--skill-policy", "run/policy", "--out", "pictures"],
                          capture_output=True, text=True, cwd=folder, timeout=300)
    assert done.returncode == 0, done.stdout + done.stderr
    assert "Pick(spice)" in done.stdout, done.stdout
    log = read_log(folder / "run.mcap")
    node = log.ir.node(POLICY_NODE)
    assert node["type"] == "agents.flows:LearnedSkill" and node["params"]["path"] == str(folder / "run" / "policy")
    chunks = [e for e in log.iter_events() if e.node == POLICY_NODE and e.port == "action"]
    assert chunks and all(log.value(e).actions.shape == (150, 5) for e in chunks)


def test_on_zenoh_in_real_time_the_learned_pick_replays_identically(loop, tmp_path):
    folder, _ = loop
    log = tmp_path / "pick.mcap"
    pipe = build(seed=9, episode="pick", skill_policy=str(folder / "run" / "policy"), deadline=30.0)
    trace = pipe.run(duration=30.0, backend="zenoh", log=str(log), quiet=True)
    assert trace.events_of(POLICY_NODE, "action"), "the learned policy sent no chunk"
    assert [e.value for e in trace.events_of("skill", "progress")][-1].status != "running"
    assert replay(read_log(log)).identical


@pytest.mark.parametrize("args, message", [
    (["evaluate", "--seeds", "3:1"], "--seeds '3:1': expected A:B with 0 <= A < B"),
    (["evaluate", "--seeds", "x"], "--seeds 'x': expected A:B"),
    (["evaluate", "--seeds", "0:1", "--skill-policy", "absent"], "skill policy 'absent': no such directory"),
    (["evaluate", "--seeds", "0:1", "--skill-policy", "empty"], "the directory holds no model.safetensors"),
    (["collect", "--episodes", "5", "--seeds", "0:2", "-o", "d"], "--episodes 5: give 1 to 2"),
    (["export", "empty", "-o", "ds"], "empty: no episodes.json"),
    (["train", "empty", "-o", "p"], "empty: no exported dataset"),
    (["all", "--train-seeds", "0:5", "--eval-seeds", "4:6", "-o", "d"], "--eval-seeds 4:6 overlaps --train-seeds"),
])
def test_bad_arguments_get_a_clear_error(tmp_path, args, message):
    (tmp_path / "empty").mkdir()
    done = learn(*args, cwd=tmp_path)
    assert done.returncode == 2 and message in done.stderr and "Traceback" not in done.stderr, done.stderr


def test_seeds_are_a_half_open_range():
    assert parse_seeds("3:6") == range(3, 6) and parse_seeds("4") == range(4, 5)


def test_an_interrupted_collection_lists_no_stale_episode_and_export_refuses_its_log(tmp_path, monkeypatch):
    """collect --force rewrites episodes.json after each episode, so an interrupted one is not
    left listed as the success it was before; export refuses a log whose run did not finish."""
    from agents.flows import Controller
    from agents.learn.__main__ import collect, export
    out = tmp_path / "logs"
    collect(1, "5:6", out)
    listed = json.loads((out / "episodes.json").read_text())
    assert [(r["seed"], r["success"]) for r in listed] == [(5, True)]
    ticks = []

    def interrupted(self, action):
        ticks.append(1)
        if len(ticks) == 50:
            raise KeyboardInterrupt
        return step(self, action)
    step = Controller.step
    monkeypatch.setattr(Controller, "step", interrupted)
    with pytest.raises(KeyboardInterrupt):
        collect(1, "5:6", out, force=True)
    assert not (out / "episodes.json").exists()
    assert read_log(out / "pick-seed00005.mcap").end["status"] == "interrupted"
    (out / "episodes.json").write_text(json.dumps(listed))      # the list as it was before the fix
    with pytest.raises(ValueError, match=r"pick-seed00005.mcap: its run did not end normally \(interrupted\)"):
        export(out, tmp_path / "dataset", "npz")
    assert not (tmp_path / "dataset").exists()


def test_collect_into_a_folder_of_other_episodes_is_refused_unless_forced(tmp_path):
    from agents.learn.__main__ import collect
    out = tmp_path / "logs"
    out.mkdir()
    (out / "episodes.json").write_text(json.dumps([{"seed": 9, "success": True, "log": "pick-seed00009.mcap"}]))
    with pytest.raises(ValueError, match="episodes.json lists episodes collected before.*--force"):
        collect(1, "5:6", out)
    assert len(json.loads((out / "episodes.json").read_text())) == 1


def test_seeds_a_world_cannot_take_are_refused_before_the_folder_is_made(tmp_path):
    from agents.learn.__main__ import collect
    with pytest.raises(ValueError, match=r"B <= 2\*\*32"):
        collect(None, "5000000000:5000000001", tmp_path / "logs")
    assert not (tmp_path / "logs").exists()


def _strict_json(text: str):
    def refuse(name):
        raise ValueError(f"bare {name} in JSON")
    return json.loads(text, parse_constant=refuse)


def test_a_loss_there_is_none_of_is_null_and_the_output_says_no_episode_was_held_out(loop):
    folder, done = loop
    results = _strict_json((folder / "results" / "results.json").read_text())
    assert results["training"]["held_out_loss"] is None and results["training"]["held_out_episodes"] == 0
    assert "no episode held out" in done.stdout, done.stdout
    assert _strict_json((folder / "run" / "policy" / "policy.json").read_text())["training"]["held_out_loss"] is None


def test_train_refuses_to_replace_a_checkpoint_unless_forced_and_a_file_as_its_folder(loop, tmp_path):
    from agents.learn.__main__ import train_policy
    folder, _ = loop
    before = (folder / "run" / "policy" / "model.safetensors").read_bytes()
    with pytest.raises(ValueError, match="already exists; pass --force"):
        train_policy(folder / "run" / "dataset", folder / "run" / "policy", 1.0, 1)
    assert (folder / "run" / "policy" / "model.safetensors").read_bytes() == before
    (tmp_path / "afile").write_text("")
    done = learn("train", str(folder / "run" / "dataset"), "-o", str(tmp_path / "afile"), cwd=tmp_path)
    assert done.returncode == 2 and "a file is there; the checkpoint is a directory" in done.stderr, done.stderr
    assert "Traceback" not in done.stderr


@pytest.mark.parametrize("args, message", [
    (("train", "ds", "-o", "p", "--max-epochs", "0"), "--max-epochs 0: give a positive number"),
    (("train", "ds", "-o", "p", "--minutes", "-1"), "--minutes -1.0: give a positive number"),
    (("all", "--train-seeds", "0:2", "--eval-seeds", "2:3", "--minutes", "0", "-o", "run"),
     "--minutes 0.0: give a positive number"),
    (("all", "--train-seeds", "0:2000000000", "--eval-seeds", "5:6", "-o", "run"), "overlaps --train-seeds"),
])
def test_budgets_that_train_nothing_and_overlapping_seeds_are_refused_up_front(tmp_path, monkeypatch, capsys, args,
                                                                               message):
    from agents.learn.__main__ import main
    monkeypatch.chdir(tmp_path)
    assert main(list(args)) == 2
    assert message in capsys.readouterr().err
    assert not (tmp_path / "run").exists() and not (tmp_path / "p").exists()


def test_the_loops_output_labels_each_result_and_the_legend_covers_no_bar(loop):
    import matplotlib.pyplot as plt
    from agents.learn.plot import loop_figure
    folder, done = loop
    for name in ("learned", "scripted"):
        assert f"{name} skill: success" in done.stdout and f"{name} task: success" in done.stdout, done.stdout
    fig = loop_figure(json.loads((folder / "results" / "results.json").read_text()))
    try:
        bars = fig.axes[0]
        renderer = fig.canvas.get_renderer()
        legend = bars.get_legend().get_window_extent(renderer)
        marks = [p.get_window_extent(renderer) for p in bars.patches] + \
                [t.get_window_extent(renderer) for t in bars.texts]
        assert marks and not any(legend.overlaps(mark) for mark in marks)
    finally:
        plt.close(fig)


def test_the_readme_says_the_learned_policys_scene_is_simulator_ground_truth():
    from pathlib import Path
    readme = (Path(__file__).parents[2] / "README.md").read_text()
    loop_paragraph = readme[readme.index("## From runs to a trained policy"):readme.index("## Layout")]
    assert "`scene` vector that is **simulator ground truth**" in loop_paragraph


def test_ctrl_c_in_collect_ends_with_one_line_and_exit_130(tmp_path, monkeypatch, capsys):
    """Ctrl-C during an episode (the KeyboardInterrupt a tick raises, as the signal would)."""
    from agents.flows import Controller
    from agents.learn.__main__ import main
    step = Controller.step

    def interrupted(self, action):
        if self.last is not None:
            raise KeyboardInterrupt
        return step(self, action)
    monkeypatch.setattr(Controller, "step", interrupted)
    assert main(["collect", "--seeds", "5:6", "-o", str(tmp_path / "logs")]) == 130
    err = capsys.readouterr().err
    assert "interrupted: collect stopped by Ctrl-C" in err and "Traceback" not in err
    assert not (tmp_path / "logs" / "episodes.json").exists()


@pytest.mark.parametrize("listing", ["{not json", '[{"success": true}]', '{"seed": 1}', '["pick-seed00001.mcap"]',
                                     '[{"success": true, "log": "../elsewhere.mcap"}]'])
def test_export_refuses_an_episode_list_it_cannot_read_in_one_line(tmp_path, capsys, listing):
    """A folder whose episodes.json is not what collect writes; its name has brackets, which the
    message keeps (the output is text, not markup)."""
    from agents.learn.__main__ import main
    folder = tmp_path / "logs[v2]"
    folder.mkdir()
    (folder / "episodes.json").write_text(listing)
    assert main(["export", str(folder), "-o", str(tmp_path / "ds")]) == 2
    err = capsys.readouterr().err
    assert f"error: {folder / 'episodes.json'} is not" in err.replace("\n", "") and "Traceback" not in err, err
    assert not (tmp_path / "ds").exists()


def test_a_missing_extra_is_named_with_the_extra_to_install(tmp_path):
    """train without torch (a package that cannot be imported stands in for it): one line and
    the extra, brackets and all, not a traceback."""
    fake = tmp_path / "site" / "torch"
    fake.mkdir(parents=True)
    (fake / "__init__.py").write_text("raise ModuleNotFoundError(\"No module named 'torch'\", name='torch')\n")
    from pathlib import Path
    root = Path(__file__).parents[2]
    env = {**__import__("os").environ, "PYTHONPATH": f"{tmp_path / 'site'}:{root}"}
    done = subprocess.run([sys.executable, "-m", "agents.learn", "train", "ds", "-o", "policy"], capture_output=True,
                          text=True, cwd=tmp_path, env=env, timeout=120)
    assert done.returncode == 2 and "Traceback" not in done.stderr, done.stderr
    assert "error: train needs torch, which cannot be imported here" in done.stderr, done.stderr
    assert "pip install 'retriever-robotics[lerobot]'" in done.stderr, done.stderr


def test_training_says_nothing_but_its_progress(recwarn):
    """No warning from the training loop (a loss read as a float while it required grad)."""
    from agents.learn.bc import train
    from agents.learn.dataset import Samples
    rng = np.random.default_rng(0)
    samples = Samples(state=rng.normal(size=(12, 18)), scene=rng.normal(size=(12, 10)),
                      action=rng.normal(size=(12, 150, 5)), episode=np.repeat(np.arange(6), 2))
    _, _, summary = train(samples, budget_s=30.0, max_epochs=2, hidden=8)
    assert summary.epochs == 2 and summary.held_out_episodes == 1
    assert [str(w.message) for w in recwarn] == []


def test_the_learning_docs_link_only_to_files_that_exist():
    import re
    from pathlib import Path
    doc = Path(__file__).parents[2] / "docs" / "learning.md"
    targets = re.findall(r"\]\(([^)#\s]+)(?:#[^)]*)?\)", doc.read_text())
    missing = [t for t in targets if "://" not in t and not (doc.parent / t).exists()]
    assert targets and missing == []


def test_the_results_say_what_they_were_measured_with(loop):
    import torch
    folder, _ = loop
    summary = json.loads((folder / "results" / "results.json").read_text())
    environment = summary["environment"]
    assert environment["torch"] == torch.__version__.split("+")[0] and environment["lerobot"]
    assert environment["python"] == ".".join(map(str, sys.version_info[:3])) and "commit" in environment
    assert summary["seconds"] > summary["training"]["seconds"]


def test_a_message_is_one_line_whatever_the_paths_length(tmp_path):
    """Not broken at the 80 columns rich assumes off a terminal (where it fell depended on the
    temporary folder's name)."""
    deep = tmp_path / ("a_rather_long_folder_name_" * 4)
    deep.mkdir()
    (deep / "afile").write_text("")
    done = learn("train", "ds", "-o", str(deep / "afile"), "--minutes", "1", cwd=tmp_path)
    assert done.returncode == 2, done.stderr
    assert f"error: -o {deep / 'afile'}: a file is there; the checkpoint is a directory (give a new path)\n" \
        == done.stderr, done.stderr


def _tiny_samples():
    from agents.learn.dataset import Samples
    rng = np.random.default_rng(0)
    return Samples(state=rng.normal(size=(12, 18)), scene=rng.normal(size=(12, 10)),
                   action=rng.normal(size=(12, 150, 5)), episode=np.repeat(np.arange(6), 2))


def _recording_learning_rates(monkeypatch) -> list[float]:
    """The learning rate of each optimiser step of the trainings that follow."""
    import torch
    rates = []

    class Recorded(torch.optim.AdamW):
        def step(self, *args, **kwargs):
            rates.append(self.param_groups[0]["lr"])
            return super().step(*args, **kwargs)
    monkeypatch.setattr(torch.optim, "AdamW", Recorded)
    return rates


def test_a_time_budget_that_ends_the_training_anneals_it_and_the_bar_counts_to_its_end(monkeypatch):
    """A clock on which each epoch takes 1 s and a 10 s budget: the budget ends the training
    after 10 of the 3000 epochs; the learning rate went down to near 0 on the way, and from its
    first epoch on the training expected 10 epochs, not 3000."""
    from agents.learn.bc import LEARNING_RATE, TIME_BUDGET, train
    rates = _recording_learning_rates(monkeypatch)
    ticks = iter(range(100))
    told = []
    _, _, summary = train(_tiny_samples(), budget_s=10.0, max_epochs=3000, hidden=8, clock=lambda: float(next(ticks)),
                          log=lambda epoch, loss, epochs: told.append((epoch, epochs)))
    assert summary.epochs == 10 and summary.ended_by == TIME_BUDGET
    assert told == [(k, 10) for k in range(1, 11)]
    assert rates[0] == LEARNING_RATE and rates[-1] < 0.03 * LEARNING_RATE
    assert rates == sorted(rates, reverse=True)


def test_without_a_time_budget_a_seed_trains_the_same_weights_along_a_schedule_over_the_epochs(monkeypatch):
    import torch

    from agents.learn.bc import LEARNING_RATE, MAX_EPOCHS, train
    rates = _recording_learning_rates(monkeypatch)
    first, _, summary = train(_tiny_samples(), budget_s=None, max_epochs=4, hidden=8)
    again, _, _ = train(_tiny_samples(), budget_s=float("inf"), max_epochs=4, hidden=8)
    assert summary.epochs == 4 and summary.ended_by == MAX_EPOCHS
    assert all(torch.equal(a, b) for a, b in zip(first.state_dict().values(), again.state_dict().values()))
    per_epoch = [LEARNING_RATE * 0.5 * (1 + np.cos(np.pi * k / 4)) for k in range(4)]
    assert rates == pytest.approx(per_epoch * 2, rel=1e-12)  # one batch an epoch, two trainings


def test_collects_progress_says_the_last_episodes_time_as_the_last(tmp_path, monkeypatch, capsys):
    from agents.learn import __main__ as command
    from agents.learn import episodes
    walls = iter([0.5, 2.25])
    monkeypatch.setattr(episodes, "pick_episode", lambda seed, policy, log: episodes.Outcome(
        seed, "TL", True, 5.0, next(walls), "done"))
    command.collect(2, "5:7", tmp_path / "logs")
    said = capsys.readouterr().err  # the command's console writes to stderr, whatever it is then
    assert "2/2 succeeded, the last in 2.25 s wall" in said and " each" not in said
