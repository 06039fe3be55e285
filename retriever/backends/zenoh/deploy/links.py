"""Links: the deployment's two sessions, the control session to the worker daemons and the run's
hub (module docstring of deploy/: why two), or one client session of the routers that is both."""

from __future__ import annotations

import dataclasses
import re
import time
from collections.abc import Callable, Iterator, Mapping
from contextlib import contextmanager
from pathlib import Path

import zenoh

from ....errors import BackendError
from ..access import CONTROL_DICTIONARY, AccessError, RunAccess, SessionDictionary, TlsFiles, secret_bytes
from ..daemon import DaemonInfo, no_router
from ..hub import (HUB_SHARED_MEMORY, client_config, forward_dropping, free_port, peer_config, raise_open_file_limit,
                   remove_orphaned_segments_at_exit, wait_for_peers)
from ..protocol import RunSpec
from ..coordinator.hosting import HostedRun

#: how long the coordinator waits for links to its --connect endpoints before it looks for workers
JOIN_S = 5.0
#: where a coordinator told only --connect listens: every address of its machine, a port the OS picks
ANY_ADDRESS = "tcp/0.0.0.0:0"


@contextmanager
def phase(on_phase: Callable[[str, float], None] | None, name: str) -> Iterator[None]:
    """Time step ``name`` of the start for ``on_phase``, whether it ends or raises."""
    begin = time.perf_counter()
    try:
        yield
    finally:
        if on_phase is not None:
            on_phase(name, time.perf_counter() - begin)


