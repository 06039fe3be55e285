"""retriever.gym.PipelineEnv: a pipeline as a gymnasium.Env, the agent one of its flows, in virtual time."""

from __future__ import annotations

import warnings
from dataclasses import dataclass

import numpy as np
import pytest

gymnasium = pytest.importorskip("gymnasium")

from gymnasium.utils.env_checker import check_env  # noqa: E402

from retriever import Flow, Pipeline, Rate, Trigger, io  # noqa: E402
from retriever.gym import GymWorld, PipelineEnv  # noqa: E402
from retriever.gym import env as env_module  # noqa: E402
from tests.gym.gym_flows import AGENT_HZ, WORLD_HZ, CartView, Push, cartpole, summing  # noqa: E402

CARTPOLE = gymnasium.make("CartPole-v1")


def cartpole_env(latency: float = 0.0, **options) -> PipelineEnv:
    return PipelineEnv(lambda seed: cartpole(seed, latency), "pilot", reward="reward", terminated="terminated",
                       truncated="truncated", observation_space=CARTPOLE.observation_space,
                       action_space=gymnasium.spaces.Discrete(2), **options)


def episode(env: PipelineEnv, seed: int | None, actions) -> list[np.ndarray]:
    """The observations of an episode of ``actions``, up to its end."""
    observation, _ = env.reset(seed=seed)
    seen = [observation]
    for action in actions:
        observation, _, terminated, truncated, _ = env.step(action)
        seen.append(observation)
        if terminated or truncated:
            break
    return seen


def test_gymnasiums_own_checker_passes():
    env = cartpole_env()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        check_env(env)
    # what it may say: CartPole's own space is unbounded in two coordinates; an env made without
    # gymnasium.make has no spec to try render modes from
    allowed = ("space minimum value is -infinity", "space maximum value is infinity", "not having a spec")
    assert [str(w.message) for w in caught if not any(a in str(w.message) for a in allowed)] == []


def test_a_seeded_episode_repeats_exactly_and_another_seed_differs():
    env = cartpole_env()
    actions = [1, 0, 0, 1, 1, 1, 0, 1, 0, 0] * 3
    first = episode(env, 7, actions)
    first_trace = env.trace.digest()
    again = episode(env, 7, actions)
    assert [o.tobytes() for o in again] == [o.tobytes() for o in first]
    assert env.trace.digest() == first_trace  # every event and step of the run, not only what the agent saw
    other = episode(env, 8, actions)
    assert other[0].tobytes() != first[0].tobytes()


def test_an_unseeded_reset_draws_its_episode_from_the_seeded_generator():
    env = cartpole_env()
    env.reset(seed=3)
    after_3 = env.reset()[0]
    env.reset(seed=3)
    assert env.reset()[0].tobytes() == after_3.tobytes()
    assert env.reset()[0].tobytes() != after_3.tobytes()


def test_with_no_latency_and_the_world_ticking_between_the_agents_ticks_it_is_plain_cartpole():
    env, direct = cartpole_env(), gymnasium.make("CartPole-v1")
    observation, info = env.reset(seed=11)
    expected, _ = direct.reset(seed=11)
    # the agent's tick at 0 s has no observation yet (the world's first is at 0.01 s): skipped
    assert info == {"time": 0.02, "tick": 1, "skipped": 1, "ended": False}
    assert observation.tobytes() == expected.tobytes()
    for action in [0, 1, 1, 0, 1, 0, 0, 0, 1, 1]:
        observation, reward, terminated, truncated, _ = env.step(action)
        expected, expected_reward, expected_terminated, expected_truncated, _ = direct.step(action)
        assert observation.tobytes() == expected.tobytes()
        assert (reward, terminated, truncated) == (expected_reward, expected_terminated, expected_truncated)


def test_a_latency_longer_than_the_worlds_offset_delays_every_action_by_one_world_step():
    """With latency 0.015 s the action of the agent's tick at t reaches the world after its tick at
    t + 0.01 s: the world applies it at t + 0.03 s, and the agent sees its effect at t + 0.04 s,
    two of its ticks later; meanwhile it decides on the observation before (the asynchronous MDP)."""
    env, direct = cartpole_env(latency=0.015), gymnasium.make("CartPole-v1")
    actions = [0, 1, 1, 0, 1, 0, 0, 0, 1, 1]
    seen = episode(env, 11, actions)
    expected = [direct.reset(seed=11)[0]]
    expected += [direct.step(action)[0] for action in actions[:-1]]
    assert [o.tobytes() for o in seen] == [o.tobytes() for o in [expected[0], *expected]]


