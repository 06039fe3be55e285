"""The programming model at the paths the paper uses: ``from retriever.flow import Rate, Trigger``."""

from ..clocks import Clock, Hybrid, Rate, Trigger
from ..sync import MISSING, ActionChunking, Exact, Latest, LatestDistinct, Queue, SyncPolicy, Window
from ._base import Flow, io
from .types import EventStream

__all__ = sorted([
    "MISSING", "ActionChunking", "Clock", "EventStream", "Exact", "Flow", "Hybrid", "Latest",
    "LatestDistinct", "Queue", "Rate", "SyncPolicy", "Trigger", "Window", "io",
])
