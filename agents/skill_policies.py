"""The policies behind the learned-skill slot of Retriever-0 (the ``pick_policy`` flow): the
scripted skill, or a trained checkpoint.

A skill policy turns what the robot senses (the ``state`` and ``scene`` vectors and the wrist
camera's frame, :mod:`agents.skill_features`) into an action chunk: ``steps`` rows of absolute
command targets (``ACTUATORS`` order: x, y, z, pitch, grip), one per control tick from the
observation on, the same chunks the scripted skills send the controller. The skill's progress,
success and failure are not the policy's business: the skill flow computes them from the
world's observation as it does for every skill.

    "scripted"      the scripted skill, fed only what a learned one gets (ScriptedSkill, run by
                    agents.flows.SkillActor)
    DIR             a checkpoint of python -m agents.learn train, run by agents.flows.LearnedSkill
                    (a retriever.learn.TorchPolicy): policy.json (read_config) and model.safetensors
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .robot import NU

CONFIG_FILE, WEIGHTS_FILE = "policy.json", "model.safetensors"
#: the class a checkpoint's module is, named in code (policy.json says it, and nothing else is built)
KIND = "agents.learn.bc.PickMLP"
#: policy.json's sizes of the module, each a positive integer
CONFIG = ("state_dim", "scene_dim", "steps", "nu", "hidden")
COMMAND = slice(2 * NU, 3 * NU)     # the commanded targets in the state vector


@dataclass(frozen=True)
class SkillObservation:
    """One tick's input of the scripted skill policy. ``t`` counts seconds since the skill began
    (the policy's own ticks: no clock of the world's); ``skill`` is the command, "Pick(spice)"."""
    t: float
    skill: str
    state: np.ndarray           # float64 (18,), skill_features.STATE_NAMES
    scene: np.ndarray           # float64 (10,), skill_features.SCENE_NAMES
    wrist: np.ndarray           # uint8 (H, W, 3); zeros before the camera's first frame


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


def read_config(folder: str | Path) -> dict:
    """A checkpoint's ``policy.json``, checked (the sizes its module is built with); a
    ValueError says what is wrong."""
    path = Path(folder) / CONFIG_FILE
    try:
        config = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError) as e:
        raise ValueError(f"skill policy {str(folder)!r}: {CONFIG_FILE} is not readable JSON ({type(e).__name__}); a "
                         f"checkpoint holds {CONFIG_FILE} and {WEIGHTS_FILE} (python -m agents.learn train)") from None
    if type(config) is not dict or config.get("kind") != KIND:
        raise ValueError(f"skill policy {str(folder)!r}: {CONFIG_FILE} is no Pick policy's config (its kind must be "
                         f"{KIND!r})")
    bad = [key for key in CONFIG if type(config.get(key)) is not int or not 0 < config[key] <= 1 << 16]
    if bad:
        raise ValueError(f"skill policy {str(folder)!r}: {CONFIG_FILE}'s {', '.join(bad)} must be positive integers")
    if config["nu"] != NU or config["state_dim"] < COMMAND.stop:
        raise ValueError(f"skill policy {str(folder)!r}: nu={config['nu']}, state_dim={config['state_dim']}: the "
                         f"robot has {NU} actuators, and the state holds their commands at {COMMAND.start}:"
                         f"{COMMAND.stop}")
    return config


def check_skill_policy(spec: str) -> None:
    """``spec`` names a policy (``"scripted"`` or a checkpoint directory), or a ValueError says
    why not (cheap: it loads no weights)."""
    if spec == "scripted":
        return
    if not isinstance(spec, str) or not Path(spec).is_dir():
        raise ValueError(f"skill policy {spec!r}: no such directory (give 'scripted' or a checkpoint directory "
                         "of python -m agents.learn train)")
    if not (Path(spec) / WEIGHTS_FILE).is_file():
        raise ValueError(f"skill policy {spec!r}: the directory holds no {WEIGHTS_FILE} (python -m agents.learn "
                         "train writes it)")
    read_config(spec)
