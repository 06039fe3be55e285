"""retriever.gym.GymWorld: a real gymnasium environment as a world flow, stepped on its clock."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pytest

gymnasium = pytest.importorskip("gymnasium")

from retriever import Flow, Latest, LatestDistinct, Pipeline, Rate, io  # noqa: E402
from retriever.gym import EnvAction, EnvStep, GymWorld  # noqa: E402
from retriever.log import read_log  # noqa: E402
from retriever.replay import replay  # noqa: E402
from tests.gym.gym_flows import Balance, cartpole  # noqa: E402


@io
@dataclass
class PendulumView:
    observation: np.ndarray


@io
@dataclass
class Torque:
    action: np.ndarray


class Swing(Flow[PendulumView, Torque]):
    """Torque against the pendulum's angular velocity, as a float64 row (the space is float32)."""

    def step(self, inp: PendulumView) -> Torque:
        return Torque(np.array([-0.5 * float(inp.observation[2])]))


def played_back(trace, env_id: str, seed: int, world: str = "world") -> int:
    """Step a plain ``gymnasium.make(env_id)`` with the actions each tick of ``world`` consumed,
    resetting it where the world began an episode, and check every event the world made against
    it, bit for bit. Returns how many env steps it checked."""
    direct = gymnasium.make(env_id)
    values = {event.id: event.value for event in trace.events}
    checked = 0
    for record in trace.steps_of(world):
        made = {port: values[(node, port, seq)] for node, port, seq in record.produced}
        if not made:  # no action yet in this episode: the env waited
            assert "action" not in record.consumed
            continue
        if "episode" in made:
            observation, _ = direct.reset(seed=seed if made["episode"] == 0 else None)
            assert (made["terminated"], made["truncated"]) == (False, False)
        else:
            action = values[record.consumed["action"][0]]
            observation, reward, terminated, truncated, _ = direct.step(
                action.astype(np.float32) if isinstance(action, np.ndarray) else action)
            assert (made["reward"], made["terminated"], made["truncated"]) == (reward, terminated, truncated)
            checked += 1
        assert made["observation"].tobytes() == observation.tobytes()
    return checked


def test_cartpole_runs_as_the_world_flow_and_begins_a_new_episode_after_one_ends():
    pipe = cartpole(seed=4)
    trace = pipe.run(duration=6.0)
    assert played_back(trace, "CartPole-v1", seed=4) > 100
    assert len(trace.values_of("world", "episode")) >= 2  # the balancing pilot fails now and then


def test_pendulum_takes_a_float64_action_row_as_its_float32_box():
    with Pipeline("pendulum") as pipe:
        world = GymWorld("Pendulum-v1", seed=2).named("world") @ Rate(20, offset=0.025)
        swing = Swing().named("swing") @ Rate(20)
        world.then(swing).then(world)
    trace = pipe.run(duration=3.0)
    assert played_back(trace, "Pendulum-v1", seed=2) == 59  # every world tick after the first (the reset)


class ClipsInPlace(gymnasium.Env):
    """An env that clips the action it is given in place, as an env may (its own argument)."""

    observation_space = gymnasium.spaces.Box(-1.0, 1.0, shape=(1,), dtype=np.float32)
    action_space = gymnasium.spaces.Box(-1.0, 1.0, shape=(1,), dtype=np.float32)

    def reset(self, seed=None, options=None):
        super().reset(seed=seed)
        return np.zeros(1, dtype=np.float32), {}

    def step(self, action):
        np.clip(action, -0.5, 0.5, out=action)
        return action.copy(), 0.0, False, False, {}


@io
@dataclass
class Pushed:
    action: np.ndarray


class PushHard(Flow[PendulumView, Pushed]):
    def step(self, inp: PendulumView) -> Pushed:
        return Pushed(np.array([0.9], dtype=np.float32))  # of the space's dtype: no conversion copies it


def test_an_env_that_changes_the_action_it_is_given_changes_a_copy_not_the_agents_event():
    """The action is the agent's event, read-only (an emitted value is immutable): the env gets
    its own copy, so an env that writes into its argument runs (it failed, with a hint blaming
    the world flow), and the agent's logged action stays what it emitted."""
    with Pipeline("clips") as pipe:
        world = GymWorld(ClipsInPlace).named("world") @ Rate(10, offset=0.05)
        push = PushHard().named("push") @ Rate(10)
        world.then(push).then(world)
    trace = pipe.run(duration=1.0)
    assert {s.status for s in trace.steps_of("world")} == {"ok"}
    assert [float(v[0]) for v in trace.values_of("world", "observation")][1:] == [0.5] * 9
    assert {float(v[0]) for v in trace.values_of("push", "action")} == {np.float32(0.9)}


