"""Gymnasium, both ways (needs ``pip install 'retriever-robotics[gym]'``):

- :class:`PipelineEnv` (``env.py``): a pipeline as a ``gymnasium.Env`` in virtual time; one Rate
  flow is the agent, whose actions the env's caller supplies, while every other flow runs on its
  own clock, and the agent's declared latency delays its actions as on the robot.
- :class:`GymWorld` (``world.py``): any ``gymnasium.Env`` as a world flow of a pipeline,
  stepped on its clock with the action its input selects.
"""

try:
    import gymnasium  # noqa: F401
except ImportError:
    raise ImportError("retriever.gym needs gymnasium, which is not installed\n"
                      "    hint: pip install 'retriever-robotics[gym]'") from None

from .env import PipelineEnv
from .world import EnvAction, EnvStep, GymWorld

__all__ = ["EnvAction", "EnvStep", "GymWorld", "PipelineEnv"]
