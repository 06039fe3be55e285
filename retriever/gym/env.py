"""``PipelineEnv``: a pipeline as a ``gymnasium.Env``, in virtual time, one of its flows the agent.

The agent is a flow on a ``Rate`` clock whose outputs the env's caller supplies: ``step(action)``
is that flow's step at its tick. Between two of its ticks every other flow runs on its own clock,
so the world does not wait for the agent (the paper's asynchronous MDP, Sec. III), and the
agent's declared ``latency`` delays its action as on the robot:

    reset()          ──▶ run every tick before t0; observation = what the agent's inputs select at t0
    step(a0)         ──▶ the agent's tick at t0 emits a0 (tagged t0 + latency, or the next
                         microstep); run every tick before t1; observation at t1; reward, end
    step(a1)  …

An agent tick whose required input has nothing is skipped by the runtime, as in any run: no
action is asked for it, and the env goes on to the next tick. The observation is read from the
agent's input buffers with its own sync policies (``InprocSession.inputs_at``) and is exactly
what its tick then consumes (its step record names the same events).
"""

from __future__ import annotations

import copy
from typing import Any, Callable

import gymnasium
import numpy as np
from gymnasium import spaces

from ..backends.inproc import InprocSession
from ..clocks import Rate
from ..errors import InternalError
from ..graph import Graph, Node
from ..pipeline import Pipeline
from ..trace import KEEP, Trace

#: the most agent ticks in a row ``reset``/``step`` runs through while a required input of the agent
#: has nothing (those ticks are skipped): past it, the wiring is taken to be wrong and said so
MAX_SKIPPED_TICKS = 100_000


