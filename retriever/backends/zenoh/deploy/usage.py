"""The usage poller: each node's CPU seconds, as its worker daemon reads them, for ``retriever status``."""

from __future__ import annotations

import threading

from ....errors import BackendError
from ..coordinator.hosting import HostedRun
from .book import WorkerBook

#: how often the coordinator asks its workers for their flows' CPU time (retriever status, the live table)
USAGE_EVERY_S = 1.0


class UsagePoller:
    """From a thread of its own once started, while the run goes: each node's CPU seconds so far,
    as its worker reads them, every USAGE_EVERY_S (a worker that does not answer is skipped)."""

    def __init__(self, run: HostedRun, book: WorkerBook):
        self.run, self.book = run, book
        self._cpu: dict[str, float] = {}  # node -> CPU seconds of its process, last read
        self._stop = threading.Event()

    def start(self) -> None:
        threading.Thread(target=self._poll, name="retriever-usage", daemon=True).start()

    def stop(self) -> None:
        self._stop.set()

    def cpu(self) -> dict[str, float]:
        """Each node's CPU seconds, as last read (a copy)."""
        return dict(self._cpu)

    def _poll(self) -> None:
        while not self.run.closed() and not self._stop.wait(USAGE_EVERY_S):
            for remote in list(self.book.remotes.values()):
                try:
                    self._cpu.update(remote.usage())
                except BackendError:
                    continue
