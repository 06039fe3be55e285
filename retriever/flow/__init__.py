"""The programming model at the paths the paper uses: ``from retriever.flow import Flow,
flow_io, Rate, Trigger, Pipeline, Latest`` (Listing 4). ``flow_io`` is the paper's name of ``io``."""

from ..clocks import Clock, Hybrid, Rate, Trigger
from ..sync import MISSING, ActionChunking, Exact, Latest, LatestDistinct, Queue, SyncPolicy, Window
from .core import Flow, flow_io, io
from .burst import Burst
from .types import EventStream


def __getattr__(name: str):
    if name == "Pipeline":  # imported on first use: the pipeline module imports this package
        from ..pipeline import Pipeline

        return Pipeline
    raise AttributeError(f"module 'retriever.flow' has no attribute {name!r}")

__all__ = sorted([
    "MISSING", "ActionChunking", "Burst", "Clock", "EventStream", "Exact", "Flow", "Hybrid", "Latest",
    "LatestDistinct", "Pipeline", "Queue", "Rate", "SyncPolicy", "Trigger", "Window", "flow_io", "io",
])
