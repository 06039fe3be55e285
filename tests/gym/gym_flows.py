"""Flows the gym tests wire around an agent: CartPole through GymWorld, and a world whose state is
a plain sum, so that what an action did, and when, can be computed independently of the runtime."""

from __future__ import annotations

import sys
from dataclasses import dataclass

import numpy as np

from retriever import Flow, Pipeline, Queue, Rate, io
from retriever.gym import GymWorld

#: CartPole-v1 steps its physics 0.02 s at a time: its world ticks at 50 Hz
CARTPOLE_HZ = 50


@io
@dataclass
class CartView:
    observation: np.ndarray
    reward: float = 0.0
    terminated: bool = False
    truncated: bool = False


@io
@dataclass
class Push:
    action: int


class Balance(Flow[CartView, Push]):
    """Push the cart toward the side the pole leans to (a scripted pilot)."""

    def step(self, inp: CartView) -> Push:
        return Push(int(inp.observation[2] > 0))


def cartpole(seed: int, latency: float = 0.0, world_offset: float = 0.01) -> Pipeline:
    """CartPole as the world, ``pilot`` the agent, both at 50 Hz; the world ticks ``world_offset``
    after the pilot, so with no latency each action is applied at the world's next tick, the
    step of a plain CartPole."""
    with Pipeline("cartpole") as pipe:
        world = GymWorld("CartPole-v1", seed=seed).named("world") @ Rate(CARTPOLE_HZ, offset=world_offset)
        pilot = Balance().named("pilot").configure(latency=latency) @ Rate(CARTPOLE_HZ)
        world.then(pilot)
        pilot.then(world)
    return pipe


# -- a world that sums its commands, one per millisecond -----------------------------------------
@io
@dataclass
class Command:
    u: float = 0.0


@io
@dataclass
class Sum:
    x: float
    gain: float


@io
@dataclass
class SumView:
    x: float = 0.0
    gain: list = None


class Summer(Flow[Command, Sum]):
    """x grows by the newest command at each tick; ``gain`` is that growth (a reward)."""

    def __init__(self, stop_at: float | None = None):
        self.x = 0.0
        self.stop_at = stop_at

    def step(self, inp: Command) -> Sum:
        if self.stop_at is not None and self.x >= self.stop_at:
            sys.exit(0)
        self.x += inp.u
        return Sum(self.x, inp.u)


class Driver(Flow[SumView, Command]):
    """The agent's slot: its actions come from the env's caller."""

    def step(self, inp: SumView) -> Command:
        raise AssertionError("the env supplies this flow's actions")


WORLD_HZ, AGENT_HZ = 1000, 10


def summing(latency: float, stop_at: float | None = None, reward_sync=None) -> Pipeline:
    with Pipeline("summing") as pipe:
        world = Summer(stop_at).named("world") @ Rate(WORLD_HZ)
        driver = Driver().named("driver").configure(latency=latency) @ Rate(AGENT_HZ)
        world.then(driver, map={"x": "x"})
        world.then(driver, map={"gain": "gain"}, sync=reward_sync or Queue())
        driver.then(world)
    return pipe
