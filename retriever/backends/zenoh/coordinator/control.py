"""The coordinator's one way to speak to the run's workers: control messages on ``ctl/run``.

Every handler that tells the workers something (``start``, ``grant``, ``stop``, ``have``,
``restarted``...) puts it through one :class:`RunControl`; a test or a benchmark that needs to see
or time those puts wraps :meth:`RunControl.put` on the coordinator's ``control``. Each put, and
each answer to a worker's question (``start``, ``finished``), is sealed for the run's processes
(protocol/seal.py): a worker takes no control message that the coordinator did not make.
"""

from __future__ import annotations

from ..protocol import ControlSigner, Record
from ..wire import RELIABLE, KeySpace


class RunControl:
    """Puts control messages on the run's control key through the hub's session, sealed by
    ``signer`` (which holds the key of every process the coordinator started)."""

    def __init__(self, hub, keys: KeySpace):
        self.hub, self.keys = hub, keys
        self.signer = ControlSigner()

    def put(self, record: Record) -> None:
        """Put ``record`` (one of protocol.RUN_CONTROL's) on ctl/run, sealed."""
        key_expr, payload = self.keys.run_control(), record.encode()
        self.hub.put(key_expr, payload, congestion_control=RELIABLE, attachment=self.signer.seal(key_expr, payload))

    def reply(self, query, key_expr: str, record: Record) -> None:
        """Answer a worker's ``query`` on ``key_expr`` with ``record``, sealed over the nonce it asked with."""
        payload = record.encode()
        nonce = None if query.attachment is None else query.attachment.to_bytes()
        query.reply(key_expr, payload, attachment=self.signer.seal_reply(key_expr, payload, nonce))
