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
#: the largest policy.json read (python -m agents.learn train writes about 400 bytes)
MAX_CONFIG_BYTES = 1 << 16
#: the most parameters a checkpoint's module may have (a Pick MLP of hidden=256 has about 270 000)
MAX_PARAMETERS = 1 << 24
COMMAND = slice(2 * NU, 3 * NU)     # the commanded targets in the state vector
#: the dtypes a checkpoint's tensors may have (safetensors' names; agents.learn.bc saves F32)
FLOAT_DTYPES = ("F16", "F32", "F64")


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
    if not path.exists() and (Path(folder) / "config.json").is_file():
        raise ValueError(f"skill policy {str(folder)!r}: a LeRobot checkpoint (config.json, no {CONFIG_FILE}); this "
                         "takes a checkpoint of python -m agents.learn train; run a LeRobot policy as a "
                         "retriever.learn.LeRobotPolicy flow (docs/learning.md)")
    if path.is_file() and path.stat().st_size > MAX_CONFIG_BYTES:
        raise ValueError(f"skill policy {str(folder)!r}: {CONFIG_FILE} is {path.stat().st_size} bytes; a Pick "
                         f"policy's config is a few hundred (at most {MAX_CONFIG_BYTES} are read)")
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
    from .skill_features import SCENE_NAMES, STATE_NAMES
    if (config["nu"], config["state_dim"], config["scene_dim"]) != (NU, len(STATE_NAMES), len(SCENE_NAMES)):
        raise ValueError(f"skill policy {str(folder)!r}: nu={config['nu']}, state_dim={config['state_dim']}, "
                         f"scene_dim={config['scene_dim']}: the robot has {NU} actuators, its state "
                         f"{len(STATE_NAMES)} values and its scene {len(SCENE_NAMES)} (agents/skill_features.py): "
                         "a policy trained on other features cannot run in this slot")
    return config


def weight_shapes(config: dict) -> dict[str, tuple[int, ...]]:
    """The tensors of ``model.safetensors`` a :class:`agents.learn.bc.PickMLP` of ``config``'s
    sizes holds, and their shapes."""
    x_dim, y_dim, hidden = config["state_dim"] + config["scene_dim"], config["steps"] * config["nu"], config["hidden"]
    return {"x_mean": (x_dim,), "x_std": (x_dim,), "y_mean": (y_dim,), "y_std": (y_dim,),
            "net.0.weight": (hidden, x_dim), "net.0.bias": (hidden,), "net.2.weight": (hidden, hidden),
            "net.2.bias": (hidden,), "net.4.weight": (y_dim, hidden), "net.4.bias": (y_dim,)}


def check_weights(folder: str | Path, config: dict) -> None:
    """``model.safetensors`` in ``folder`` holds the tensors ``config``'s sizes imply, of their
    shapes, and the module is not too large to build; else a ValueError says what differs. Reads
    the file's header only."""
    from safetensors import safe_open
    want = weight_shapes(config)
    size = sum(int(np.prod(shape)) for shape in want.values())
    if size > MAX_PARAMETERS:
        raise ValueError(f"skill policy {str(folder)!r}: {CONFIG_FILE}'s sizes make a module of {size} values, more "
                         f"than the {MAX_PARAMETERS} a Pick policy may have")
    try:
        with safe_open(str(Path(folder) / WEIGHTS_FILE), "np") as f:
            got = {name: tuple(f.get_slice(name).get_shape()) for name in f.keys()}
    except Exception as e:      # safetensors raises its own error types on a damaged header
        raise ValueError(f"skill policy {str(folder)!r}: {WEIGHTS_FILE} is not a readable safetensors file "
                         f"({type(e).__name__})") from None
    problems = ([f"{name} is missing" for name in want if name not in got]
                + [f"{name} is not the module's" for name in got if name not in want]
                + [f"{name} has shape {got[name]}, not {want[name]}" for name in want
                   if name in got and got[name] != want[name]])
    if problems:
        raise ValueError(f"skill policy {str(folder)!r}: {WEIGHTS_FILE} does not fit the sizes of {CONFIG_FILE}: "
                         + "; ".join(problems[:4]) + (f" (and {len(problems) - 4} more)" if len(problems) > 4 else ""))


def check_values(folder: str | Path) -> None:
    """Every tensor of ``model.safetensors`` in ``folder`` is of a float dtype and finite, or a
    ValueError names the first that is not (a NaN weight would stop the run at Pick's first
    tick; an integer one would be cast silently)."""
    from safetensors import safe_open
    with safe_open(str(Path(folder) / WEIGHTS_FILE), "np") as f:
        for name in f.keys():
            dtype = f.get_slice(name).get_dtype()
            if dtype not in FLOAT_DTYPES:
                raise ValueError(f"skill policy {str(folder)!r}: {WEIGHTS_FILE}'s {name} is {dtype}, not a float "
                                 f"tensor ({', '.join(FLOAT_DTYPES)})")
            bad = int(np.count_nonzero(~np.isfinite(f.get_tensor(name))))
            if bad:
                raise ValueError(f"skill policy {str(folder)!r}: {WEIGHTS_FILE}'s {name} holds {bad} value(s) that "
                                 "are not finite (NaN or infinity): the checkpoint is damaged, or its training "
                                 "diverged")


def check_installed() -> None:
    """torch and safetensors, which a checkpoint policy needs, can be imported here, or a
    ValueError says what to install."""
    from importlib.util import find_spec
    missing = [name for name in ("torch", "safetensors") if find_spec(name) is None]
    if missing:
        raise ValueError(f"a trained skill policy needs {' and '.join(missing)}, which cannot be imported here\n"
                         "    hint: pip install 'retriever-robotics[lerobot]' (or run the scripted Pick: "
                         "--skill-policy scripted)")


def check_skill_policy(spec: str) -> None:
    """``spec`` names a policy (``"scripted"`` or a checkpoint directory), or a ValueError says
    why not: before anything starts, the packages it needs, its config, the weights' names and
    shapes (from the header) and then their dtypes and values (a Pick module's are a few MB)."""
    if spec == "scripted":
        return
    if not isinstance(spec, str) or not Path(spec).is_dir():
        raise ValueError(f"skill policy {spec!r}: no such directory (give 'scripted' or a checkpoint directory "
                         "of python -m agents.learn train)")
    if not (Path(spec) / WEIGHTS_FILE).is_file():
        raise ValueError(f"skill policy {spec!r}: the directory holds no {WEIGHTS_FILE} (python -m agents.learn "
                         "train writes it)")
    check_installed()
    check_weights(spec, read_config(spec))
    check_values(spec)
