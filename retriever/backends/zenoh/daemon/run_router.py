"""A worker daemon's router for one run (``retriever worker --router ENDPOINT --local-router``).

Through a remote router alone, two flows on one machine talk through it: every edge between them
goes out to the router and back, and stops while the machine is cut off from it. So a daemon with
``--local-router`` starts, for each run it prepares, a Zenoh router of the run's own, listening on
a free loopback port and linked to the upstream routers; the run's flows join it as clients
(runs.DaemonRuns.local_spec) in place of the remote router. Zenoh routes between routers: an edge
between two flows of this machine stays on it, an edge to another machine goes through the
upstream routers as before.

    flow ──┐                             ┌── flow (other machine)
    flow ──┴─ run router (127.0.0.1) ── upstream router ── coordinator, daemons
         this machine

The run router is a process of its own (router_process.py), with shared memory: a big message
between two flows here goes through the sender's pool, which the router maps to forward it, and
a process keeps every pool it mapped until it exits (hub.HUB_SHARED_MEMORY). In the daemon, which
outlives its runs, those pools would pile up; in a process of the run's they go with it. It is
started from the daemon's spawner thread, as the workers are, so it gets PARENT_DIED when the
daemon dies, a SIGKILL too, and stops (worker/process.py).

Who may join, as strict as at the upstream router (router.py): its dictionary holds the run's own
password alone (access.RunAccess.create with the run id, derived here from the secret, as for
peers), under the namespace's run user, so a session without that run's password gets no link:
not another run's flows, not a holder of the namespace's passwords. Its access control denies by
default (routing.access_control): the run user everything on the namespace's keys; the upstream
routers, whose user it cannot learn (Zenoh authenticates the connecting side only), by their
Zenoh ids, which the daemon's own session is linked to. Upstream it proves what the daemon
proves: the namespace's run user and password; with TLS, its certificate on ``tls/`` links. Its
own listener is plain TCP on loopback: no other machine reaches it, and a process of this one
still needs the run's password. The passwords reach it on its stdin, never its command line.

One router per run, because Zenoh reads a router's dictionary once, when the session opens. It
stops with its run (runs.DaemonRuns._end), and when the daemon stops or dies. One that ends
before (it crashed, or was killed) is told to whoever watches it (RunRouter.watch), with how it
ended and its last words.
"""

from __future__ import annotations

import collections
import json
import os
import select
import signal
import subprocess
import sys
import threading
from collections.abc import Callable
from dataclasses import dataclass

from ..access import RunAccess, TlsFiles
from ..hub import LOOPBACK, endpoint, free_port
from ..wire import WireError, check_chunk

#: what the process prints on its stdout once it is linked upstream, and nothing else
READY = "ready"
#: its exit code when it could not start (a ZError opening its session, no upstream link, bad settings)
EXIT_FAILED = 1
#: how long a run router is given to link to an upstream router: a link takes one round trip
#: and the daemon's own session is linked already, so only a router that went away meets it
UPSTREAM_LINK_S = 5.0
#: the links a run router admits: its run's flow processes on this machine
MAX_RUN_SESSIONS = 1000
#: how often it looks at its links while it waits for its upstream one
LINK_POLL_S = 0.01
#: how often its main thread wakes to look whether its daemon is gone (a signal is handled only
#: when the main thread runs; PARENT_DIED comes at once, this is for a daemon that lingers as a zombie)
PARENT_CHECK_S = 0.5
#: the kind of private folder (folders.py) of its dictionary where there is no memory file for it
ROUTER_PROCESS_FOLDER = "retriever-runrouter"


@dataclass(frozen=True)
class RouterProcessSettings:
    """What a run router's process is started with, on its stdin (router_process.py)."""

    namespace: str
    run: str
    listen: str
    upstream: tuple[str, ...]
    upstream_ids: tuple[str, ...]
    run_password: str  # the run's: the one password its dictionary holds
    upstream_password: str  # the daemon's: what the upstream routers admit
    tls: TlsFiles | None = None

    def to_json(self) -> str:
        doc = {**vars(self), "tls": vars(self.tls) if self.tls else None}
        return json.dumps(doc)

    @classmethod
    def from_json(cls, text: str) -> RouterProcessSettings:
        """The settings a daemon wrote; ValueError for anything else."""
        try:
            doc = json.loads(text)
            if not all(isinstance(doc[key], list) for key in ("upstream", "upstream_ids")):
                raise TypeError("upstream and upstream_ids are no lists")
            doc["upstream"], doc["upstream_ids"] = tuple(doc["upstream"]), tuple(doc["upstream_ids"])
            doc["tls"] = TlsFiles(**doc["tls"]) if doc.get("tls") else None
            settings = cls(**doc)
            check_chunk("namespace", settings.namespace)
        except (TypeError, KeyError, AttributeError, ValueError, RecursionError) as e:  # RecursionError: too deep
            raise ValueError(f"the run router's settings are not a daemon's: {e}") from None
        tls = (settings.tls.ca, settings.tls.cert, settings.tls.key) if settings.tls else ()
        if not all(isinstance(v, str) for v in (settings.namespace, settings.run, settings.listen,
                                                  settings.run_password, settings.upstream_password,
                                                  *settings.upstream, *settings.upstream_ids, *tls)):
            raise ValueError("the run router's settings are not a daemon's: a value that is no text")
        if any(c in settings.run_password for c in "\r\n"):  # one line of the router's dictionary
            raise ValueError("the run router's settings are not a daemon's: a password of more than one line")
        return settings


