"""What worker processes print, on the coordinator's own stdout and stderr.

A flow's ``print`` runs in its worker process. The coordinator reads each worker's stdout and
stderr through pipes, from a thread per stream, and writes every line to its own stream of the
same name prefixed with the node (``[camera] warming up``), as dora and ROS launch files do. It
keeps the last lines of each stderr for its error messages: a crashed worker's traceback, a stuck
worker's stacks.
"""

from __future__ import annotations

import subprocess
import sys
import threading
import time
from collections import deque
from collections.abc import Callable

from .protocol import Stream

#: one line at a time on the coordinator's streams, whichever worker it comes from
_WRITING = threading.Lock()


def write_line(stream, line: str) -> None:
    """Write ``line`` to ``stream`` whole: no other line the workers' output writes comes between
    its parts. Nothing if the stream is closed or gone."""
    with _WRITING:
        try:
            stream.write(f"{line}\n")
            stream.flush()
        except (OSError, ValueError, AttributeError):
            pass


class WorkerOutput:
    """The output of one node's worker processes (a restarted flow gets a new process)."""

    def __init__(self, node: str, keep: int = 200):
        self.node = node
        self.stderr_lines = 0  # how many lines its stderr has had
        self._tail: deque[str] = deque(maxlen=keep)
        self._pumps: list[threading.Thread] = []
        #: whether its stderr lines go on to the coordinator's stderr; off, they only go to the
        #: tail (stacks dumped for an error message, which shows them: printed once)
        self.forwarding = True

    def attach(self, proc: subprocess.Popen) -> None:
        """Forward this process's stdout and stderr (both ``subprocess.PIPE``) until it closes them."""
        self._pumps = [p for p in self._pumps if p.is_alive()]
        for pipe, stream in ((proc.stdout, Stream.STDOUT), (proc.stderr, Stream.STDERR)):
            pump = threading.Thread(target=self._pump, args=(pipe, stream), daemon=True,
                                    name=f"retriever-{stream}-{self.node}")
            pump.start()
            self._pumps.append(pump)

    def attach_fifos(self, paths: dict[Stream, str], noise: Callable[[str], bool] | None = None) -> None:
        """Forward what a process that is not this one's child writes to these named pipes
        (``{Stream.STDOUT: path, Stream.STDERR: path}``), from when it opens them until it closes
        them; lines that ``noise`` says are noise are dropped."""
        for stream, path in paths.items():
            pump = threading.Thread(target=self._pump_fifo, args=(path, stream, noise), daemon=True,
                                    name=f"retriever-{stream}-{self.node}")
            pump.start()
            self._pumps.append(pump)

    def _pump_fifo(self, path: str, stream: Stream, noise: Callable[[str], bool] | None) -> None:
        try:
            pipe = open(path, "rb")  # blocks until the writer opens it (or close_fifos does)
        except OSError:
            return
        self._pump(pipe, stream, noise)

    def _pump(self, pipe, stream: Stream, noise: Callable[[str], bool] | None = None) -> None:
        with pipe:
            for raw in iter(pipe.readline, b""):
                line = raw.decode(errors="replace").rstrip("\r\n")
                if noise is None or not noise(line):
                    self.feed(stream, line)

    def feed(self, stream: Stream, line: str) -> None:
        """One line the node's process wrote to ``stream``: kept if stderr, and written to the
        coordinator's stream of that name, prefixed with the node."""
        if stream == Stream.STDERR:
            self._tail.append(line)
            self.stderr_lines += 1
            if not self.forwarding:
                return
        write_line(getattr(sys, stream), f"[{self.node}] {line}")  # looked up per line: pytest and rich replace it

    def keep(self, line: str) -> None:
        """Keep ``line`` in the tail that an error about this node shows, beside its stderr (what
        another program, such as dora, said of the node's process)."""
        self._tail.append(line)

    def drain(self, timeout: float = 1.0) -> None:
        """Wait (at most ``timeout``) until an exited process's last lines are read."""
        give_up = time.monotonic() + timeout
        for pump in self._pumps:
            pump.join(max(0.0, give_up - time.monotonic()))

    def settle(self, since: int, timeout: float) -> None:
        """Wait until stderr has had lines beyond ``since`` and then none for 0.1 s, at most
        ``timeout``: a stack dump written by a signal handler, read in full."""
        give_up = time.monotonic() + timeout
        while self.stderr_lines == since and time.monotonic() < give_up:
            time.sleep(0.02)
        seen = -1
        while seen != self.stderr_lines and time.monotonic() < give_up:
            seen = self.stderr_lines
            time.sleep(0.1)

    def tail(self, lines: int = 15) -> str:
        """The last lines of its stderr, indented for an error message."""
        text = list(self._tail)[-lines:]
        while text and not text[-1].strip():
            text.pop()
        return "\n".join("        " + line for line in text)
