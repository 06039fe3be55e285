"""Episodes for the learning loop, in virtual time on ``inproc``: the Pick skill alone, or the
whole task, with a given policy in the Pick slot; and what each came to."""

from __future__ import annotations

import time
from dataclasses import dataclass

from ..retriever0 import build

#: world seconds a Pick-only episode may take (the scripted one takes 4-7 s) and a whole task
PICK_SECONDS, TASK_SECONDS = 30.0, 150.0


@dataclass
class Outcome:
    seed: int
    drawer: str
    success: bool
    seconds: float                  # world seconds the episode covered
    wall: float                     # wall seconds it took
    detail: str = ""                # the skill's last status, or the task's ending


def parse_seeds(text: str) -> range:
    """``"A:B"`` → seeds A, A+1, …, B−1 (``"A"`` alone: just A)."""
    try:
        first, _, last = text.partition(":")
        seeds = range(int(first), int(last) if last else int(first) + 1)
    except ValueError:
        raise ValueError(f"--seeds {text!r}: expected A:B (seeds A to B-1), such as 0:20") from None
    if not seeds or seeds.start < 0 or seeds.stop > 1 << 32:
        raise ValueError(f"--seeds {text!r}: expected A:B with 0 <= A < B <= 2**32 (a world's seed is below 2**32)")
    return seeds


def pick_episode(seed: int, policy: str | None = "scripted", log: str | None = None) -> Outcome:
    """The Pick skill alone for ``seed``, with ``policy`` in its slot (None: the skill flow's
    own scripted Pick, no policy flow); success is the skill saying done (its postcondition:
    the bottle is in the hand, lifted)."""
    from ..world import Layout
    pipe = build(seed=seed, episode="pick", skill_policy=policy)
    started = time.perf_counter()
    trace = pipe.run(duration=PICK_SECONDS, backend="inproc", log=log)
    wall = time.perf_counter() - started
    last = [e.value for e in trace.events_of("skill", "progress")][-1:]
    status = last[0].status if last else "never started"
    seconds = trace.steps[-1].tag[0] / 1e9 if trace.steps else 0.0
    return Outcome(seed, Layout.from_seed(seed).target_drawer, status == "done", seconds, wall, status)


def task_episode(seed: int, policy: str | None = None) -> Outcome:
    """The whole task for ``seed``, with ``policy`` in Pick's slot (None: the scripted agent);
    success is full task progress (spice found, grasped, food seasoned, drawers closed)."""
    from ..demo import ending
    from ..episode import summarize
    from ..world import Layout
    pipe = build(seed=seed, skill_policy=policy)
    started = time.perf_counter()
    trace = pipe.run(duration=TASK_SECONDS, backend="inproc")
    wall = time.perf_counter() - started
    ep = summarize(trace, pipe.build_ir())
    return Outcome(seed, Layout.from_seed(seed).target_drawer, ep.score >= 1.0, ep.duration, wall, ending(ep))