def test_the_observation_is_what_the_agents_tick_consumes():
    env = cartpole_env(latency=0.015)
    seen = episode(env, 5, [1, 0] * 10)
    trace = env.trace
    values = {event.id: event.value for event in trace.events}
    ran = [record for record in trace.steps_of("pilot") if record.status == "ok"]
    assert [values[record.consumed["observation"][0]].tobytes() for record in ran] == [o.tobytes() for o in seen[:-1]]
    assert [values[record.produced[0]] for record in ran] == [1, 0] * 10


def _start(k: int, latency_ms: int) -> int:
    """The first world tick (ms) that applies the action of the agent's tick k, by the rules
    (docs/semantics.md): the action's tag is (t + latency, 0), or (t, 1) with no latency, and a
    world tick at (j, 0) applies the newest action tagged at or before it."""
    t = k * WORLD_HZ // AGENT_HZ
    return t + latency_ms if latency_ms else t + 1


@pytest.mark.parametrize("latency_ms", [0, 50, 150])
def test_an_action_at_tick_t_takes_effect_at_t_plus_the_agents_latency(latency_ms):
    env = PipelineEnv(summing(latency_ms / 1000), "driver", reward="gain")
    actions = [1.0, 10.0, 100.0, 1000.0, 0.0, 2.0, 20.0]
    observation, _ = env.reset(seed=0)
    seen, rewards = [float(observation)], []
    for action in actions:
        observation, reward, *_ = env.step(action)
        seen.append(float(observation))
        rewards.append(reward)

    # the consumer (the world) first consumes the action of tick k at t_k + latency
    end_ms = len(actions) * WORLD_HZ // AGENT_HZ  # the episode ran the world's ticks before it
    consumers = {}
    for record in env.trace.steps_of("world"):
        for event in record.consumed.get("u", ()):
            consumers.setdefault(event, record.tag)
    expected = {("driver", "u", k): (_start(k, latency_ms) * 1_000_000, 0) for k in range(len(actions))
                if _start(k, latency_ms) < end_ms}
    assert consumers == expected

    # the observation at the agent's tick k: the sum of the commands of the world's ticks before it
    period = WORLD_HZ // AGENT_HZ
    starts = [_start(k, latency_ms) for k in range(len(actions))]
    command = [next((actions[k] for k in reversed(range(len(actions))) if starts[k] <= j), 0.0)
               for j in range(period * len(actions))]
    assert seen == [sum(command[:period * k]) for k in range(len(actions) + 1)]
    # the reward (a Queue of the world's gains since the agent's last tick) is the growth between them
    assert rewards == [b - a for a, b in zip(seen, seen[1:])]


def test_latency_changes_what_the_agent_sees():
    runs = {}
    for latency in (0.0, 0.05):
        env = PipelineEnv(summing(latency), "driver", reward="gain")
        env.reset(seed=0)
        runs[latency] = [float(env.step(1.0)[0]) for _ in range(3)]
    assert runs[0.0] == [99.0, 199.0, 299.0]  # from 1 ms after each tick
    assert runs[0.05] == [50.0, 150.0, 250.0]  # from 50 ms after


def test_a_run_a_step_ends_ends_the_episode():
    env = PipelineEnv(summing(0.0, stop_at=150.0), "driver", reward="gain")
    env.reset(seed=0)
    assert env.step(1.0)[2:4] == (False, False)
    observation, reward, terminated, truncated, info = env.step(1.0)
    # the world ended the run at its tick at 151 ms, before the agent's at 200 ms: what it saw at 100 ms holds
    assert (float(observation), terminated, truncated) == (99.0, True, False)
    assert (info["ended"], info["time"]) == (True, 0.151)
    with pytest.raises(RuntimeError, match=r"the episode is over .*\n    hint: call env.reset\(\)"):
        env.step(1.0)


def test_the_env_needs_a_rate_agent_that_exists_and_spaces_for_its_ports():
    with pytest.raises(ValueError, match=r"pipeline 'summing' has no node 'pilot' \(its nodes: driver, world\)"):
        PipelineEnv(summing(0.0), "pilot")
    with pytest.raises(ValueError, match=r"the agent driver has no input port 'score' \(its inputs: x, gain\)"):
        PipelineEnv(summing(0.0), "driver", reward="score")
    with pytest.raises(ValueError, match=r"PipelineEnv\(keep='all'\): expected one of 'trace', "):
        PipelineEnv(summing(0.0), "driver", keep="all")
    with pytest.raises(ValueError, match=r"no observation space for pilot.observation \(numpy.ndarray\).*\n"
                                         r"    hint: give it, e.g. observation_space=\{'observation': "):
        PipelineEnv(lambda seed: cartpole(seed), "pilot", reward="reward", terminated="terminated",
                    truncated="truncated", action_space=gymnasium.spaces.Discrete(2))

    class Watch(Flow[CartView, Push]):
        def step(self, inp):
            return Push(0)

    with Pipeline("triggered") as pipe:
        world = GymWorld("CartPole-v1").named("world") @ Rate(50)
        watch = Watch().named("watch") @ Trigger("observation")
        world.then(watch).then(world)
    with pytest.raises(ValueError, match=r"the agent watch runs on Trigger\('observation'\).*\n    hint: bind it "
                                         r"with @ Rate"):
        PipelineEnv(pipe, "watch")


