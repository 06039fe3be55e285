"""The coordinator's inbox: the signed statuses and reports of the run, one handler per kind.

Zenoh's thread checks who signed each message (origin.py) and queues it; the coordinator's
thread takes them here and only dispatches: a report to :class:`ReportIngest`, a status to
:class:`StatusMachine`. Nothing else of the run changes the coordinator's record.
"""

from __future__ import annotations

import queue

from ..wire import KeySpace
from .reports import ReportIngest
from .statuses import StatusMachine


class Inbox:
    """Messages on the run's status keys, taken on the coordinator's thread."""

    def __init__(self, keys: KeySpace, reports: ReportIngest, statuses: StatusMachine):
        self.queue: queue.SimpleQueue = queue.SimpleQueue()
        self.report_prefix = keys.status("report") + "/"
        self.reports, self.statuses = reports, statuses

    def put(self, item: tuple) -> None:
        """Queue ``(key, data, sender)``: a message, and the process of its node that signed it."""
        self.queue.put(item)

    def handle(self, item: tuple) -> None:
        """A status or report, with the process of its node that signed it (origin.py)."""
        key, data, sender = item
        if key.startswith(self.report_prefix):
            self.reports.take(key, data, sender)
        else:
            self.statuses.take(key, data, sender)

    def take(self, timeout: float) -> bool:
        """Handle what came, waiting up to ``timeout`` for the first; whether anything came."""
        try:
            self.handle(self.queue.get(timeout=timeout))
        except queue.Empty:
            return False
        self.drain()
        return True

    def take_one(self, timeout: float) -> None:
        """Handle the next message, if one comes within ``timeout``."""
        try:
            self.handle(self.queue.get(timeout=timeout))
        except queue.Empty:
            pass

    def drain(self) -> None:
        """Handle every message queued."""
        while True:
            try:
                self.handle(self.queue.get_nowait())
            except queue.Empty:
                return
