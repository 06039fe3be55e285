"""Where a dora run's worker processes run: ``dora run`` starts them all, from the dataflow.

    DoraHost         starts ``dora run dataflow.yml`` (one dora node per process: a flow's, or a
                     group's) in a directory of
                     its own (dora writes its logs there), and reads dora's errors; each worker
                     writes its stdout and stderr to named pipes of the run's directory, which the
                     coordinator forwards prefixed with the node, as on the zenoh backend
    DoraNodeProcess  one node's worker process, as the coordinator sees it (``pid``, ``poll()``...):
                     dora's child, not the coordinator's; it says its pid and, at its end, its exit
                     code in files of the run's directory (node.py)
"""

from __future__ import annotations

import contextlib
import json
import os
import re
import shutil
import signal
import subprocess
import sys
import threading
import time
from collections import deque
from collections.abc import Sequence
from pathlib import Path

from ...errors import BackendError
from ..zenoh.host import Host
from ..zenoh.output import write_line
from ..zenoh.protocol import Stream

#: a node whose process is gone without saying how it ended (killed, or a crash): its exit code
LOST = 255
#: how long ``dora run`` has to end once every node ended, before it is stopped
DORA_EXIT_S = 5.0
#: how long after a node's process is seen gone, without its exit file, dora has to say how it
#: ended (``exited because of signal SIGKILL``), before it counts as LOST
DORA_SAYS_S = 1.0
#: how long ``dora run`` has to end when interrupted before the start, before it is SIGKILLed
INTERRUPT_S = 0.5
#: how often the coordinator looks for new lines in dora's output file
FOLLOW_S = 0.05
_KILLED_BY = re.compile(r"exited because of signal (SIG[A-Z0-9]+)")
_EXITED_WITH = re.compile(r"exited with code (\d+)")


def dora_command() -> str:
    """The ``dora`` command: next to this interpreter (a venv's), else on PATH."""
    beside = Path(sys.executable).parent / "dora"
    found = str(beside) if beside.is_file() else shutil.which("dora")
    if found is None:
        raise BackendError("the dora backend needs dora's runtime, which is not installed\n"
                           "    hint: pip install 'retriever-robotics[dora]' (the dora-rs and dora-rs-cli packages)")
    try:
        import dora  # noqa: F401  (the workers' node API)
    except ImportError:
        raise BackendError("the dora backend needs dora's Python node API (the dora-rs package), which is not "
                           "installed\n    hint: pip install 'retriever-robotics[dora]'") from None
    return found


def dora_diagnostic(line: str) -> bool:
    """Whether a worker's output line is a diagnostic of dora's node API: dora 1.1 logs two
    warnings, as JSON lines on the node's output, for each of a run's first messages over 4 KiB
    ("dora-rs/dora#2742 diagnostic"), and reads no setting that turns them off (neither RUST_LOG
    nor the dataflow's min_log_level did). They say nothing about the run: dropped."""
    return line.startswith("{") and "(dora-rs/dora#2742 diagnostic)" in line


