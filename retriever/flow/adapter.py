"""Sync policies (edge adapters), at the path the paper imports them from."""

from ..sync import MISSING, ActionChunking, Exact, Latest, LatestDistinct, Queue, SyncPolicy, Window

__all__ = sorted(["MISSING", "ActionChunking", "Exact", "Latest", "LatestDistinct", "Queue", "SyncPolicy", "Window"])
