"""Behaviour cloning of the Pick policy: a small MLP (:class:`PickMLP`) from the exported
dataset's ``observation.state`` and ``observation.environment_state`` to the action chunk,
trained on the CPU within a time budget and saved as a checkpoint directory that
:class:`agents.flows.LearnedSkill` (a :class:`retriever.learn.TorchPolicy`) runs:

- ``model.safetensors``: the MLP's weights and its normalisation (the buffers ``x_mean``,
  ``x_std``, ``y_mean``, ``y_std``), as ``safetensors.torch.save_file`` writes a state dict;
- ``policy.json``: the MLP's sizes, which :func:`agents.skill_policies.read_config` checks
  before the class named here builds it; nothing in the directory is imported or unpickled.

The chunk is predicted relative to the commanded targets (``state``'s ``*_cmd``: where the hand
is being sent now), every value normalised by the training set's mean and spread. The wrist
image is given to the module (it is in the dataset) and not used.
"""

from __future__ import annotations

import json
import math
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Callable

import numpy as np
import torch
from torch import nn

from ..skill_policies import COMMAND, CONFIG, CONFIG_FILE, KIND, WEIGHTS_FILE
from .dataset import Samples

#: the learning rate at the start of the training (AdamW's), annealed to 0 along a cosine
LEARNING_RATE = 1e-3
#: how a training ended (:attr:`Training.ended_by`)
MAX_EPOCHS, TIME_BUDGET = "max_epochs", "time_budget"


@dataclass
class Training:
    samples: int
    episodes: int
    epochs: int
    seconds: float
    train_loss: float | None        # the last epoch's (None before any)
    held_out_loss: float | None     # on the episodes kept out of training (None without any)
    held_out_episodes: int
    parameters: int
    ended_by: str                   # MAX_EPOCHS or TIME_BUDGET: the limit it reached first


class PickMLP(nn.Module):
    """``forward(batch)``: the feature dict of a :class:`retriever.learn.TorchPolicy` (batch of
    n) → the chunk (n, steps, nu) of absolute command targets."""

    def __init__(self, state_dim: int, scene_dim: int, steps: int, nu: int, hidden: int):
        super().__init__()
        x_dim, y_dim = state_dim + scene_dim, steps * nu
        for name, size in (("x_mean", x_dim), ("x_std", x_dim), ("y_mean", y_dim), ("y_std", y_dim)):
            self.register_buffer(name, torch.zeros(size) if name.endswith("mean") else torch.ones(size))
        self.steps, self.nu = steps, nu
        self.net = nn.Sequential(nn.Linear(x_dim, hidden), nn.ReLU(), nn.Linear(hidden, hidden), nn.ReLU(),
                                 nn.Linear(hidden, y_dim))

    def normalised(self, state: torch.Tensor, scene: torch.Tensor) -> torch.Tensor:
        return self.net((torch.cat([state, scene], dim=1) - self.x_mean) / self.x_std)

    def forward(self, batch: dict) -> torch.Tensor:
        state = batch["observation.state"].to(torch.float32)
        scene = batch["observation.environment_state"].to(torch.float32)
        delta = self.normalised(state, scene) * self.y_std + self.y_mean
        return delta.view(-1, self.steps, self.nu) + state[:, None, COMMAND]


def make_module(config: dict):
    """A :class:`PickMLP` of ``config``'s sizes, freshly initialised."""
    return PickMLP(**{key: config[key] for key in CONFIG})


def save(module, config: dict, folder: str | Path, training: Training | None = None) -> Path:
    """Write ``module``'s checkpoint into ``folder`` (created). Both files are written aside and
    renamed into place only once both are whole: a save that fails or is killed while writing
    leaves the checkpoint that was there (weights and config of one training)."""
    from safetensors.torch import save_file
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    parts = {name: folder / f".{name}.part" for name in (WEIGHTS_FILE, CONFIG_FILE)}
    try:
        save_file({k: v.contiguous() for k, v in module.state_dict().items()}, str(parts[WEIGHTS_FILE]))
        doc = {"kind": KIND, **{key: config[key] for key in CONFIG}}
        if training is not None:
            doc["training"] = asdict(training)
        parts[CONFIG_FILE].write_text(json.dumps(doc, indent=1) + "\n")
        for name, part in parts.items():
            part.replace(folder / name)
    finally:
        for part in parts.values():
            part.unlink(missing_ok=True)
    return folder


