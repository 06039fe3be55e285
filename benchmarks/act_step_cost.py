"""What LeRobot's ACT costs on the CPU for Retriever-0's Pick policy inputs (docs/learning.md):
the seconds of one training step (batch of 8) and of one chunk inference, with the pick_policy
flow's features: state (18), environment state (10), the wrist image (3×64×64), action (5),
chunks of 100, no pretrained backbone (nothing is fetched).

    python benchmarks/act_step_cost.py [--threads 2] [--steps 5]
"""

from __future__ import annotations

import argparse
import time


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--steps", type=int, default=5)
    parser.add_argument("--batch", type=int, default=8)
    args = parser.parse_args()
    import torch
    from lerobot.configs.types import FeatureType, PolicyFeature
    from lerobot.policies.act.configuration_act import ACTConfig
    from lerobot.policies.act.modeling_act import ACTPolicy
    torch.set_num_threads(args.threads)
    torch.manual_seed(0)
    features = {"observation.state": PolicyFeature(FeatureType.STATE, (18,)),
                "observation.environment_state": PolicyFeature(FeatureType.ENV, (10,)),
                "observation.images.wrist": PolicyFeature(FeatureType.VISUAL, (3, 64, 64))}
    config = ACTConfig(input_features=features, output_features={"action": PolicyFeature(FeatureType.ACTION, (5,))},
                       chunk_size=100, n_action_steps=100, pretrained_backbone_weights=None, device="cpu")
    policy = ACTPolicy(config)
    optimiser = torch.optim.AdamW(policy.parameters(), lr=1e-5)
    b = args.batch
    batch = {"observation.state": torch.randn(b, 18), "observation.environment_state": torch.randn(b, 10),
             "observation.images.wrist": torch.rand(b, 3, 64, 64), "action": torch.randn(b, 100, 5),
             "action_is_pad": torch.zeros(b, 100, dtype=torch.bool)}
    print(f"ACT: {sum(p.numel() for p in policy.parameters()) / 1e6:.1f} M parameters, {args.threads} threads")
    times = []
    for _ in range(args.steps):
        started = time.perf_counter()
        loss, _ = policy.forward(batch)
        optimiser.zero_grad()
        loss.backward()
        optimiser.step()
        times.append(time.perf_counter() - started)
    print(f"training step (batch {b}): {' '.join(f'{t:.2f}' for t in times)} s")
    policy.eval()
    observation = {k: v[:1] for k, v in batch.items() if k.startswith("observation")}
    with torch.no_grad():
        started = time.perf_counter()
        for _ in range(args.steps):
            policy.predict_action_chunk(observation)
    print(f"one chunk's inference: {(time.perf_counter() - started) / args.steps:.2f} s")


if __name__ == "__main__":
    main()
