"""``GymWorld``: any ``gymnasium.Env`` as a world flow, stepped on its clock with the newest action.

    agent ──action──▶ world = GymWorld("CartPole-v1", seed=0) @ Rate(50)
      ▲                                                    │
      └──── observation, reward, terminated, truncated ────┘

Each tick either starts an episode (the first tick, and the tick after one ended: ``env.reset``,
seeded with ``seed`` the first time and continuing the env's own generator after that, so a run
repeats exactly) or steps it with the action its ``action`` port selects. The world does not wait
for the agent: what that port's edge selects decides what a tick applies. ``Latest()`` holds the
last action, as an actuator holds its last command, and applies it again on every tick until a
newer one arrives; ``LatestDistinct()`` steps the env only on a new action. Before the first
action of an episode a tick makes no event.
"""

from __future__ import annotations

import copy
from dataclasses import dataclass
from typing import Any, Callable

import numpy as np

from ..flow import Flow, io


@io
@dataclass
class EnvAction:
    """What the world consumes: the action to step its env with (None: none yet)."""

    action: Any = None


@io
@dataclass
class EnvStep:
    """What one tick of the world emits. A tick that starts an episode emits ``observation``,
    ``episode`` (its number, from 0) and ``terminated = truncated = False``; a tick that steps it,
    ``observation``, ``reward``, ``terminated`` and ``truncated``, as ``env.step`` returned them."""

    observation: Any = None
    reward: float | None = None
    terminated: bool | None = None
    truncated: bool | None = None
    episode: int | None = None


class GymWorld(Flow[EnvAction, EnvStep]):
    """A gymnasium environment as a flow: ``env`` is an id for ``gymnasium.make`` (with ``kwargs``),
    which an IR carries, so a deployment can rebuild it on any worker; or a function of no
    arguments returning an env, which runs in-process only. ``setup()`` makes the env,
    ``teardown()`` closes it, ``reset()`` starts over from the first episode and its ``seed``.

    Give it the clock of the env's own time step (``CartPole-v1`` steps 0.02 s: ``Rate(50)``):
    Retriever's virtual time then runs at the env's pace."""

    def __init__(self, env: str | Callable[[], Any], seed: int | None = 0, kwargs: dict | None = None):
        if not (isinstance(env, str) or callable(env)):
            raise TypeError(f"GymWorld(env={env!r}): expected a gymnasium id such as 'CartPole-v1' or a function "
                            "of no arguments that returns a gymnasium.Env")
        if isinstance(env, str) and ":" in env:
            # gymnasium.make("module:Id") imports the module: an IR, which names the id, must not
            # make a worker import what its allowlist does not name (docs/security.md)
            raise ValueError(f"GymWorld(env={env!r}): give the id alone; gymnasium would import the module before "
                             "the ':'\n    hint: register the env in the module that defines the pipeline (it is "
                             "imported already), or pass a function that makes the env")
        if seed is not None and (type(seed) is not int or seed < 0):
            raise ValueError(f"GymWorld(seed={seed!r}): expected an integer >= 0, or None for an unseeded env")
        if kwargs is not None and not isinstance(kwargs, dict):
            raise TypeError(f"GymWorld(kwargs={kwargs!r}): expected a dict of gymnasium.make keyword arguments")
        if isinstance(env, str):
            _refuse_paths(kwargs or {}, "kwargs")
        self.env_id = env
        self.seed = seed
        self.kwargs = dict(kwargs or {})
        self.episode = -1  # the episode going on (-1: none yet)
        self.running = False  # whether it goes on (False: the next tick starts one)

    def setup(self) -> None:
        if isinstance(self.env_id, str):
            import gymnasium

            self.env = gymnasium.make(self.env_id, **self.kwargs)
        else:
            self.env = self.env_id(**self.kwargs)

    def teardown(self) -> None:
        self.env.close()

    def step(self, inp: EnvAction) -> EnvStep | None:
        env = self.__dict__.get("env")
        if env is None:  # called directly, with no runtime to call setup() first
            self.setup()
            env = self.env
        if not self.running:
            self.episode += 1
            self.running = True
            observation, _ = env.reset(seed=self.seed if self.episode == 0 else None)
            return EnvStep(observation=_own(observation), terminated=False, truncated=False, episode=self.episode)
        if inp.action is None:
            return None
        observation, reward, terminated, truncated, _ = env.step(_as_action(inp.action, env.action_space))
        self.running = not (terminated or truncated)
        return EnvStep(observation=_own(observation), reward=float(reward), terminated=bool(terminated),
                       truncated=bool(truncated))


def _own(observation: Any) -> Any:
    """An observation the world may hand on: an env may fill one array again at its next step."""
    if isinstance(observation, np.ndarray):
        return observation.copy()
    if isinstance(observation, dict):
        return {key: _own(value) for key, value in observation.items()}
    if isinstance(observation, tuple):
        return tuple(_own(value) for value in observation)
    return observation


def _as_action(action: Any, space: Any) -> Any:
    """``action`` as ``space`` holds it, the env's own: an array of the space's dtype for a Box
    (an agent's float64 row for a float32 space), a Python int for a Discrete; else a copy of it.
    The action is the agent's event, whose arrays are read-only (an emitted value is immutable),
    and an env may change the action it is given (``np.clip(action, lo, hi, out=action)``)."""
    from gymnasium import spaces

    if isinstance(space, spaces.Box):
        return np.array(action, dtype=space.dtype)
    if isinstance(space, spaces.Discrete):
        return int(action)
    return copy.deepcopy(action)


def _looks_like_path(text: str) -> bool:
    """Whether an env would take ``text`` as a file of the machine it runs on: gymnasium's MuJoCo
    envs read ``xml_file`` as a path when it starts with ``/``, ``.`` or ``~`` (else as one of
    their own assets), and any other env may open what names a folder."""
    return text.startswith(("/", ".", "~")) or "/" in text or "\\" in text


def _refuse_paths(value: object, where: str) -> None:
    """Refuse a file path among the gymnasium.make keyword arguments of an env named by its id.

    Such a GymWorld travels in the IR, and a worker daemon rebuilds it from there: an IR's path
    would make the worker read a file an insider chose (and tell, by its error, whether it
    exists; issue 40). A function that makes the env runs in-process only, so it may name any file."""
    if isinstance(value, str):
        if _looks_like_path(value):
            raise ValueError(f"GymWorld: {where} = {value!r} is a file path, which a worker rebuilding this flow "
                             "from the IR would read on its own machine\n    hint: pass a function that makes the "
                             "env (GymWorld(lambda: gymnasium.make(ID, ...))), which runs in-process only, or "
                             "name one of the env's own assets")
    elif isinstance(value, dict):
        for key, item in value.items():
            _refuse_paths(item, f"{where}[{key!r}]")
    elif isinstance(value, (list, tuple)):
        for i, item in enumerate(value):
            _refuse_paths(item, f"{where}[{i}]")
