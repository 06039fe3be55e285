"""A TorchScript skill policy for tests: it replays the chunks a logged pick_policy flow sent,
answering each tick with the chunk of the logged tick whose state and scene are nearest
(float64 throughout, so on the logged seed it sends the logged chunks exactly)."""

from __future__ import annotations

import numpy as np
import torch
from torch import nn

from agents.learn.dataset import read_samples


class Replay(nn.Module):
    def __init__(self, keys: np.ndarray, chunks: np.ndarray):
        super().__init__()
        self.register_buffer("keys", torch.as_tensor(keys, dtype=torch.float64))
        self.register_buffer("chunks", torch.as_tensor(chunks, dtype=torch.float64))

    def forward(self, state: torch.Tensor, scene: torch.Tensor, wrist: torch.Tensor) -> torch.Tensor:
        x = torch.cat([state, scene], dim=1)
        nearest = torch.argmin(((self.keys - x) ** 2).sum(dim=1))
        return self.chunks[nearest][None]


def save_replay(log, path) -> list[np.ndarray]:
    """Write the replay module of ``log``'s pick_policy ticks to ``path``; returns their chunks."""
    states, scenes, actions = read_samples(log)
    module = torch.jit.script(Replay(np.concatenate([np.stack(states), np.stack(scenes)], axis=1), np.stack(actions)))
    module.save(str(path))
    return actions
