"""Retriever-0 deployed across hosts of the netns lab as deploy/retriever0.toml places it: the
planner and the skill policy on a worker labelled gpu, the world, cameras and controller on one
labelled robot, the coordinator on a third host; real TCP between separate network stacks."""

from __future__ import annotations

import json
from pathlib import Path

import agents.messages  # noqa: F401 (the log's value types)
from agents.episode import summarize
from retriever import read_log
from retriever.replay import replay
from tests.deploy.test_deploy import deploy, secret, start_worker  # noqa: F401 (secret: a fixture)

REPO = Path(__file__).resolve().parents[2]
PAPER_TRACE = ["OpenDrawer(TL-H)", "InspectDrawer(TL)", "CloseDrawer(TL-H)", "OpenDrawer(TR-H)", "InspectDrawer(TR)",
               "Pick(spice)", "Season(food)", "CloseDrawer(TR-H)"]


def test_retriever0_runs_across_a_robot_host_and_a_gpu_host_and_its_log_replays(hosts, secret, tmp_path):  # noqa: F811
    coordinator, arm, gpu = hosts
    start_worker(arm, "arm-pc", secret, "--labels", "robot", "--allow", "agents")
    start_worker(gpu, "gpu-box", secret, "--labels", "gpu", "--allow", "agents")
    log = tmp_path / "run.mcap"
    done = deploy(coordinator, [arm, gpu], secret, f"{REPO / 'agents' / 'retriever0.py'}:pipe",
                  "--placement", str(REPO / "deploy" / "retriever0.toml"), "--duration", "150", "--log", str(log),
                  timeout=300)
    assert done.returncode == 0, done.stdout + done.stderr
    recorded = read_log(log)
    placed = json.loads(recorded.run["deployment"])["placed"]
    assert {placed[n] for n in ("planner", "skill")} == {"gpu-box"}, placed
    assert {placed[n] for n in ("world", "head_camera", "wrist_camera", "controller")} == {"arm-pc"}, placed
    episode = summarize(recorded.trace(), recorded.ir)
    # (the run ends when the episode does: about 45 s of world time here; a loaded machine's world falls behind)
    assert episode.skills == PAPER_TRACE and episode.finished and episode.score == 1.0, (
        f"{episode.skill_trace}: {episode.duration} s, {episode.failures} failures, {episode.replans} replans, "
        f"rates {[r for r in episode.rates if r.node in ('world', 'controller', 'skill')]}")
    assert replay(recorded).identical