def test_latest_holds_the_last_action_and_latest_distinct_steps_only_on_a_new_one():
    consumed = {}
    for sync in (Latest(), LatestDistinct()):
        with Pipeline("held") as pipe:
            world = GymWorld("CartPole-v1", seed=0).named("world") @ Rate(100)
            pilot = Balance().named("pilot") @ Rate(25)
            world.then(pilot)
            pilot.then(world, sync=sync)
        trace = pipe.run(duration=1.0)
        played_back(trace, "CartPole-v1", seed=0)
        consumed[type(sync).__name__] = [r.consumed["action"][0] for r in trace.steps_of("world")
                                         if "action" in r.consumed]
    held, distinct = consumed["Latest"], consumed["LatestDistinct"]
    assert len(held) > 3 * len(set(held))  # each action applied at the world's 4 ticks until the next
    assert len(distinct) == len(set(distinct)) == len(set(held))


def test_a_logged_run_replays_identically_and_its_ir_rebuilds_the_same_run(tmp_path):
    pipe = cartpole(seed=9)
    log = tmp_path / "cartpole.mcap"
    trace = pipe.run(duration=2.0, log=log)
    assert replay(read_log(log)).identical

    ir = pipe.build_ir()
    (node,) = [n for n in ir.nodes if n["id"] == "world"]
    assert (node["type"], node["params"]) == ("retriever.gym.world:GymWorld",
                                              {"env": "CartPole-v1", "seed": 9})
    assert Pipeline.from_ir(ir).run(duration=2.0).digest() == pipe.trace.digest() == trace.digest()


def test_called_directly_it_resets_then_steps():
    world = GymWorld("CartPole-v1", seed=1)
    first = world(EnvAction())
    assert (first.episode, first.reward) == (0, None)
    assert world(EnvAction()) is None  # no action yet
    stepped = world(EnvAction(1))
    assert isinstance(stepped, EnvStep) and stepped.reward == 1.0 and stepped.episode is None


def test_bad_arguments_are_refused_with_what_was_expected():
    with pytest.raises(TypeError, match=r"GymWorld\(env=3\): expected a gymnasium id such as 'CartPole-v1'"):
        GymWorld(3)
    with pytest.raises(ValueError, match=r"GymWorld\(seed=-1\): expected an integer >= 0, or None"):
        GymWorld("CartPole-v1", seed=-1)
    with pytest.raises(ValueError, match=r"GymWorld\(env='os:CartPole-v1'\): give the id alone; gymnasium would "
                                         r"import the module before the ':'"):
        GymWorld("os:CartPole-v1")


def test_a_kwargs_value_the_ir_cannot_carry_is_named_by_its_path_and_type():
    with Pipeline("render") as pipe:
        GymWorld("CartPole-v1", kwargs={"render_mode": object(), "max_episode_steps": 10}).named("world") @ Rate(50)
    (node,) = pipe.build_ir().nodes
    assert node["rebuild_problem"].startswith("argument 'kwargs' holds a object at kwargs['render_mode'], which the "
                                              "IR cannot carry")


@pytest.mark.parametrize("kwargs", [{"xml_file": "/root/secret.xml"}, {"xml_file": "./x.xml"}, {"xml_file": "~/x.xml"},
                                    {"assets": ["ok", "../x"]}, {"nested": {"path": "models/x.xml"}}])
def test_a_file_path_among_an_env_ids_kwargs_is_refused(kwargs):
    """A GymWorld named by its id travels in the IR; a worker rebuilding it would read the path on
    its own machine (an insider's choice of file: issue 40)."""
    with pytest.raises(ValueError, match=r"is a file path, which a worker rebuilding this flow from the IR would "
                                         r"read on its own machine\n    hint: pass a function that makes the env"):
        GymWorld("CartPole-v1", kwargs=kwargs)


def test_an_env_function_may_name_any_file_and_plain_kwargs_pass():
    GymWorld(lambda **kw: None, kwargs={"xml_file": "/home/me/robot.xml"})  # in-process only: the user's own file
    GymWorld("CartPole-v1", kwargs={"render_mode": "rgb_array", "max_episode_steps": 10, "xml_file": "ant.xml"})
