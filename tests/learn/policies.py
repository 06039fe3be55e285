"""Policy flows and tiny checkpoints for the tests of retriever.learn: a real LeRobot ACT policy
(small dimensions, no pretrained backbone) saved with LeRobot's own ``save_pretrained``, and a
plain torch module saved as safetensors. Importable by module path, as a replay from the IR
rebuilds them."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from retriever import Flow
from retriever.learn import LeRobotPolicy, TorchPolicy
from tests.log.dataset_flows import Pose

CHUNK = 6
ACTION_DIM = 2
IMAGE = (24, 32)


def act_checkpoint(path: Path, *, processors: bool = True) -> Path:
    """A freshly initialised ACT policy with an image and a state input, saved as lerobot-train does."""
    import torch
    from lerobot.configs.types import FeatureType, PolicyFeature
    from lerobot.policies.act.configuration_act import ACTConfig
    from lerobot.policies.act.modeling_act import ACTPolicy
    from lerobot.policies.factory import make_pre_post_processors

    torch.manual_seed(0)
    config = ACTConfig(
        input_features={"observation.state": PolicyFeature(FeatureType.STATE, (3,)),
                        "observation.images.image": PolicyFeature(FeatureType.VISUAL, (3, *IMAGE))},
        output_features={"action": PolicyFeature(FeatureType.ACTION, (ACTION_DIM,))},
        chunk_size=CHUNK, n_action_steps=CHUNK, dim_model=16, dim_feedforward=32, n_heads=2,
        n_encoder_layers=1, n_decoder_layers=1, n_vae_encoder_layers=1, latent_dim=4,
        pretrained_backbone_weights=None, device="cpu", push_to_hub=False)
    policy = ACTPolicy(config)
    policy.save_pretrained(path)
    if processors:
        stats = {"observation.state": {"mean": torch.tensor([0.5, 0.0, -0.5]), "std": torch.tensor([2.0, 1.0, 0.5])},
                 "observation.images.image": {"mean": torch.full((3, 1, 1), 0.5), "std": torch.full((3, 1, 1), 0.25)},
                 "action": {"mean": torch.tensor([1.0, -1.0]), "std": torch.tensor([3.0, 0.5])}}
        pre, post = make_pre_post_processors(config, dataset_stats=stats)
        pre.save_pretrained(path)
        post.save_pretrained(path)
    return path


class Camera(Flow):
    """A source of a uint8 image and a 3-vector state that change every tick."""

    def __init__(self):
        self.n = 0

    def step(self):
        self.n += 1
        rng = np.random.default_rng(self.n)
        return {"image": rng.integers(0, 256, (*IMAGE, 3), dtype=np.uint8),
                "state": np.array([self.n * 0.1, np.sin(self.n), -1.0])}


class ActPick(LeRobotPolicy):
    def step(self, image: np.ndarray | None = None, state: np.ndarray | None = None):
        return self.act(image=image, state=state)


class Player(Flow):
    """The controller: plays the row it is given."""

    def step(self, action: np.ndarray):
        return {"played": np.array(action, copy=True)}


def row_module(steps: int):
    import torch

    class Rows(torch.nn.Module):
        """Row i of the chunk made from state s is ``[1000 s + i]``: every row of a run is unique."""

        def __init__(self):
            super().__init__()
            self.scale = torch.nn.Parameter(torch.ones(1))
            self.leftovers: list = []

        def forward(self, batch, prev_chunk_left_over=None, inference_delay=0):
            self.leftovers.append((prev_chunk_left_over, inference_delay))
            state = batch["observation.state"][:, :1]  # (1, 1)
            rows = torch.arange(steps, dtype=torch.float32)[None, :, None]  # (1, T, 1)
            return (state[:, :, None] * 1000 + rows) * self.scale

    return Rows()


def rows_checkpoint(path: Path) -> Path:
    from safetensors.torch import save_file

    path.mkdir(parents=True, exist_ok=True)
    save_file(row_module(1).state_dict(), str(path / "model.safetensors"))
    return path


class Counter(Flow):
    def __init__(self):
        self.n = 0

    def step(self):
        self.n += 1
        return {"state": np.array([float(self.n)])}


class Chunker(TorchPolicy):
    """Emits its chunk, and what real-time chunking told it: the delay and the leftover rows."""

    def __init__(self, path: str, steps: int = 10, **options):
        super().__init__(path, **options)
        self.steps = steps

    def build(self):
        return row_module(self.steps)

    def step(self, state: np.ndarray | None = None):
        out = self.act(state=state)
        if out is None:
            return None
        leftover = np.array(self.leftover.rows, dtype=np.int64).reshape(-1, 2)
        return {**out, "delay": self.leftover.delay, "leftover": leftover}


def noisy_module():
    import torch

    class Noisy(torch.nn.Module):
        """Samples, as a diffusion policy's denoising starts from noise."""

        def __init__(self):
            super().__init__()
            self.scale = torch.nn.Parameter(torch.ones(1))

        def forward(self, batch):
            return batch["observation.state"][:, None, :1] + torch.randn(1, 4, 1) * self.scale

    return Noisy()


class NoisyPolicy(TorchPolicy):
    def build(self):
        return noisy_module()

    def step(self, state: np.ndarray | None = None):
        return self.act(state=state)


def observing_module(seen: list):
    import torch

    class Observing(torch.nn.Module):
        """Keeps each observation it is given (in ``seen``); its chunk is made from the state."""

        def __init__(self):
            super().__init__()
            self.scale = torch.nn.Parameter(torch.ones(1))

        def forward(self, batch):
            seen.append({key: value[0].numpy().copy() for key, value in batch.items()})
            return batch["observation.state"][:, None, :2] * self.scale  # (1, 1, 2): a one-row chunk

    return Observing()


def observing_checkpoint(path: Path) -> Path:
    from safetensors.torch import save_file

    path.mkdir(parents=True, exist_ok=True)
    save_file(observing_module([]).state_dict(), str(path / "model.safetensors"))
    return path


class Observer(TorchPolicy):
    """Takes the camera's image, joints and pose (tests/log/dataset_flows.py); ``seen`` holds the
    observation it built at each tick, as its model got it."""

    def __init__(self, path: str, **options):
        super().__init__(path, **options)
        self.seen: list[dict[str, np.ndarray]] = []

    def build(self):
        return observing_module(self.seen)

    def step(self, image: np.ndarray | None = None, joints: np.ndarray | None = None, pose: Pose | None = None):
        return self.act(image=image, joints=joints, pose=pose)
