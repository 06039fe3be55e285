"""The coordinator's one way to speak to the run's workers: control messages on ``ctl/run``.

Every handler that tells the workers something (``start``, ``grant``, ``stop``, ``have``,
``restarted``...) puts it through one :class:`RunControl`; a test or a benchmark that needs to see
or time those puts wraps :meth:`RunControl.put` on the coordinator's ``control``.
"""

from __future__ import annotations

from ..wire import RELIABLE, KeySpace, WireEncoder


class RunControl:
    """Puts control messages on the run's control key through the hub's session."""

    def __init__(self, hub, keys: KeySpace):
        self.hub, self.keys = hub, keys
        self.encoder = WireEncoder()

    def put(self, op: str, args: dict) -> None:
        self.hub.put(self.keys.run_control(), self.encoder.control(op, args), congestion_control=RELIABLE)