def test_a_pipeline_given_as_is_runs_afresh_at_each_reset():
    pipe = summing(0.0)
    env = PipelineEnv(pipe, "driver", reward="gain")
    runs = []
    for _ in range(2):
        env.reset(seed=1)
        runs.append([float(env.step(3.0)[0]) for _ in range(2)])
        runs.append(env.trace.digest())
    assert runs[0] == runs[2] == [297.0, 597.0]
    assert runs[1] == runs[3]


@io
@dataclass
class Nothing:
    x: float


class Silent(Flow[None, Nothing]):
    def step(self) -> None:
        return None  # no event, ever


@io
@dataclass
class Needs:
    x: float


class Waiting(Flow[Needs, Push]):
    def step(self, inp: Needs) -> Push:
        return Push(0)


def test_an_agent_whose_required_input_never_comes_is_reported_not_waited_for_forever(monkeypatch):
    monkeypatch.setattr(env_module, "MAX_SKIPPED_TICKS", 5)
    with Pipeline("silent") as pipe:
        source = Silent().named("source") @ Rate(10)
        source.then(Waiting().named("waiting") @ Rate(10))
    env = PipelineEnv(pipe, "waiting", action_space=gymnasium.spaces.Discrete(2))
    with pytest.raises(RuntimeError, match=r"the agent waiting had nothing on its required input\(s\) x at 5 ticks "
                                           r"in a row, up to 0.5 s\n    hint: wire those ports, or give them a "
                                           r"default"):
        env.reset(seed=0)


def test_an_action_outside_the_action_space_is_refused_before_the_step_and_the_episode_goes_on():
    env = cartpole_env()
    env.reset(seed=3)
    before = (env.now, env.trace.digest())
    for bad in (5, -1, 0.5, "left"):
        with pytest.raises(ValueError, match=rf"PipelineEnv\.step\(\): the action {bad!r} is not in the action space "
                                             r"Discrete\(2\) \(the episode goes on as before it\)"):
            env.step(bad)
        assert (env.now, env.trace.digest()) == before
    went_on = [env.step(action)[0] for action in (1, 0, np.int64(1))]
    assert [o.tobytes() for o in went_on] == [o.tobytes() for o in episode(cartpole_env(), 3, [1, 0, 1])[1:]]


@io
@dataclass
class Thrust:
    force: np.ndarray


@io
@dataclass
class Speed:
    v: float = 0.0


class Pilot(Flow[Speed, Thrust]):
    def step(self, inp: Speed) -> Thrust:
        raise AssertionError("the env supplies this flow's actions")


class Rocket(Flow[Thrust, Speed]):
    """Doubles the thrust it is given in place (a mistake: it is the agent's event)."""

    def step(self, inp: Thrust) -> Speed:
        inp.force *= 2
        return Speed(float(inp.force[0]))


def test_the_agents_action_is_immutable_for_its_consumers_as_any_emitted_value():
    """The env's action is the agent's event (its tick replaced by the env): a consumer that
    writes into it fails as it would on any event (docs/semantics.md, "An emitted value is
    immutable"), and the caller's own array is left writable (the env copies it in)."""
    def rocket(seed):
        with Pipeline("rocket") as pipe:
            world = Rocket().named("world").configure(on_error="skip_tick") @ Trigger("force")
            pilot = Pilot().named("pilot") @ Rate(10)
            pilot.then(world)
            world.then(pilot, delay=0.01)
        return pipe

    env = PipelineEnv(rocket, "pilot", observation_space=gymnasium.spaces.Dict({"v": gymnasium.spaces.Box(-9, 9)}),
                      action_space=gymnasium.spaces.Box(-1.0, 1.0, shape=(1,)))
    env.reset(seed=0)
    action = np.array([0.5], dtype=np.float32)
    env.step(action)
    env.step(action)
    action[0] = 0.25  # the caller's array stays its own
    errors = [s for s in env.trace.steps_of("world") if s.status == "error"]
    assert errors and "ValueError: output array is read-only" in str(errors[0].detail)
    assert [float(v[0]) for v in env.trace.values_of("pilot", "force")] == [0.5, 0.5]