def train(samples: Samples, budget_s: float | None = 120.0, max_epochs: int = 3000, hidden: int = 256,
          held_out: float = 0.1, seed: int = 0, threads: int = 2, log=None,
          clock: Callable[[], float] = time.perf_counter):
    """Train on ``samples`` for at most ``budget_s`` seconds of wall time (``clock``'s) or
    ``max_epochs``, whichever ends it first; the last ``held_out`` of the episodes measure the
    loss on data it never saw. Returns the module, its config (:data:`CONFIG`) and a
    :class:`Training` summary.

    The learning rate follows a cosine from :data:`LEARNING_RATE` to 0 over the training's
    progress (:func:`progress`): so it is annealed at the end whichever limit ends it. Without a
    time budget (``budget_s`` None or infinite) that progress counts epochs only, and a seed
    trains the same weights every time; with one, how far it got depends on the machine.
    ``log(epoch, loss, epochs)`` is told each epoch, with the epochs the training is expected to
    take by then (``max_epochs``, or fewer once the time budget is seen to end it first)."""
    torch.manual_seed(seed)
    torch.set_num_threads(threads)
    n, steps, nu = samples.action.shape
    x = np.concatenate([samples.state, samples.scene], axis=1).astype(np.float32)
    y = (samples.action - samples.state[:, None, COMMAND]).reshape(n, -1).astype(np.float32)
    episodes = np.unique(samples.episode)
    test_eps = episodes[len(episodes) - int(round(held_out * len(episodes))):] if held_out > 0 else episodes[:0]
    test = np.isin(samples.episode, test_eps)
    train_x, train_y = x[~test], y[~test]
    config = {"state_dim": samples.state.shape[1], "scene_dim": samples.scene.shape[1], "steps": steps, "nu": nu,
              "hidden": hidden}
    model = make_module(config)
    y_mean, y_std = train_y.mean(0), np.maximum(train_y.std(0), 1e-3)
    for name, value in (("x_mean", train_x.mean(0)), ("x_std", np.maximum(train_x.std(0), 1e-3)),
                        ("y_mean", y_mean), ("y_std", y_std)):
        getattr(model, name).copy_(torch.as_tensor(value))
    state_dim = config["state_dim"]
    X, Y = torch.as_tensor(train_x), torch.as_tensor((train_y - y_mean) / y_std)
    TX, TY = torch.as_tensor(x[test]), torch.as_tensor((y[test] - y_mean) / y_std)
    optimiser = torch.optim.AdamW(model.parameters(), lr=LEARNING_RATE, weight_decay=1e-4)
    started, epoch, loss_value, done = clock(), 0, None, 0.0
    while done < 1.0:
        for group in optimiser.param_groups:
            group["lr"] = LEARNING_RATE * 0.5 * (1.0 + math.cos(math.pi * done))
        order = torch.randperm(len(X))
        total = 0.0
        for batch in order.split(256):
            out = model.normalised(X[batch, :state_dim], X[batch, state_dim:])
            loss = torch.nn.functional.mse_loss(out, Y[batch])
            optimiser.zero_grad()
            loss.backward()
            optimiser.step()
            total += loss.item() * len(batch)
        epoch += 1
        loss_value = total / len(X)
        done = progress(epoch, max_epochs, clock() - started, budget_s)
        if log is not None:
            log(epoch, loss_value, epoch if done >= 1.0 else min(max_epochs, math.ceil(epoch / done)))
    seconds = clock() - started
    model.eval()
    with torch.no_grad():
        held = (float(torch.nn.functional.mse_loss(model.normalised(TX[:, :state_dim], TX[:, state_dim:]), TY))
                if len(TX) else None)
    parameters = sum(p.numel() for p in model.parameters())
    ended_by = MAX_EPOCHS if epoch >= max_epochs else TIME_BUDGET
    return model, config, Training(n, len(episodes), epoch, seconds, loss_value, held, len(test_eps), parameters,
                                   ended_by)


def progress(epoch: int, max_epochs: int, elapsed_s: float, budget_s: float | None) -> float:
    """How far a training is, from 0 to 1 (done): the larger of the share of ``max_epochs`` done
    and the share of the time budget spent (the epochs' alone without a budget)."""
    by_time = 0.0 if budget_s is None or math.isinf(budget_s) else elapsed_s / budget_s
    return min(1.0, max(epoch / max_epochs, by_time))