class DoraHost(Host):
    """This machine, through ``dora run``: started once with every node of the run."""

    name = "dora"

    def __init__(self, run_dir: Path, dataflow: Path, processes: dict[str, str]):
        """``processes``: each worker process's dora node id, by the process's name (a node's id,
        or a group's name: DoraNames.processes)."""
        super().__init__()
        self.dir = run_dir  # the workers' pid, exit and output files
        self.dora_dir = dataflow.parent  # dora's: its logs grow there, on disk
        self.by_dora_id = {dora_id: name for name, dora_id in processes.items()}
        self.tail: deque[str] = deque(maxlen=50)  # dora's own errors
        self.signalled: dict[str, int] = {}  # process -> how it ended, as dora said (-signal or code)
        self.fifos: list[str] = []
        self.interrupted = False  # ended by interrupt(): what dora says of its nodes' ends is ours
        for nid, dora_id in processes.items():
            paths = {stream: str(run_dir / f"{dora_id}.{stream}") for stream in Stream}
            for path in paths.values():
                os.mkfifo(path, 0o600)
            self.fifos += paths.values()
            self.output(nid).attach_fifos(paths, noise=dora_diagnostic)
        # --log-level error: what a worker prints comes through its named pipes, not dora's log
        # (which, at its default level, also carries a warning per message on the daemon's route:
        # read a line at a time, they held dora's daemon back for a second at a run's start).
        # It does not die with the coordinator: dora SIGKILLs its nodes as it exits, before they
        # could remove the run's directories; the nodes watch the coordinator, remove them and exit,
        # and dora run ends with its last node (zenoh/worker/process.py, _watch_parent).
        # Its output goes to a file the coordinator follows, not a pipe: a dora run that writes to
        # a pipe whose reader died (a coordinator SIGKILLed as it started) ends at once, and
        # SIGKILLs its nodes before they could remove the run's directories.
        self.output_file = self.dora_dir / "dora.out"
        with open(self.output_file, "wb") as output:
            self.proc = subprocess.Popen([dora_command(), "run", str(dataflow), "--log-format", "json",
                                          "--log-level", "error"],
                                         cwd=self.dora_dir, stdin=subprocess.DEVNULL, stdout=output,
                                         stderr=subprocess.STDOUT, start_new_session=True)
        self._pump = threading.Thread(target=self._read, daemon=True, name="retriever-dora-output")
        self._pump.start()

    def spawn(self, node: str, mode: Sequence[str] = (), key: bytes | None = None) -> tuple["DoraNodeProcess", bytes]:
        """(``key``: the one the node's process finds in the run's spec, DoraCoordinator.place.)"""
        if mode:  # a restart's new process: dora started the dataflow's processes once
            raise BackendError(f"the dora backend cannot start another process for '{node}'")
        return DoraNodeProcess(node, self), key

    def spawn_group(self, name: str, nodes: list[str], key: bytes) -> tuple["DoraNodeProcess", bytes]:
        """The process of the group ``name`` (one dora node): what it prints is each member's."""
        self.share_output(name, nodes)
        return DoraNodeProcess(name, self), key

    def _read(self) -> None:
        """Follows dora's output file until dora run ended and its last line is read."""
        with open(self.output_file, "rb") as output:
            partial = b""
            while True:
                ended = self.proc.poll() is not None  # before the read: nothing comes after it
                partial += output.read()
                *lines, partial = partial.split(b"\n")
                for raw in lines:
                    self._line(raw.decode(errors="replace").rstrip("\r"))
                if ended:
                    break
                time.sleep(FOLLOW_S)
            if partial:
                self._line(partial.decode(errors="replace").rstrip("\r"))

    def _line(self, line: str) -> None:
        try:
            record = json.loads(line)
            level, message, dora_id = record["level"], str(record["message"]), record.get("node_id")
        except (ValueError, KeyError, TypeError):  # not one of its JSON lines (its last words are plain text)
            self.tail.append(line)
            return
        node = self.by_dora_id.get(dora_id)
        if level not in ("ERROR", "WARN"):
            return
        text = f"{dora_id or 'dora'}: {message}"
        self.tail.append(text)  # kept for the error that names a failed node
        if node is not None:
            self.output(node).keep(f"(dora) {message}")
            killed, code = _KILLED_BY.search(message), _EXITED_WITH.search(message)
            if killed and hasattr(signal, killed.group(1)):
                self.signalled[node] = -getattr(signal, killed.group(1))
            elif code:
                self.signalled[node] = int(code.group(1))
        if self.interrupted:
            return
        write_line(sys.stderr, f"[dora] {text}")

    def said_all(self) -> bool:
        """Whether dora run ended and every line it wrote was read: it has no more to say."""
        return self.proc.poll() is not None and not self._pump.is_alive()

    def drain(self, timeout: float = 1.0) -> None:
        self._pump.join(timeout)

    def close_fifos(self) -> None:
        """Let go of the named pipes no worker opened (it never started): their readers end."""
        for path in self.fifos:
            with contextlib.suppress(OSError):
                os.close(os.open(path, os.O_WRONLY | os.O_NONBLOCK))

    def interrupt(self) -> None:
        """Before the run's start (Ctrl-C, a failed setup), once the workers it started had their
        chance to stop: no worker has anything to send, so ``dora run`` is ended, and takes its
        nodes with it (it SIGKILLs them as it exits); what it says of their ends, caused here, is
        kept from the user's terminal."""
        self.interrupted = True
        with contextlib.suppress(ProcessLookupError):
            os.kill(self.proc.pid, signal.SIGTERM)
        # it then asks its nodes to stop, and gives those that do not (not yet started) seconds
        self._killed_unless_ended(INTERRUPT_S)
        self.drain()

    def stop(self) -> None:
        """``dora run`` ends by itself once every node ended; else (a node stuck, or never
        started) it is told to stop as Ctrl-C would, then killed with whatever it started."""
        try:
            self.proc.wait(timeout=DORA_EXIT_S)
        except subprocess.TimeoutExpired:
            with contextlib.suppress(ProcessLookupError):
                os.killpg(self.proc.pid, signal.SIGINT)
            self._killed_unless_ended(DORA_EXIT_S)
        self.drain()
        self.close_fifos()
        shutil.rmtree(self.dora_dir, ignore_errors=True)

    def _killed_unless_ended(self, timeout: float) -> None:
        """Wait ``timeout`` s for ``dora run`` to end; then SIGKILL it with whatever it started."""
        try:
            self.proc.wait(timeout=timeout)
        except subprocess.TimeoutExpired:
            with contextlib.suppress(ProcessLookupError):
                os.killpg(self.proc.pid, signal.SIGKILL)
            self.proc.wait()


