"""Worker processes on a worker daemon (``retriever-worker``, daemon/), here or on another machine.

    coordinator                                          daemon <name>
      query ctl/<name>  prepare {run, spec, nodes}  ──▶   checks each node's class (allowlist), keeps the spec
      query ctl/<name>  spawn {run, node, mode}     ──▶   starts that node's worker process: {pid, key}
                        spawn {run, node, group}    ──▶   ... or the one process of a group of flows
      query ctl/<name>  signal {run, pid, signal}   ──▶   signals one (SIGUSR1: its stacks; SIGKILL)
      query ctl/<name>  usage {run}                 ──▶   the CPU seconds of its live processes: {cpu_s}
      query ctl/<name>  end {run}                   ──▶   stops what is left of the run, forgets it
      subscriber workers/<name>/events  ◀── put  exit {run, node, pid, code} · output {run, node, stream, lines},
                                                 sealed with the run's key (the prepare reply's) and a counter (seal.py)

A remote worker process answers the coordinator as a local one does (host.WorkerProcess): its
exit code arrives as an ``exit`` event, or, when the daemon itself is lost (its liveliness token
went), every process of it counts as killed (:meth:`RemoteHost.lost`).

Every request but ``info`` is sealed with a key derived from the deployment secret (seal.py
RequestSealer), which a daemon with a secret checks, taking each once: a holder of the namespace's
passwords alone cannot have a daemon prepare or start anything, nor replay what it captured.
A query reaches every queryable on its key, an insider's too (one holding the namespace's
secret), so nothing secret goes in one: the key a process signs with (origin.py) is made by the
daemon and comes back in its reply, which Zenoh routes to the querier alone. And since an insider
may answer too, the coordinator takes answers only from the session it learned the daemon by
(``zid``: the replier of its ``info`` at discovery, daemon.describe). An insider may put on the
daemon's events key too: the daemon signs each event with a key it made for the run and answered
in its prepare reply, and the coordinator takes no other (a forged ``exit`` would count a live
process dead).
"""

from __future__ import annotations

import signal
import subprocess
import threading
import time
from collections.abc import Sequence
import zenoh

from ...errors import AccessError, BackendError
from .access import daemon_control_key, secret_bytes
from .host import Host
from .hub import weak_callback
from .protocol import (DAEMON_EVENT, SEALED_OPS, ControlOpener, EndRequest, PrepareRequest, ProcessExit, Record,
                       RequestSealer, RunSpec, SignalRequest, SpawnRequest, UsageRequest, decode_reply, error_message)
from .wire import KeySpace, WireError

#: how long the coordinator waits for a daemon to answer a request (a spawn forks a process)
REQUEST_TIMEOUT_S = 10.0
#: how often, and how far apart, a prepare is asked again of a daemon that has not yet seen the
#: coordinator's liveliness token (declared just before: it travels in milliseconds)
PREPARE_TRIES = 20
PREPARE_AGAIN_S = 0.1
#: the exit code of a process whose daemon was lost: as if SIGKILLed
LOST_CODE = -signal.SIGKILL


class RemoteProcess:
    """A node's worker process, a child of a daemon: what the coordinator knows of it."""

    def __init__(self, host: RemoteHost, node: str, pid: int, key: bytes):
        self.host, self.node, self.pid, self.key = host, node, pid, key
        self.returncode: int | None = None
        self._exited = threading.Event()
        self._confirmed = threading.Event()

    @property
    def exit_confirmed(self) -> bool:
        """Its daemon said it exited; one whose daemon was lost has a returncode (as if killed),
        yet may still run: the coordinator seals control for it until this (coordinator/processes.py)."""
        return self._confirmed.is_set()

    def wait_confirmed(self, timeout: float | None = None) -> bool:
        """Wait until its daemon says it exited (``exit_confirmed``); whether it did in time."""
        return self._confirmed.wait(timeout)

    def poll(self) -> int | None:
        return self.returncode

    def wait(self, timeout: float | None = None) -> int:
        if not self._exited.wait(timeout):
            raise subprocess.TimeoutExpired(f"{self.host.name}:{self.pid}", timeout or 0.0)
        return self.returncode

    def send_signal(self, sig: int) -> None:
        if self.returncode is None:
            try:
                self.host.request(SignalRequest(run=self.host.run, pid=self.pid, signal=int(sig)))
            except BackendError:  # it exited meanwhile, or its daemon is gone: its exit event says so
                pass

    def kill(self) -> None:
        self.send_signal(signal.SIGKILL)

    def exited(self, code: int, confirmed: bool = True) -> None:
        """It ended with ``code``: its daemon said so (``confirmed``), or its daemon was lost."""
        if confirmed:
            self._confirmed.set()
        if self.returncode is None:
            self.returncode = code
            self._exited.set()


