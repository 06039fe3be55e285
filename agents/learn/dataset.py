"""The Pick policy's dataset: the collected logs exported by ``retriever log export`` (one frame
per tick of the ``pick_policy`` flow: what it consumed on ``state``, ``scene`` and ``wrist`` as
its sync policies selected them, and the chunk it sent), and read back for training with the
format's own loader (``LeRobotDataset(repo_id, root=DIR)``, or the npz files).

The export's features (:data:`MAPS`): ``state`` → ``observation.state``, ``scene`` →
``observation.environment_state``, the wrist frame's pixels → ``observation.images.wrist``, the
chunk's rows (150×5, flattened) → ``action``; the command (a ``SkillCmd``, not text) is left out
and every frame's task is the skill's call, ``Pick(spice)``.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from retriever.log import export_dataset
from retriever.log.dataset import NPZ_FORMAT

from ..retriever0 import LEARNED_SKILL_CALL, POLICY_NODE

STATE, SCENE, WRIST, ACTION = "observation.state", "observation.environment_state", "observation.images.wrist", "action"
MAPS = {"state": STATE, "scene": SCENE, "wrist.rgb": WRIST}
EXCLUDE = ("skill", "wrist.t", "action.skill_id")


@dataclass
class Samples:
    state: np.ndarray       # (n, 18)
    scene: np.ndarray       # (n, 10)
    action: np.ndarray      # (n, steps, NU)
    episode: np.ndarray     # (n,) the episode each came from


def export(logs, out: str | Path, format: str = "lerobot", overwrite: bool = False, progress=None):
    """Export ``logs`` (one episode each) as the Pick policy's dataset ``out``; returns the
    export's summary (:class:`retriever.log.ExportSummary`)."""
    from .. import messages  # noqa: F401  (the value types the logs' events decode to)
    return export_dataset(list(logs), out, flow=POLICY_NODE, format=format, maps=MAPS, exclude=EXCLUDE,
                          task=LEARNED_SKILL_CALL, overwrite=overwrite, progress=progress)


def load_dataset(folder: str | Path, steps_nu: tuple[int, int] = (150, 5)) -> Samples:
    """The training samples of an exported dataset folder (LeRobot or npz)."""
    folder = Path(folder)
    info = folder / "info.json"
    if info.is_file() and json.loads(info.read_text()).get("format") == NPZ_FORMAT:
        columns = _npz_columns(folder)
    elif (folder / "meta" / "info.json").is_file():
        columns = _lerobot_columns(folder)
    else:
        raise ValueError(f"{folder}: no exported dataset (LeRobot's meta/info.json or the npz format's info.json); "
                         "export the logs first (python -m agents.learn export)")
    missing = [key for key in (STATE, SCENE, ACTION) if key not in columns]
    if missing:
        raise ValueError(f"{folder}: the dataset has no {', '.join(missing)}: it is not the Pick policy's export")
    action = columns[ACTION]
    if action.shape[1] != steps_nu[0] * steps_nu[1]:
        raise ValueError(f"{folder}: its action has {action.shape[1]} values, a chunk of {steps_nu[0]}×{steps_nu[1]}"
                         f" has {steps_nu[0] * steps_nu[1]}")
    return Samples(columns[STATE].astype(np.float64), columns[SCENE].astype(np.float64),
                   action.astype(np.float64).reshape(len(action), *steps_nu), columns["episode_index"])


def _lerobot_columns(folder: Path) -> dict[str, np.ndarray]:
    """The numeric columns, as LeRobot loads them (the images are not decoded: the MLP does not
    use them)."""
    from lerobot.datasets.lerobot_dataset import LeRobotDataset
    info = json.loads((folder / "meta" / "info.json").read_text())
    keys = [k for k in (STATE, SCENE, ACTION, "episode_index") if k in info.get("features", {})]
    dataset = LeRobotDataset(f"retriever/{folder.name}", root=folder)
    table = dataset.hf_dataset.select_columns(keys).with_format("numpy")[:]
    return {key: np.asarray(table[key]) for key in keys}


def _npz_columns(folder: Path) -> dict[str, np.ndarray]:
    columns: dict[str, list] = {}
    for k, path in enumerate(sorted(folder.glob("episode_*.npz"))):
        with np.load(path, allow_pickle=False) as episode:
            for key in episode.files:
                columns.setdefault(key, []).append(episode[key])
            columns.setdefault("episode_index", []).append(np.full(len(episode[ACTION]), k))
    return {key: np.concatenate(parts) for key, parts in columns.items()}
