"""A dataset of the Pick policy read straight from collected logs: at each tick of the policy
flow that sent a chunk, what it consumed on ``state`` and ``scene`` and the chunk it produced
(the step record names the events; nothing is re-derived from arrival order). ``retriever log
export`` (issue 36, section 1) does this for any flow and format; this reader is the learning
loop's own, for its first small policy."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from retriever import read_log

from ..retriever0 import POLICY_NODE


@dataclass
class Samples:
    state: np.ndarray       # (n, 18)
    scene: np.ndarray       # (n, 10)
    action: np.ndarray      # (n, steps, NU)
    episode: np.ndarray     # (n,) index of the log each came from


def read_samples(path: str | Path, node: str = POLICY_NODE) -> tuple[list, list, list]:
    """(state, scene, action) of each tick of ``node`` in the log that sent an action."""
    from .. import messages  # noqa: F401  (the value types the log's events decode to)
    log = read_log(path)
    steps = [s for s in log.iter_steps() if s.node == node and s.status == "ok" and s.produced]
    wanted = {i for s in steps for port in ("state", "scene") for i in s.consumed.get(port, ())}
    wanted |= {i for s in steps for i in s.produced}
    events = {e.id: e for e in log.iter_events() if e.id in wanted}
    states, scenes, actions = [], [], []
    for s in steps:
        if not {"state", "scene"} <= s.consumed.keys():
            continue
        (action_id,) = [i for i in s.produced if i[1] == "action"]
        states.append(log.value(events[s.consumed["state"][0]]))
        scenes.append(log.value(events[s.consumed["scene"][0]]))
        actions.append(log.value(events[action_id]).actions)
    return states, scenes, actions


def skill_succeeded(path: str | Path) -> bool:
    """Whether the log's skill flow said done (a Pick-only episode's success)."""
    from .. import messages  # noqa: F401
    log = read_log(path)
    last = None
    for e in log.iter_events():
        if e.node == "skill" and e.port == "progress":
            last = e
    return last is not None and log.value(last).status == "done"


def load_dataset(paths, successful_only: bool = True) -> Samples:
    """The samples of every log (of the successful episodes only, by default)."""
    states, scenes, actions, episodes = [], [], [], []
    for k, path in enumerate(paths):
        if successful_only and not skill_succeeded(path):
            continue
        st, sc, ac = read_samples(path)
        states += st
        scenes += sc
        actions += ac
        episodes += [k] * len(st)
    if not states:
        raise ValueError("no samples: the logs hold no successful episode with ticks of the policy flow "
                         f"'{POLICY_NODE}' (collect them with python -m agents.learn collect)")
    return Samples(np.stack(states), np.stack(scenes), np.stack(actions), np.asarray(episodes))