class DoraNodeProcess:
    """One worker process under dora (a node's, or a group's, by its name), as ``subprocess.Popen``
    would say of it."""

    def __init__(self, node: str, host: DoraHost):
        self.node, self.host = node, host
        self._pid: int | None = None
        self.returncode: int | None = None
        self._gone_since: float | None = None

    @property
    def pid(self) -> int:
        """Its pid, once it said it (-1 before)."""
        if self._pid is None:
            with contextlib.suppress(OSError, ValueError):
                self._pid = int((self.host.dir / f"{self.node}.pid").read_text())
        return -1 if self._pid is None else self._pid

    def poll(self) -> int | None:
        if self.returncode is not None:
            return self.returncode
        pid = self.pid
        if pid < 0:  # not started yet: unless dora is gone, which then never will
            code = self.host.proc.poll()
            if code is not None:
                self.returncode = code or LOST
            return self.returncode
        if pid_alive(pid):
            return None
        try:
            self.returncode = int((self.host.dir / f"{self.node}.exit").read_text())
        except (OSError, ValueError):  # it did not get to say: dora says which signal ended it
            said = self.host.signalled.get(self.node)
            if said is not None:
                self.returncode = said
            elif not self.host.said_all() and (self._gone_since is None
                                               or time.monotonic() - self._gone_since < DORA_SAYS_S):
                self._gone_since = self._gone_since or time.monotonic()
                return None
            else:
                self.returncode = LOST
        return self.returncode

    def wait(self, timeout: float | None = None) -> int:
        give_up = None if timeout is None else time.monotonic() + timeout
        while (code := self.poll()) is None:
            if give_up is not None and time.monotonic() >= give_up:
                raise subprocess.TimeoutExpired(f"dora node {self.node}", timeout)
            time.sleep(0.02)
        return code

    def send_signal(self, sig: int) -> None:
        if self.poll() is None and self.pid > 0:
            with contextlib.suppress(ProcessLookupError):
                os.kill(self.pid, sig)

    def kill(self) -> None:
        self.send_signal(signal.SIGKILL)


def pid_alive(pid: int) -> bool:
    """Whether ``pid`` runs (a zombie, which dora has yet to reap, does not)."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return False
    return stat[stat.rindex(")") + 2] not in "ZX"

