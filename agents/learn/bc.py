"""Behaviour cloning of the Pick policy: a small MLP from ``state`` and ``scene`` to the action
chunk, trained on the CPU within a time budget, saved as a TorchScript module that
:class:`agents.skill_policies.TorchScriptSkill` runs (it ignores the wrist frame).

The chunk is predicted relative to the commanded targets (``state``'s ``*_cmd``: where the hand
is being sent now), every value normalised by the dataset's mean and spread.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from ..robot import NU
from .dataset import Samples

COMMAND = slice(2 * NU, 3 * NU)     # the commanded targets in the state vector


@dataclass
class Training:
    samples: int
    episodes: int
    epochs: int
    seconds: float
    train_loss: float
    held_out_loss: float            # on the episodes kept out of training (nan without any)
    parameters: int


def _module(x_mean, x_std, y_mean, y_std, steps: int, hidden: int):
    import torch
    from torch import nn

    class ChunkMLP(nn.Module):
        def __init__(self):
            super().__init__()
            for name, value in (("x_mean", x_mean), ("x_std", x_std), ("y_mean", y_mean), ("y_std", y_std)):
                self.register_buffer(name, torch.as_tensor(value, dtype=torch.float32))
            self.steps, self.nu, self.command = steps, NU, COMMAND.start
            self.net = nn.Sequential(nn.Linear(len(x_mean), hidden), nn.ReLU(), nn.Linear(hidden, hidden), nn.ReLU(),
                                     nn.Linear(hidden, len(y_mean)))

        def normalised(self, state: torch.Tensor, scene: torch.Tensor) -> torch.Tensor:
            x = torch.cat([state, scene], dim=1).to(torch.float32)
            return self.net((x - self.x_mean) / self.x_std)

        def forward(self, state: torch.Tensor, scene: torch.Tensor, wrist: torch.Tensor) -> torch.Tensor:
            delta = self.normalised(state, scene) * self.y_std + self.y_mean
            command = state[:, self.command:self.command + self.nu].to(torch.float64)
            return delta.to(torch.float64).view(-1, self.steps, self.nu) + command[:, None, :]

    return ChunkMLP()


def train(samples: Samples, budget_s: float = 120.0, max_epochs: int = 3000, hidden: int = 256,
          held_out: float = 0.1, seed: int = 0, threads: int = 2, log=None):
    """Train on ``samples`` for at most ``budget_s`` seconds of wall time or ``max_epochs``;
    the last ``held_out`` of the episodes measure the loss on data it never saw. Returns the
    scripted module and a :class:`Training` summary. ``log(epoch, loss)`` is told each epoch."""
    import torch
    torch.manual_seed(seed)
    torch.set_num_threads(threads)
    x = np.concatenate([samples.state, samples.scene], axis=1)
    n, steps = len(x), samples.action.shape[1]
    y = (samples.action - samples.state[:, None, COMMAND]).reshape(n, -1)
    episodes = np.unique(samples.episode)
    test_eps = episodes[len(episodes) - int(round(held_out * len(episodes))):] if held_out > 0 else episodes[:0]
    test = np.isin(samples.episode, test_eps)
    train_x, train_y = x[~test], y[~test]
    x_mean, x_std = train_x.mean(0), np.maximum(train_x.std(0), 1e-3)
    y_mean, y_std = train_y.mean(0), np.maximum(train_y.std(0), 1e-3)
    model = _module(x_mean, x_std, y_mean, y_std, steps, hidden)
    X = torch.as_tensor(train_x, dtype=torch.float64)
    Y = torch.as_tensor((train_y - y_mean) / y_std, dtype=torch.float32)
    TX = torch.as_tensor(x[test], dtype=torch.float64)
    TY = torch.as_tensor((y[test] - y_mean) / y_std, dtype=torch.float32)
    optimiser = torch.optim.AdamW(model.parameters(), lr=1e-3, weight_decay=1e-4)
    schedule = torch.optim.lr_scheduler.CosineAnnealingLR(optimiser, T_max=max_epochs)
    state_dim = samples.state.shape[1]
    started, epoch, loss_value = time.perf_counter(), 0, float("nan")
    while epoch < max_epochs and time.perf_counter() - started < budget_s:
        order = torch.randperm(len(X))
        total = 0.0
        for batch in order.split(256):
            out = model.normalised(X[batch, :state_dim], X[batch, state_dim:])
            loss = torch.nn.functional.mse_loss(out, Y[batch])
            optimiser.zero_grad()
            loss.backward()
            optimiser.step()
            total += float(loss) * len(batch)
        schedule.step()
        epoch += 1
        loss_value = total / len(X)
        if log is not None:
            log(epoch, loss_value)
    seconds = time.perf_counter() - started
    model.eval()
    with torch.no_grad():
        held = (float(torch.nn.functional.mse_loss(model.normalised(TX[:, :state_dim], TX[:, state_dim:]), TY))
                if len(TX) else float("nan"))
    parameters = sum(p.numel() for p in model.parameters())
    return torch.jit.script(model), Training(n, len(episodes), epoch, seconds, loss_value, held, parameters)