class RemoteHost(Host):
    """The worker daemon ``name``, for one run of the coordinator's session; ``zid``: its
    session's Zenoh id, the only replier whose answers are taken; ``secret``: the deployment's
    (bytes or its file; None: --insecure), with which every request but info is sealed (seal.py)."""

    def __init__(self, session: zenoh.Session, keys: KeySpace, name: str, run: str, zid: str, secret=None):
        super().__init__()
        self.session, self.keys, self.name, self.run, self.zid = session, keys, name, run, zid
        try:
            self.sealer = (RequestSealer(daemon_control_key(secret_bytes(secret), keys.namespace))
                           if secret is not None else None)
        except AccessError as e:
            raise BackendError(str(e)) from None
        self.processes: dict[int, RemoteProcess] = {}
        self.garbage = 0  # events on its key that were not its daemon's
        # opens its events with the run's key from the prepare reply, each once (seal.py)
        self.events: ControlOpener | None = None
        self._events = session.declare_subscriber(keys.worker_events(name), weak_callback(self._event))

    # -- requests ------------------------------------------------------------------------------
    def request(self, request: Record) -> Record:
        """Ask the daemon; its reply (exact), or a BackendError saying what it answered."""
        op, payload, selector = request.NAME, request.encode(), self.keys.ctl(self.name)
        seal = self.sealer.seal(selector, payload) if self.sealer is not None and op in SEALED_OPS else None
        replies = self.session.get(selector, payload=payload, attachment=seal, timeout=REQUEST_TIMEOUT_S,
                                   consolidation=zenoh.ConsolidationMode.NONE)  # one answer may not hide another
        for reply in replies:  # the first of the daemon's: a silent queryable of an insider's does not delay it
            if reply.replier_id is None or str(reply.replier_id) != self.zid:
                continue  # an insider's answer (or Zenoh's own, when the query timed out)
            if reply.ok is None:
                message = error_message(reply.err.payload.to_bytes())
                if message is None:  # an error reply that says nothing: no answer
                    break
                raise BackendError(f"worker '{self.name}' refused {op}: {message}")
            try:
                return decode_reply(reply.ok.payload.to_bytes(), op)
            except WireError as e:
                raise BackendError(f"worker '{self.name}' answered {op} with garbage: {e}") from None
        raise BackendError(f"worker '{self.name}' did not answer {op} within {REQUEST_TIMEOUT_S:g} s"
                           "\n    hint: is it still up? `retriever workers` lists the workers that are")

    def prepare(self, spec: RunSpec, nodes: Sequence[str]) -> list[str]:
        """Hand the daemon the run's spec for ``nodes`` (RunSpec.for_remote); it refuses what it
        will not run, and says what it runs with a warning (code that differs from the
        coordinator's, --code-mismatch warn): those warnings. It takes a run only while the
        coordinator's liveliness token is up, which it may not have seen yet. The spec is read
        here as the daemon will read it: what its decoder refuses (an argument past
        MAX_PATH_CHARS) is a WireError here, before any request."""
        spec = RunSpec.from_fields(spec.to_fields(), "the run's spec")
        for attempt in range(PREPARE_TRIES):
            try:
                reply = self.request(PrepareRequest(run=self.run, spec=spec, nodes=tuple(nodes)))
                self.events = ControlOpener(reply.key)
                return list(reply.warnings)
            except BackendError as e:
                if "liveliness token" not in str(e) or attempt == PREPARE_TRIES - 1:
                    raise
                time.sleep(PREPARE_AGAIN_S)

    def spawn(self, node: str, mode: Sequence[str] = (), key: bytes | None = None) -> tuple[RemoteProcess, bytes]:
        """(``key``: unused; the daemon makes its process's key, and answers it.)"""
        reply = self.request(SpawnRequest(run=self.run, node=node, mode=tuple(mode)))
        proc = self.processes[reply.pid] = RemoteProcess(self, node, reply.pid, reply.key)
        return proc, reply.key

    def spawn_group(self, name: str, nodes: list[str], key: bytes) -> tuple[RemoteProcess, bytes]:
        """The one process of the group ``name`` (``key``: unused, as for :meth:`spawn`); what it
        prints is each of its ``nodes``' output."""
        reply = self.request(SpawnRequest(run=self.run, node=name, mode=(), group=True))
        proc = self.processes[reply.pid] = RemoteProcess(self, name, reply.pid, reply.key)
        self.share_output(name, nodes)
        return proc, reply.key

    def usage(self) -> dict[str, float]:
        """The CPU seconds each live process of the run used so far, by node (BackendError if
        the daemon did not say)."""
        return self.request(UsageRequest(run=self.run)).cpu_s

    def end(self) -> None:
        """Ask the daemon to stop what is left of the run and forget it (best effort)."""
        try:
            self.request(EndRequest(run=self.run))
        except BackendError:
            pass

    def close(self) -> None:
        self._events.undeclare()

    # -- what the daemon tells ---------------------------------------------------------------
    def lost(self) -> None:
        """The daemon is gone (its liveliness token went): its processes are as good as killed."""
        self.alive = False
        for proc in list(self.processes.values()):
            proc.exited(LOST_CODE, confirmed=False)

    def _event(self, sample: zenoh.Sample) -> None:
        payload = sample.payload.to_bytes()
        try:
            if self.events is None:
                raise WireError("an event before the daemon answered the run's key")
            self.events.open(str(sample.key_expr), payload, sample.attachment)
        except WireError:
            self.garbage += 1  # not the daemon's for this run (an insider's, or another run's), or a replay
            return
        try:
            event = DAEMON_EVENT.decode(payload)
        except WireError:
            self.garbage += 1
            return
        if event.run != self.run:
            return  # another run's (the daemon serves one at a time; a late event of the last one)
        if isinstance(event, ProcessExit):
            proc = self.processes.get(event.pid)
            if proc is None:  # no process the coordinator started there
                self.garbage += 1
                return
            proc.exited(event.code)
            return
        output = self.output(event.node)
        for line in event.lines:
            output.feed(event.stream, line)
