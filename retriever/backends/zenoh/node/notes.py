"""What a node counts over its run, and what its next step record must tell."""

from __future__ import annotations

import sys
from collections import Counter
from typing import Any


class Notes:
    """``counts``: garbage, late, incomplete, overrun, deadline_miss, report_waits, … (the worker
    sends them with its last status). ``detail``: late events, skipped ticks and restarts not yet
    told; the next step record takes it whole."""

    def __init__(self, node_id: str):
        self.id = node_id
        self.counts: Counter = Counter()
        self.detail: dict[str, Any] = {}

    def garbage(self, key: Any, error: Exception) -> None:
        """A message refused (never applied): counted, and the first few told on stderr."""
        self.counts["garbage"] += 1
        if self.counts["garbage"] <= 3:
            print(f"retriever worker {self.id}: dropped a message on {key}: {error}", file=sys.stderr, flush=True)
