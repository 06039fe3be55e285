"""python -m agents.learn: collecting Pick episodes into logs, a dataset read from the policy
flow's step records, training a small policy, and evaluating one."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

from agents.learn.dataset import load_dataset, read_samples
from agents.learn.episodes import parse_seeds
from agents.retriever0 import POLICY_NODE
from retriever import read_log


def learn(*args, cwd, timeout=300):
    return subprocess.run([sys.executable, "-m", "agents.learn", *args], capture_output=True, text=True, cwd=cwd,
                          timeout=timeout)


@pytest.fixture(scope="module")
def collected(tmp_path_factory):
    folder = tmp_path_factory.mktemp("collected")
    done = learn("collect", "--skill", "pick", "--episodes", "2", "--seeds", "5:9", "-o", "data", cwd=folder)
    assert done.returncode == 0, done.stdout + done.stderr
    return folder, done


def test_collect_logs_one_episode_per_seed_and_says_how_long_each_took(collected):
    folder, done = collected
    assert sorted(p.name for p in (folder / "data").glob("*.mcap")) == ["pick-seed00005.mcap", "pick-seed00006.mcap"]
    assert "2 episodes in data: 2 succeeded;" in done.stdout and "s wall per episode" in done.stdout, done.stdout
    rows = json.loads((folder / "data" / "episodes.json").read_text())
    assert [(r["seed"], r["success"], r["detail"]) for r in rows] == [(5, True, "done"), (6, True, "done")]
    assert {r["drawer"] for r in rows} <= {"TL", "TR", "BL", "BR"} and all(r["wall"] > 0 for r in rows)


def test_the_policy_flows_step_records_hold_exactly_its_inputs_and_the_action(collected):
    folder, _ = collected
    log = read_log(folder / "data" / "pick-seed00005.mcap")
    steps = [s for s in log.iter_steps() if s.node == POLICY_NODE and s.status == "ok"]
    assert steps and all(set(s.consumed) <= {"skill", "state", "scene", "wrist"} for s in steps)
    assert all({"skill", "state", "scene"} <= set(s.consumed) for s in steps)
    assert all([i[1] for i in s.produced] == ["action"] for s in steps)
    chunks = [e for e in log.iter_events() if e.node == POLICY_NODE]
    states, scenes, actions = read_samples(folder / "data" / "pick-seed00005.mcap")
    assert len(actions) == len(steps) == len(chunks)
    assert all(np.array_equal(a, log.value(e).actions) for a, e in zip(actions, chunks))
    assert all(s.shape == (18,) and c.shape == (10,) and a.shape == (150, 5)
               for s, c, a in zip(states, scenes, actions))
    samples = load_dataset(sorted((folder / "data").glob("*.mcap")))
    assert len(samples.state) == len(steps) + len(read_samples(folder / "data" / "pick-seed00006.mcap")[0])
    assert set(samples.episode) == {0, 1}


def test_collect_keeps_existing_logs_unless_forced(collected):
    folder, _ = collected
    before = (folder / "data" / "pick-seed00005.mcap").read_bytes()
    done = learn("collect", "--episodes", "1", "--seeds", "5:6", "-o", "data", cwd=folder)
    assert done.returncode == 2 and "pick-seed00005.mcap already exists" in done.stderr and "--force" in done.stderr
    assert (folder / "data" / "pick-seed00005.mcap").read_bytes() == before


def test_train_then_evaluate_a_small_policy_on_a_held_out_seed(collected):
    pytest.importorskip("torch")
    folder, _ = collected
    done = learn("train", "data", "-o", "policy.pt", "--max-epochs", "3", "--json", "training.json", cwd=folder)
    assert done.returncode == 0, done.stdout + done.stderr
    training = json.loads((folder / "training.json").read_text())
    assert training["epochs"] == 3 and training["episodes"] == 2 and training["logs"] == 2
    done = learn("evaluate", "--seeds", "9:10", "--skill-policy", "policy.pt", "--skill-only", "--out", "eval.json",
                 cwd=folder)
    assert done.returncode == 0, done.stdout + done.stderr
    result = json.loads((folder / "eval.json").read_text())
    assert result["policy"] == "policy.pt" and result["seeds"] == "9:10" and "task" not in result
    (episode,) = result["skill"]["episodes"]
    assert episode["seed"] == 9 and result["skill"]["success_mean"] == float(episode["success"])
    assert f"skill: success {float(episode['success']):.2f} ± 0.00 over 1 seeds" in done.stdout, done.stdout


def test_evaluate_scripted_reports_the_skill_and_the_whole_task(tmp_path):
    done = learn("evaluate", "--seeds", "4:5", "--out", "eval.json", cwd=tmp_path)  # the spice in TL: found first
    assert done.returncode == 0, done.stdout + done.stderr
    result = json.loads((tmp_path / "eval.json").read_text())
    assert result["policy"] == "scripted"
    assert result["skill"]["success_mean"] == 1.0 and result["task"]["success_mean"] == 1.0, result
    assert "skill: success 1.00 ± 0.00 over 1 seeds (1/1)" in done.stdout
    assert "task: success 1.00 ± 0.00 over 1 seeds (1/1)" in done.stdout


@pytest.mark.parametrize("args, message", [
    (["evaluate", "--seeds", "3:1"], "--seeds '3:1': expected A:B with 0 <= A < B"),
    (["evaluate", "--seeds", "x"], "--seeds 'x': expected A:B"),
    (["evaluate", "--seeds", "0:1", "--skill-policy", "absent.pt"], "skill policy 'absent.pt': no such file"),
    (["collect", "--episodes", "5", "--seeds", "0:2", "-o", "d"], "--episodes 5: give 1 to 2"),
    (["train", "empty", "-o", "p.pt"], "empty: no logs (*.mcap) to train on"),
])
def test_bad_arguments_get_a_clear_error(tmp_path, args, message):
    (tmp_path / "empty").mkdir()
    done = learn(*args, cwd=tmp_path)
    assert done.returncode == 2 and message in done.stderr and "Traceback" not in done.stderr, done.stderr


def test_seeds_are_a_half_open_range():
    assert parse_seeds("3:6") == range(3, 6) and parse_seeds("4") == range(4, 5)
