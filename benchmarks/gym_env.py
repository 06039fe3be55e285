"""Steps per second of a pipeline as a gymnasium env (retriever.gym.PipelineEnv), against the env it wraps.

The pipeline is CartPole-v1 as a world flow (GymWorld @ Rate(50, offset=0.01)) and the agent
@ Rate(50), the pairing under which the env is plain CartPole step for step
(tests/gym/test_env.py). Each ``env.step`` runs the agent's tick (the action), the world's tick
(gymnasium's own step), and reads the agent's next observation from its inputs. The baseline is
``gymnasium.make("CartPole-v1")`` stepped with the same actions, so the difference is what the
runtime adds per agent step: two ticks, their records, the observation read.

    PYTHONPATH=. .venv/bin/python benchmarks/gym_env.py                 # ~30 s
    PYTHONPATH=. .venv/bin/python benchmarks/gym_env.py --steps 20000 --repeats 5

Measured, never asserted; it prints the medians and the load average.
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # run from a checkout without installing

import gymnasium  # noqa: E402

from retriever.gym import PipelineEnv  # noqa: E402
from tests.gym.gym_flows import cartpole  # noqa: E402


def steps_per_second(env, steps: int, seed: int = 0) -> float:
    """Steps per second over ``steps`` steps of alternating pushes, resetting when an episode ends."""
    env.reset(seed=seed)
    start = time.perf_counter()
    for i in range(steps):
        _, _, terminated, truncated, _ = env.step(i % 2)
        if terminated or truncated:
            env.reset()
    return steps / (time.perf_counter() - start)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--steps", type=int, default=10_000)
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()
    space = gymnasium.make("CartPole-v1").observation_space
    envs = {"gymnasium CartPole-v1": lambda: gymnasium.make("CartPole-v1")}
    for keep in ("trace", "counters"):
        envs[f"PipelineEnv keep={keep}"] = lambda keep=keep: PipelineEnv(
            cartpole, "pilot", reward="reward", terminated="terminated", truncated="truncated",
            observation_space=space, action_space=gymnasium.spaces.Discrete(2), keep=keep)
    print(f"{args.steps} steps x {args.repeats} repeats; load average {os.getloadavg()[0]:.2f}")
    results = {}
    for name, make in envs.items():
        runs = [steps_per_second(make(), args.steps) for _ in range(args.repeats)]
        results[name] = statistics.median(runs)
        print(f"  {name:28s} {results[name]:10.0f} steps/s (runs: {', '.join(f'{r:.0f}' for r in runs)})")
    base = results["gymnasium CartPole-v1"]
    for name, rate in results.items():
        if name.startswith("PipelineEnv"):
            print(f"  {name}: {1e6 / rate - 1e6 / base:.1f} µs per step over gymnasium's own")
    print(f"load average after: {os.getloadavg()[0]:.2f}")


if __name__ == "__main__":
    main()
