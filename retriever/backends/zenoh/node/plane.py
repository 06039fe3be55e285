"""A node's control plane: what it declares on the run's session whatever carries its events
(transport.py). It hears the run's control (``ctl/run``: opened with this process's key and
decoded, then queued for the loop, control.obey) and answers its consumers' progress queries
(``progress/<node>``: its frontier and the last seq sent on each port)."""

from __future__ import annotations

import zenoh

from ..hub import weak_callback
from ..wire import WireEncoder
from .control import opened_control


class ControlPlane:
    """The control subscriber and progress queryable of ``loop`` (a NodeLoop), in ``declared``
    (one list, kept: the loop hands it out), until ``undeclare``. Zenoh holds its callbacks
    weakly, so they never keep the loop alive."""

    def __init__(self, loop):
        self.loop = loop
        self.declared: list = []

    def listen(self) -> None:
        """Hear the run's control."""
        self.declared.append(self._subscriber())

    def answer(self) -> None:
        """Answer progress queries."""
        self.declared.append(self._queryable())

    def redeclare(self) -> None:
        """Declare each again, then drop the old ones (NodeLoop.redeclare says when and why)."""
        old = list(self.declared)
        self.declared.clear()
        for d in old:
            self.declared.append(self._queryable() if isinstance(d, zenoh.Queryable) else self._subscriber())
        for d in old:
            d.undeclare()

    def undeclare(self) -> None:
        for d in self.declared:
            d.undeclare()
        self.declared.clear()

    def _subscriber(self) -> zenoh.Subscriber:
        loop = self.loop
        return loop.session.declare_subscriber(loop.keys.run_control(), weak_callback(self._control_in))

    def _queryable(self) -> zenoh.Queryable:
        loop = self.loop
        return loop.session.declare_queryable(loop.keys.progress(loop.id), weak_callback(self._answer_progress))

    def _control_in(self, sample) -> None:
        """A put on ctl/run (on Zenoh's thread), queued: see control.opened_control."""
        self.loop.inbox.put(opened_control(self.loop.opener, sample))

    def _answer_progress(self, query: zenoh.Query) -> None:
        loop = self.loop
        frontier = loop.outputs.frontier()  # first: the seqs read after it can only be later ones
        query.reply(loop.keys.progress(loop.id), WireEncoder().progress(frontier, loop.id, dict(loop.sent)))