class PipelineEnv(gymnasium.Env):
    """A pipeline as a gymnasium environment; its node ``agent`` takes the actions.

    ``pipeline`` is a :class:`~retriever.Pipeline`, run afresh (``pipe.reset()``) by every
    ``reset()``, or a function ``seed -> Pipeline`` building the episode of a seed (such as
    ``lambda seed: agents.retriever0.build(seed=seed)``): ``reset(seed=s)`` runs the pipeline it
    builds for ``s``, and ``reset()`` one for a seed drawn from the env's ``np_random``. Either way
    a seeded episode repeats exactly.

    ``reward``, ``terminated`` and ``truncated`` name input ports of the agent; the other inputs
    are the observation. Each is what the agent's tick selects on that port, by its edge's sync
    policy: ``Latest()`` the newest value, ``Queue()`` every value since the agent's last step (a
    list: rewards are summed, terminations ``any``). Give those ports a default (``reward: float =
    0.0``) so that the agent's ticks do not wait for them.

    The observation is the value of the agent's one observation port, or a dict by port name when
    it has several; the action likewise, for its output ports. Their spaces are derived for ports
    typed ``float`` (an unbounded ``Box`` of shape ``()``); give the others, as one space
    (``observation_space=Box(...)``: the whole observation) or a dict of spaces by port name.

    ``keep`` is the episode's trace kept in ``env.trace`` (see ``Trace``): ``"trace"`` (every
    value), ``"records"`` or ``"counters"`` (nothing, for long training runs).
    """

    metadata = {"render_modes": []}

    def __init__(self, pipeline: Pipeline | Callable[[int], Pipeline], agent: str, *,
                 reward: str | None = None, terminated: str | None = None, truncated: str | None = None,
                 observation_space: spaces.Space | dict[str, spaces.Space] | None = None,
                 action_space: spaces.Space | dict[str, spaces.Space] | None = None, keep: str = "trace"):
        if not (isinstance(pipeline, Pipeline) or callable(pipeline)):
            raise TypeError(f"PipelineEnv(pipeline={pipeline!r}): expected a Pipeline or a function seed -> Pipeline")
        if keep not in KEEP:
            raise ValueError(f"PipelineEnv(keep={keep!r}): expected one of {', '.join(map(repr, KEEP))}")
        self._source = pipeline
        self.agent = agent
        self.keep = keep
        signals = {"reward": reward, "terminated": terminated, "truncated": truncated}
        self._signals = {role: port for role, port in signals.items() if port is not None}
        graph = self._build(0).compile()
        node = self._agent_node(graph)
        self._clock: Rate = node.clock
        self._observed = [port for port in node.inputs if port not in self._signals.values()]
        self._acting = list(node.outputs)
        self._ports = (node.inputs, node.outputs)
        self.observation_space = _space_of("observation", agent, {p: node.inputs[p] for p in self._observed},
                                           observation_space)
        self.action_space = _space_of("action", agent, {p: node.outputs[p] for p in self._acting}, action_space)
        self._session: InprocSession | None = None
        self._pending: list[tuple[str, Any]] | None = None  # the action the agent's next tick emits
        self._k = 0  # the agent's tick the env is at
        self._over = True  # whether the episode ended (or none began): step() needs a reset()
        self._last: Any = None  # the episode's last observation
        self._trace = Trace()

    # -- building an episode ------------------------------------------------------------------
    def _build(self, seed: int) -> Pipeline:
        if isinstance(self._source, Pipeline):
            self._source.reset()
            return self._source
        pipe = self._source(seed)
        if not isinstance(pipe, Pipeline):
            raise TypeError(f"PipelineEnv: the function given as pipeline returned {type(pipe).__qualname__} for "
                            f"seed {seed}, expected a Pipeline")
        return pipe

    def _agent_node(self, graph: Graph) -> Node:
        node = graph.nodes.get(self.agent)
        if node is None:
            raise ValueError(f"PipelineEnv(agent={self.agent!r}): pipeline '{graph.name}' has no node "
                             f"{self.agent!r} (its nodes: {', '.join(sorted(graph.nodes))})")
        if type(node.clock) is not Rate:
            raise ValueError(f"PipelineEnv: the agent {self.agent} runs on {node.clock!r}; an env steps it at the "
                             "ticks of a Rate clock\n    hint: bind it with @ Rate(hz=...): the env's steps are its "
                             "ticks")
        for role, port in self._signals.items():
            if port not in node.inputs:
                raise ValueError(f"PipelineEnv({role}={port!r}): the agent {self.agent} has no input port {port!r} "
                                 f"(its inputs: {', '.join(node.inputs) or 'none'})")
        if not node.outputs:
            raise ValueError(f"PipelineEnv: the agent {self.agent} has no output port for the action")
        return node

    def _open(self, seed: int) -> None:
        graph = self._build(seed).compile()
        node = self._agent_node(graph)
        if (node.inputs, node.outputs) != self._ports or node.clock != self._clock:
            raise ValueError(f"PipelineEnv: the pipeline built for seed {seed} has an agent {self.agent} with other "
                             "ports or another clock than the first one built: the spaces would not fit it")
        self._session = session = InprocSession(graph, keep=self.keep)
        self._trace = session.trace
        session.replace_step(self.agent, _Actions(self))
        session.set_up(skip=frozenset({self.agent}))  # its step() is the env's caller

    # -- gymnasium ----------------------------------------------------------------------------
    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None):
        """Start an episode: a fresh run of the pipeline (built for ``seed``), up to the agent's
        first tick that has its inputs. Returns ``(observation, info)``."""
        super().reset(seed=seed)
        self.close()
        if seed is None:
            seed = int(self.np_random.integers(2**31))
        self._open(seed)
        self._k, self._pending, self._over, self._last = 0, None, False, None
        observation, _, info = self._observe()
        return observation, info

    def step(self, action: Any):
        """The agent's tick emits ``action``; the pipeline runs to the agent's next tick that has
        its inputs. Returns ``(observation, reward, terminated, truncated, info)``; ``info`` holds
        that tick's ``time`` (seconds) and index (``tick``), how many agent ticks before it were
        ``skipped`` for want of an input, and whether a step ``ended`` the run (``sys.exit(0)``:
        then ``terminated``, and the observation before holds)."""
        if self._over or self._session is None:
            raise RuntimeError("PipelineEnv.step(): the episode is over (or none began)\n    hint: call env.reset()")
        if not _contains(self.action_space, action):
            raise ValueError(f"PipelineEnv.step(): the action {action!r:.200} is not in the action space "
                             f"{self.action_space} (the episode goes on as before it)\n    hint: pass an action "
                             "that env.action_space.contains()")
        outputs = self._outputs(action)
        self._pending = outputs
        self._k += 1
        observation, values, info = self._observe()
        if self._pending is not None:
            raise InternalError(f"PipelineEnv: the agent {self.agent} did not take the action at its tick")
        reward = _reward(self.agent, self._signals.get("reward"), values)
        terminated = _flag(self.agent, self._signals.get("terminated"), values) or info["ended"]
        truncated = _flag(self.agent, self._signals.get("truncated"), values)
        self._over = terminated or truncated
        return observation, reward, terminated, truncated, info

    def close(self) -> None:
        """Tear the episode's flows down (each flow's ``teardown()``)."""
        if self._session is not None:
            self._session.close()
            self._session = None

    # -- the agent's ticks --------------------------------------------------------------------
    def _observe(self) -> tuple[Any, dict[str, Any], dict[str, Any]]:
        """Run every tick before the agent's tick ``self._k``, and on past ticks that will be
        skipped, up to one that has its inputs; return the observation there, the values of the
        agent's inputs, and the info. A run that a step ended (``sys.exit(0)``) ends the
        episode: the observation before it holds."""
        session = self._session
        assert session is not None
        skipped = 0
        while True:
            t = self._clock.tick_time(self._k)
            if not _ended(session):
                session.advance(t)
            if _ended(session):
                if self._last is None:
                    raise RuntimeError(f"PipelineEnv.reset(): the run ended ({session.ended}) before the agent "
                                       f"{self.agent} had its inputs")
                self._pending = None
                info = {"time": session.now_ns / 1e9, "tick": self._k, "skipped": skipped, "ended": True}
                return copy.deepcopy(self._last), {}, info
            values, _, missing = session.inputs_at(self.agent, (t, 0))
            if missing is None:
                break
            skipped += 1
            if skipped > MAX_SKIPPED_TICKS:
                raise RuntimeError(f"PipelineEnv: the agent {self.agent} had nothing on its required input(s) "
                                   f"{', '.join(missing)} at {MAX_SKIPPED_TICKS} ticks in a row, up to {t / 1e9:g} s"
                                   "\n    hint: wire those ports, or give them a default in the agent's input type")
            self._k += 1
        observation = self._observation(values)
        self._last = copy.deepcopy(observation)
        return observation, values, {"time": t / 1e9, "tick": self._k, "skipped": skipped, "ended": False}

    def _observation(self, values: dict[str, Any]) -> Any:
        space = self.observation_space
        if len(self._observed) == 1:
            (port,) = self._observed
            return _fit(self.agent, port, values.get(port), space)
        return {port: _fit(self.agent, port, values.get(port), space[port]) for port in self._observed}

    def _outputs(self, action: Any) -> list[tuple[str, Any]]:
        """``action`` (in the action space: a dict by port for several) as the agent's outputs:
        ``(port, value)`` per port, each value of its port's type."""
        ports = self._ports[1]
        if len(self._acting) == 1:
            (port,) = self._acting
            return [(port, _as_port_value(action, ports[port]))]
        return [(port, _as_port_value(action[port], ports[port])) for port in self._acting]

    @property
    def trace(self) -> Trace:
        """The episode's trace so far (its step records name what every tick consumed)."""
        return self._trace

    @property
    def now(self) -> float:
        """Virtual time, in seconds since the episode's start."""
        return 0.0 if self._session is None else self._session.now_ns / 1e9


