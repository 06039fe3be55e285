"""Learning through Retriever: learned policies as flows (:mod:`.policy`), real-time chunking from
event time (:mod:`.rtc`), and the observation features they share with ``retriever log export``
(:mod:`.features`). Importing this package imports no torch: a policy flow imports it in ``setup()``."""

from .policy import LeRobotPolicy, PolicyFlow, TorchPolicy
from .rtc import ChunkTimeline, Leftover

__all__ = sorted(["ChunkTimeline", "LeRobotPolicy", "Leftover", "PolicyFlow", "TorchPolicy"])