class Links:
    """The deployment's sessions: where it connects and listens (or the routers it joins), with
    which credentials, and where the hub is reached from each worker's host."""

    def __init__(self, *, connect: list[str], listen: list[str], router: list[str], secret, insecure: bool,
                 lease: float | None, tls: TlsFiles | None, on_phase: Callable[[str, float], None] | None):
        self.connect, self.listen_at, self.router = list(connect), list(listen), list(router)
        self.tls, self._insecure, self._lease, self._on_phase = tls, insecure, lease, on_phase
        #: the deployment secret (a file or bytes; None: --insecure): the namespace's credentials,
        #: and the key that seals each request to a daemon (remote.RemoteHost)
        self.secret = secret
        #: the hub's dictionary, in memory until the hub opened (hub_dictionary)
        self._hub_dictionary: SessionDictionary | None = None
        #: the session that links to the worker daemons, with the namespace's credentials (the hub
        #: itself when joined through routers); ``control_keep``: what is declared on it
        self.control: zenoh.Session | None = None
        self.control_keep: list = []
        self._hub_port: int | None = None  # where the hub listens, on every address of its host
        self._hub_proto, self._hub_host = "tcp", "0.0.0.0"
        self._linked = False  # whether the hub has a link to each --connect endpoint

    def open_hub(self, run: HostedRun, access: dict[str, str] | None) -> tuple[zenoh.Session, str]:
        """The run's hub, and the control session beside it (or one session, a client of the
        routers, that is both): ``(hub, endpoint)``, as Hosting.open_hub answers."""
        if self.router:
            return self._open_client(run)
        links = self.tls.session_config() if self.tls is not None else {}
        raise_open_file_limit()  # it listens where strangers may connect too (hub.accept_pending)
        remove_orphaned_segments_at_exit()
        with phase(self._on_phase, "join"):
            try:
                self.control = self._open_control(run, links)
                try:
                    hub = self._open_run_hub(run, {**(access or {}), **links})
                except BaseException:
                    self.close(run.hub)
                    raise
            finally:  # Zenoh read the run's dictionary as the hub opened; no process of this machine reads it after
                self.drop_hub_dictionary()
        host = "127.0.0.1" if self._hub_host in ("0.0.0.0", "[::]") else self._hub_host
        return hub, f"{self._hub_proto}/{host}:{self._hub_port}"

    def hub_dictionary(self, access: RunAccess, run_dir) -> Path:
        """The hub's dictionary, in memory (access.SessionDictionary: no file on disk, on Linux);
        no process but this one reads it, and open_hub drops it once the hub opened."""
        self._hub_dictionary = access.session_dictionary(run_dir)
        return self._hub_dictionary.path

    def drop_hub_dictionary(self) -> None:
        dictionary, self._hub_dictionary = self._hub_dictionary, None
        if dictionary is not None:
            dictionary.close()

    def _open_control(self, run: HostedRun, links: dict[str, str]) -> zenoh.Session:
        """The session that links to the worker daemons, with the namespace's credentials. It
        listens even when told only where to connect (as the daemons do: a daemon it learns of
        by gossip may open the link). Zenoh reads the namespace's dictionary as it opens: it is given
        in memory (access.SessionDictionary), closed then: on disk at no time, on Linux."""
        listen = self.listen_at or [ANY_ADDRESS.replace("tcp/", "tls/") if self.tls else ANY_ADDRESS]
        access = dict(links)
        dictionary = None
        if not self._insecure:
            try:
                namespace_access = RunAccess.create(run.namespace, secret_bytes(self.secret))
            except AccessError as e:
                raise BackendError(str(e)) from None
            dictionary = namespace_access.session_dictionary(run.run_dir, CONTROL_DICTIONARY)
            access.update(namespace_access.session_config(dictionary.path))
        try:
            control = zenoh.open(peer_config(listen=listen, connect=self.connect, access=access or None,
                                             lease=self._lease, shared_memory=False))
        finally:
            if dictionary is not None:
                dictionary.close()
        try:
            self._linked = wait_for_peers(control, len(self.connect), JOIN_S)
        except BaseException:
            control.close()
            raise
        return control

    def _open_run_hub(self, run: HostedRun, access: dict[str, str]) -> zenoh.Session:
        """The run's hub: it checks the run's flows (and watchers) against this run's dictionary
        alone, listening on a free port of every address of its host (or of the --listen one's
        host), which each daemon's flows connect to (:meth:`spec_for`). It connects nowhere."""
        proto, host = "tls" if self.tls else "tcp", "0.0.0.0"
        if self.listen_at:
            proto, _, address = self.listen_at[0].partition("/")
            host = address.split("#")[0].rpartition(":")[0] or host
        self._hub_proto, self._hub_host = proto, host
        access = {**access, **forward_dropping(run.keys)}  # a watcher's link never holds the hub
        last: Exception | None = None
        for _ in range(5):
            port = free_port(host) if ":" not in host else free_port()  # (an IPv6 host: one free on loopback)
            try:
                hub = zenoh.open(peer_config(listen=[f"{proto}/{host}:{port}"], access=access, lease=self._lease,
                                             shared_memory=HUB_SHARED_MEMORY))
            except zenoh.ZError as e:  # taken between the check and the bind: try another
                last = e
                continue
            self._hub_port = port
            return hub
        raise BackendError(f"could not open the run's hub on {proto}/{host}: {last}")

    def _hub_for(self, run: HostedRun, name: str, daemons: Mapping[str, DaemonInfo]) -> str:
        """The hub's endpoint as worker ``name``'s host reaches it: the address of this machine
        on the control session's link to that daemon (peers do not route for each other: a
        daemon the coordinator asks has a direct link), the hub's port."""
        if self.router:
            return run.endpoint
        replier = daemons[name].zid or ""  # the replier's id: "EntityGlobalId { zid: <hex>, eid: N }"
        found = re.search(r"zid: ([0-9a-f]+)", replier)
        zid = found.group(1) if found else replier
        for link in self.control.info.links():
            if zid and str(link.zid) == zid:
                _, _, address = str(link.src).partition("/")
                host = address.split("#")[0].rpartition(":")[0]
                if host:
                    return f"{self._hub_proto}/{host}:{self._hub_port}"
        if self._hub_host not in ("0.0.0.0", "[::]"):
            return f"{self._hub_proto}/{self._hub_host}:{self._hub_port}"
        raise BackendError(f"the coordinator has no link to worker '{name}' to tell it where the run's hub is\n"
                           "    hint: pass --connect with each worker's endpoint")

    def close(self, run_hub) -> None:
        """Undeclare what the control session holds and close it (not ``run_hub``: the coordinator's)."""
        for declared in self.control_keep:
            try:
                declared.undeclare()
            except zenoh.ZError:
                pass
        self.control_keep.clear()
        control, self.control = self.control, None
        if control is not None and control is not run_hub:
            try:
                control.close()
            except zenoh.ZError:
                pass

    def _open_client(self, run: HostedRun) -> tuple[zenoh.Session, str]:
        """open_hub through the routers: a client of theirs, with the namespace's password for
        them (RunAccess.client_config). It opens only once a router admitted it: joined."""
        access = {**(run.access.client_config(run.namespace) if run.access is not None else {}),
                  **(self.tls.session_config() if self.tls is not None else {})}
        remove_orphaned_segments_at_exit()
        with phase(self._on_phase, "join"):
            self.drop_hub_dictionary()  # a client has none (see open_hub)
            try:
                hub = zenoh.open(client_config(connect=self.router, access=access or None, lease=self._lease,
                                               shared_memory=HUB_SHARED_MEMORY))
            except zenoh.ZError:
                raise BackendError(no_router("the deployment", self.router, self.tls, run.namespace)) from None
        self._linked = True
        self.control = hub  # one session does both, with the namespace's credentials
        return hub, self.router[0]

    def where(self) -> str:
        """Where the deployment is joined, for the line that says how to watch it (Hosting.where)."""
        if self.router:
            return f"deployment joined through router {', '.join(self.router)}"
        if not self.connect:
            return f"deployment listening on {', '.join(self.listen_at)}"
        # a peer's session opens without a link: "joined" only once it has one to each endpoint
        return f"deployment {'joined through' if self._linked else 'connecting to'} {', '.join(self.connect)}"

    def spec_for(self, run: HostedRun, name: str, daemons: Mapping[str, DaemonInfo]) -> RunSpec:
        """The run's spec as worker ``name`` (one of ``daemons``) gets it: the hub where its host reaches it."""
        return dataclasses.replace(run.spec.for_remote(), hub=self._hub_for(run, name, daemons))