def _ended(session: InprocSession) -> bool:
    """Whether a step ended the run (``sys.exit(0)``: the session says at which tick)."""
    return getattr(session, "ended", None) is not None


class _Actions:
    """What the agent's ticks emit (``InprocSession.replace_step``): the action the env was given."""

    def __init__(self, env: PipelineEnv):
        self.env = env

    def __iter__(self) -> "_Actions":
        return self

    def __next__(self) -> list[tuple[str, Any]]:
        env = self.env
        outputs, env._pending = env._pending, None
        if outputs is None:
            raise InternalError(f"PipelineEnv: the agent {env.agent} ticked with no action given")
        return outputs


def _contains(space: spaces.Space, action: Any) -> bool:
    """``space.contains(action)``, a Box's value given as a number or list cast to its dtype first
    (as gymnasium's own check does, without its warning for each step)."""
    if isinstance(space, spaces.Dict):
        return (isinstance(action, dict) and action.keys() == space.spaces.keys()
                and all(_contains(space[key], action[key]) for key in space.spaces))
    if isinstance(space, spaces.Box) and not isinstance(action, np.ndarray):
        try:
            action = np.asarray(action, dtype=space.dtype)
        except (TypeError, ValueError, OverflowError):
            return False
    return space.contains(action)


def _space_of(what: str, agent: str, ports: dict, given: Any) -> spaces.Space:
    """The observation or action space: ``given`` whole, or per port (given, or derived from a
    ``float`` port); one port's space alone, several ports' as a Dict."""
    if isinstance(given, spaces.Space):
        if len(ports) > 1 and not (isinstance(given, spaces.Dict) and set(given.spaces) == set(ports)):
            raise ValueError(f"PipelineEnv({what}_space=...): the agent {agent} has the {what} ports "
                             f"{', '.join(ports)}: give a Dict space with those keys, or a dict of spaces by port")
        return given
    given = dict(given or {})
    unknown = sorted(set(given) - set(ports))
    if unknown:
        raise ValueError(f"PipelineEnv({what}_space=...): the agent {agent} has no {what} port "
                         f"{', '.join(unknown)} (its {what} ports: {', '.join(ports) or 'none'})")
    problems, per_port = [], {}
    for port, spec in ports.items():
        space = given.get(port)
        if space is None and spec.type is float:
            space = spaces.Box(-np.inf, np.inf, shape=(), dtype=np.float64)
        if space is None:
            problems.append(f"{agent}.{port} ({spec.type_name})")
        elif not isinstance(space, spaces.Space):
            raise TypeError(f"PipelineEnv({what}_space=...): the space of {agent}.{port} must be a gymnasium "
                            f"space, got {space!r}")
        per_port[port] = space
    if problems:
        raise ValueError(f"PipelineEnv: no {what} space for {', '.join(problems)}: only a float port's is "
                         f"derived\n    hint: give it, e.g. {what}_space={{'{problems[0].split('.')[1].split()[0]}': "
                         "gymnasium.spaces.Box(low, high, shape, dtype)}")
    if len(per_port) == 1:
        return next(iter(per_port.values()))
    return spaces.Dict(per_port)


