"""The policies behind a learned-skill slot of Retriever-0: the scripted skill, or a model.

A skill policy turns what the robot senses (:class:`SkillObservation`: the ``state`` and
``scene`` vectors and the wrist camera's frame, :mod:`agents.skill_features`) into an action
chunk: ``steps`` rows of absolute command targets (``ACTUATORS`` order: x, y, z, pitch, grip),
one per control tick from the observation on, the same chunks the scripted skills send the
controller. The skill's progress, success and failure are not the policy's business: the skill
flow computes them from the world's observation as it does for every skill.

    load_skill_policy("scripted")      the scripted skill, fed only what a learned one gets
    load_skill_policy("policy.pt")     a TorchScript module (see TorchScriptSkill)

``load_skill_policy`` is the one hook a new kind of policy (a LeRobot checkpoint) plugs into.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Protocol

import numpy as np

from .robot import NU


@dataclass(frozen=True)
class SkillObservation:
    """One tick's input of a skill policy. ``t`` counts seconds since the skill began (the
    policy's own ticks: no clock of the world's); ``skill`` is the command, "Pick(spice)"."""
    t: float
    skill: str
    state: np.ndarray           # float64 (18,), skill_features.STATE_NAMES
    scene: np.ndarray           # float64 (10,), skill_features.SCENE_NAMES
    wrist: np.ndarray           # uint8 (H, W, 3); zeros before the camera's first frame


class SkillPolicyModel(Protocol):
    def reset(self, skill: str) -> None:
        """A new invocation of the skill begins (forget the last one)."""

    def act(self, obs: SkillObservation, steps: int, control_hz: float) -> np.ndarray:
        """The action chunk: float64 (steps, NU) absolute command targets at ``control_hz``."""


class ScriptedSkill:
    """The scripted skill (:class:`agents.skills.SkillController`) run on the facts the two
    vectors tell (:func:`agents.skill_features.facts_of`): the teacher a dataset records."""

    def __init__(self):
        self.controller = None

    def reset(self, skill: str) -> None:
        from .plan import parse_skill
        from .skills import make_skill
        parsed = parse_skill(skill, "drawers")
        self.controller = make_skill(parsed.name, parsed.arg)

    def act(self, obs: SkillObservation, steps: int, control_hz: float) -> np.ndarray:
        from .skill_features import facts_of
        return self.controller.act(facts_of(obs.t, obs.state, obs.scene), steps, control_hz).actions


class TorchScriptSkill:
    """A TorchScript module (``torch.jit.save``) as a skill policy, on the CPU: ``forward(state,
    scene, wrist)`` gets float64 (1, 18) and (1, 10) tensors and the wrist frame as uint8
    (1, H, W, 3), and returns the chunk (1, k, NU) of absolute targets, in any float dtype; a
    chunk shorter than the controller needs holds its last row."""

    def __init__(self, path: str, threads: int = 1):
        import torch
        torch.set_num_threads(threads)
        self.torch = torch
        with warnings.catch_warnings():  # TorchScript is deprecated in favour of torch.export, and still loads
            warnings.filterwarnings("ignore", category=FutureWarning, message=".*torch.jit")
            self.module = torch.jit.load(path, map_location="cpu").eval()

    def reset(self, skill: str) -> None:
        pass

    def act(self, obs: SkillObservation, steps: int, control_hz: float) -> np.ndarray:
        torch = self.torch
        with torch.inference_mode():
            # copies: a value decoded from the wire is a read-only view, which torch will not wrap
            out = self.module(torch.tensor(obs.state[None]), torch.tensor(obs.scene[None]),
                              torch.tensor(obs.wrist[None]))
        chunk = out.detach().to(torch.float64).numpy()
        if chunk.ndim != 3 or chunk.shape[0] != 1 or chunk.shape[2] != NU or chunk.shape[1] < 1:
            raise ValueError(f"the skill policy's module returned shape {tuple(chunk.shape)}: "
                             f"expected (1, steps, {NU})")
        rows = chunk[0, :steps]
        if len(rows) < steps:
            rows = np.concatenate([rows, np.repeat(rows[-1:], steps - len(rows), axis=0)])
        return rows


def check_skill_policy(spec: str) -> None:
    """``spec`` can name a policy (``"scripted"`` or a file), or a ValueError says why not
    (cheap: it loads nothing)."""
    if not isinstance(spec, str) or (spec != "scripted" and not Path(spec).is_file()):
        raise ValueError(f"skill policy {spec!r}: no such file (give 'scripted' or a TorchScript module, *.pt)")


def load_skill_policy(spec: str) -> SkillPolicyModel:
    """The policy ``spec`` names: ``"scripted"``, or the path of a policy file (a TorchScript
    module, ``*.pt``). A ValueError says what is wrong with it."""
    check_skill_policy(spec)
    if spec == "scripted":
        return ScriptedSkill()
    path = Path(spec)
    try:
        import torch  # noqa: F401
    except ImportError:
        raise ValueError(f"skill policy {spec}: loading a TorchScript module needs torch (pip install torch)") from None
    try:
        return TorchScriptSkill(str(path))
    except RuntimeError as e:
        raise ValueError(f"skill policy {spec}: not a TorchScript module torch.jit.load can read "
                         f"({str(e).strip().splitlines()[0][:200]})") from None
