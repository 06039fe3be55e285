"""The node loop's import path of old: the loop itself is the package ``node/`` (its docstring
draws it). The worker and the coordinator import these names from here."""

from ...errors import StopRun
from .node import CONTROL, RESTART_SEQ_GAP, InEdge, NodeLoop

__all__ = ["CONTROL", "RESTART_SEQ_GAP", "InEdge", "NodeLoop", "StopRun"]