def _fit(agent: str, port: str, value: Any, space: spaces.Space) -> Any:
    """The value an agent's input port holds, as an element of ``space``, and a copy of its own
    (a caller may keep it, and the flow that sent it may change it later)."""
    if value is None and isinstance(space, (spaces.Box, spaces.MultiBinary, spaces.MultiDiscrete, spaces.Discrete)):
        raise ValueError(f"PipelineEnv: {agent}.{port} holds None at the agent's tick (nothing on it, and None is "
                         f"its default), which is not in the observation space {space}\n    hint: give the port "
                         "a default in the space, or make it a required input (the env then waits for it)")
    if isinstance(space, (spaces.Box, spaces.MultiBinary, spaces.MultiDiscrete)):
        try:
            array = np.array(value, dtype=space.dtype)
        except (TypeError, ValueError) as exc:
            raise ValueError(f"PipelineEnv: {agent}.{port} holds {value!r:.200}, not an array of the observation "
                             f"space {space}: {exc}") from None
        if array.shape != space.shape:
            raise ValueError(f"PipelineEnv: {agent}.{port} holds an array of shape {array.shape}; the observation "
                             f"space {space} has shape {space.shape}")
        return array
    if isinstance(space, spaces.Discrete):
        return np.int64(value)
    return copy.deepcopy(value)


def _as_port_value(action: Any, spec: Any) -> Any:
    """An action as its port's declared type takes it: a Python scalar for a ``float``, ``int`` or
    ``bool`` port (gymnasium hands out NumPy scalars and 0-d arrays), else a copy of the array."""
    if spec.type in (float, int, bool):
        return spec.type(np.asarray(action).item())
    if isinstance(action, np.ndarray):
        return action.copy()
    return copy.deepcopy(action)


def _reward(agent: str, port: str | None, values: dict[str, Any]) -> float:
    if port is None:
        return 0.0
    value = values.get(port)
    items = value if isinstance(value, list) else [] if value is None else [value]
    try:
        return float(sum(float(item) for item in items))
    except (TypeError, ValueError):
        raise ValueError(f"PipelineEnv: the reward port {agent}.{port} holds {value!r:.200}, not a number (or a "
                         "list of numbers)") from None


def _flag(agent: str, port: str | None, values: dict[str, Any]) -> bool:
    if port is None:
        return False
    value = values.get(port)
    items = value if isinstance(value, list) else [] if value is None else [value]
    return any(bool(item) for item in items)
