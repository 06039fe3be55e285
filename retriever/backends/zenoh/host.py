"""Where a run's worker processes run: the coordinator starts, watches and stops them through a host.

    Host           starts a node's worker process (``spawn``), keeps what it prints (``output``)
    └── LocalHost  this machine: children of the coordinator, their output read through pipes

A worker process is to the coordinator what ``subprocess.Popen`` is (:class:`WorkerProcess`):
``pid``, ``poll()``, ``wait(timeout)``, ``send_signal()``, ``kill()``. The coordinator's logic —
readiness, T0, reports, the log, restarts, lost processes — does not care which host a process
runs on (issue 18: the embedded run is a deployment with one local host).
"""

from __future__ import annotations

import os
import subprocess
from abc import ABC, abstractmethod
from collections.abc import Sequence
from pathlib import Path
from typing import Protocol

from .command import GROUP_MODULE, WORKER_MODULE, worker_command
from .origin import KEY_FD_ENV, key_pipe
from .output import WorkerOutput


class WorkerProcess(Protocol):
    """One node's worker process, as the coordinator sees it (``subprocess.Popen`` is one)."""

    pid: int

    def poll(self) -> int | None: ...

    def wait(self, timeout: float | None = None) -> int: ...  # subprocess.TimeoutExpired past it

    def send_signal(self, sig: int) -> None: ...

    def kill(self) -> None: ...


class Host(ABC):
    """Starts worker processes of one run somewhere, and keeps what each node's processes print."""

    #: a short name for messages (a worker daemon's name)
    name = "this machine"

    def __init__(self) -> None:
        self._outputs: dict[str, WorkerOutput] = {}
        #: False once the host is known lost (a worker daemon's liveliness token went)
        self.alive = True

    @abstractmethod
    def spawn(self, node: str, mode: Sequence[str] = (), key: bytes | None = None) -> tuple[WorkerProcess, bytes]:
        """Start a worker process for ``node``; ``mode``: its extra arguments (``--join T0 END``...);
        ``key``: the key it signs its statuses and reports with (origin.py), given to it alone.
        The process, and the key it signs with: ``key``, or one the host made (a worker daemon)."""

    def output(self, node: str) -> WorkerOutput:
        """What ``node``'s worker processes printed (all of them: a restart makes a new one)."""
        output = self._outputs.get(node)
        if output is None:
            output = self._outputs[node] = WorkerOutput(node)
        return output

    def share_output(self, name: str, nodes: list[str]) -> None:
        """What the process ``name`` prints is what each of its ``nodes``' first process printed
        (a group's process: configure(process=))."""
        for node in nodes:
            self._outputs[node] = self.output(name)

    def spawn_group(self, name: str, nodes: list[str], key: bytes) -> tuple[WorkerProcess, bytes]:
        """Start the process of the group ``name`` of ``nodes`` (Hosting.shares_processes)."""
        raise NotImplementedError(f"{self.name} starts no process of a group of flows")

    def outputs(self) -> list[WorkerOutput]:
        return list({id(o): o for o in self._outputs.values()}.values())  # (a group's, once)


class LocalHost(Host):
    """This machine: each worker process is a child of the coordinator, in a session of its own
    (a Ctrl-C at the terminal reaches the coordinator only, which stops them), reading the run's
    spec from the coordinator's run directory."""

    def __init__(self, spec_path: Path):
        super().__init__()
        self.spec_path = spec_path

    def spawn(self, node: str, mode: Sequence[str] = (), key: bytes | None = None,
              module: str = WORKER_MODULE) -> tuple[subprocess.Popen, bytes]:
        cmd = worker_command(str(self.spec_path), node, mode, module=module)
        pipe = key_pipe(key) if key is not None else None
        try:
            proc = subprocess.Popen(cmd, stdin=subprocess.DEVNULL, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                                    start_new_session=True, pass_fds=() if pipe is None else (pipe,),
                                    env=None if pipe is None else {**os.environ, KEY_FD_ENV: str(pipe)})
        finally:
            if pipe is not None:
                os.close(pipe)
        self.output(node).attach(proc)
        return proc, key

    def spawn_group(self, name: str, nodes: list[str], key: bytes) -> tuple[subprocess.Popen, bytes]:
        proc, key = self.spawn(name, (), key, module=GROUP_MODULE)
        self.share_output(name, nodes)
        return proc, key