#: the module a run router's process runs
ROUTER_PROCESS_MODULE = "retriever.backends.zenoh.daemon.router_process"
#: how long a run router's process is given to start: its interpreter and imports, its session
#: and its upstream link, for which it waits UPSTREAM_LINK_S itself (1.5–2.6 s to ready when
#: linked at once, on a 2-core machine at load 10); all within the prepare it is started in,
#: which a coordinator waits 10 s for (remote.REQUEST_TIMEOUT_S)
START_S = UPSTREAM_LINK_S + 4.0
#: how long a run router's process has to close its session and exit after SIGTERM, before SIGKILL
STOP_S = 5.0
#: the last lines of what a run router's process printed on stderr, kept to say why it ended
LAST_WORDS = 20


class RunRouter:
    """One run's router process (close it), and the endpoint its flows join it at."""

    def __init__(self, run_id: str, process: subprocess.Popen, at: str):
        self.run_id, self.process, self.endpoint = run_id, process, at
        self.pid = process.pid
        self._closing = False
        self._said: collections.deque[str] = collections.deque(maxlen=LAST_WORDS)
        self._reader = threading.Thread(target=self._read_stderr, daemon=True, name=f"retriever-run-router-{run_id}")
        self._reader.start()

    def _read_stderr(self) -> None:
        with self.process.stderr as stderr:
            for line in stderr:
                self._said.append(line.rstrip("\n"))

    def last_words(self) -> str:
        """What it printed on stderr last (once it exited: all it printed, up to LAST_WORDS lines)."""
        if self.process.poll() is not None:
            self._reader.join(timeout=1.0)
        return "\n".join(self._said)

    def ended(self) -> str | None:
        """How it ended, said for the run's coordinator and the daemon's log; None while it runs
        or once close() stopped it."""
        code = self.process.poll()
        if code is None or self._closing:
            return None
        how = (f"was killed by {signal.Signals(-code).name}" if code < 0 and -code in signal.valid_signals()
               else f"exited with code {code}")
        said = self.last_words()
        return (f"run {self.run_id}: the worker's router for it (pid {self.pid}, {self.endpoint}) {how}"
                + (f": {said}" if said else "") + "; the run's flows on this machine have no link to anyone")

    def watch(self, on_end: Callable[[str], None]) -> None:
        """Call ``on_end`` with how it ended (ended()) if it ends before close() stops it."""
        def wait() -> None:
            self.process.wait()
            why = self.ended()
            if why is not None:
                on_end(why)

        threading.Thread(target=wait, daemon=True, name=f"retriever-run-router-exit-{self.run_id}").start()

    def close(self) -> None:
        """Stop it: SIGTERM, SIGKILL after STOP_S."""
        self._closing = True
        if self.process.poll() is None:
            self.process.terminate()
            try:
                self.process.wait(timeout=STOP_S)
            except subprocess.TimeoutExpired:
                self.process.kill()
                self.process.wait()
        self.process.stdout.close()
        self._reader.join(timeout=1.0)


def open_run_router(namespace: str, secret: bytes, run_id: str, upstream: tuple[str, ...], upstream_ids: list[str],
                    tls: TlsFiles | None = None, environ: dict[str, str] | None = None) -> RunRouter:
    """Start run ``run_id``'s router process and wait until it is linked upstream: on a free
    loopback port, linked to the routers at ``upstream`` (admitted by their Zenoh ids,
    ``upstream_ids``), admitting the run's password alone (see the module's docstring);
    ``environ``: its environment (None: this process's). Call it from a thread that lives as
    long as the daemon: the process dies when the thread that started it ends (PARENT_DIED).

    Its upstream link keeps Zenoh's lease, as the flows' own links to a remote router do
    (runs.DaemonRuns.local_spec: the daemon's short one closes links that are merely slow)."""
    if not upstream_ids:  # its access control would admit no router: nothing would route
        raise WireError(f"run {run_id}: the worker has no link to its router ({', '.join(upstream)}) now, "
                        "so its router for the run would have none")
    at = endpoint(free_port(LOOPBACK))
    settings = RouterProcessSettings(
        namespace=namespace, run=run_id, listen=at, upstream=tuple(upstream), upstream_ids=tuple(upstream_ids),
        run_password=RunAccess.create(namespace, secret, run=run_id).run_password,
        upstream_password=RunAccess.create(namespace, secret).run_password,  # the daemon's: what upstream admits
        tls=tls)
    process = subprocess.Popen(
        [sys.executable, "-m", ROUTER_PROCESS_MODULE], stdin=subprocess.PIPE, stdout=subprocess.PIPE,
        stderr=subprocess.PIPE, text=True, start_new_session=True, env=os.environ if environ is None else environ)
    router = RunRouter(run_id, process, at)
    try:
        with process.stdin as settings_in:
            settings_in.write(settings.to_json())
        said = _first_line(process, START_S)
    except BrokenPipeError:  # it exited before it read them
        said = ""
    if said != READY:
        router.close()
        why = router.last_words() or f"exit code {process.returncode}"
        raise WireError(f"run {run_id}: the worker's router for it did not start"
                        + (f" within {START_S:g} s" if said is None else "") + f": {why}")
    return router


def _first_line(process: subprocess.Popen, timeout: float) -> str | None:
    """The first line ``process`` prints on stdout, without its end ("" if it exited first);
    None if it printed none within ``timeout`` s."""
    if not select.select([process.stdout], [], [], timeout)[0]:
        return None
    return process.stdout.readline().rstrip("\n")
