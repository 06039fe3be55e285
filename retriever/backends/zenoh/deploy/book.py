"""WorkerBook: what a deployment knows of its workers, which its parts read and write."""

from __future__ import annotations

import secrets
import sys
from collections import Counter
from dataclasses import dataclass, field

import zenoh

from ....placement import LiveDaemon
from ..daemon import DaemonInfo
from ..protocol import InfoReply
from ..remote import RemoteHost
from ..wire import KeySpace


@dataclass
class WorkerBook:
    """The deployment's workers: each daemon found, the host of each that runs nodes of the run,
    where each node is placed, and what each said of the code it runs anyway."""

    #: the run's id: the daemons derive the run's passwords from it (access.RunAccess)
    run_id: str = field(default_factory=lambda: secrets.token_hex(6))
    #: each worker daemon as the deployment found it: its info reply, its clock offset, its
    #: session (RemoteHost takes only that session's answers)
    daemons: dict[str, DaemonInfo] = field(default_factory=dict)
    #: the worker daemons that run nodes of the run, by name
    remotes: dict[str, RemoteHost] = field(default_factory=dict)
    #: where each node runs: worker name by node
    placed: dict[str, str] = field(default_factory=dict)
    #: what each worker said of the code it runs anyway (--code-mismatch warn): into the log
    ran_other_code: dict[str, list[str]] = field(default_factory=dict)

    def host_of(self, name: str, control: zenoh.Session, keys: KeySpace, secret=None) -> RemoteHost:
        """Worker ``name``'s host in the run, made on ``control`` the first time it is asked for;
        ``secret``: the deployment's, which seals its requests (None: --insecure, unsealed)."""
        remote = self.remotes.get(name)
        if remote is None:
            remote = self.remotes[name] = RemoteHost(control, keys, name, self.run_id, self.daemons[name].zid,
                                                     secret)
        return remote

    def workers_up(self) -> list[LiveDaemon]:
        """The workers still up, each loaded as at the start (the nodes of other runs its info listed
        when it was found) plus this run's nodes placed on it: a move's candidates."""
        load = Counter(self.placed.values())
        return [placement_target(name, daemon.info, len(daemon.info.nodes) + load[name])
                for name, daemon in sorted(self.daemons.items())]

    def say_warnings(self, name: str, warnings: list[str]) -> None:
        """Say what worker ``name`` warned of as it prepared (the code it runs anyway), and keep it for the log."""
        for warning in warnings:
            print(f"retriever: warning: worker '{name}' runs {warning}", file=sys.stderr, flush=True)
            self.ran_other_code.setdefault(name, []).append(warning.partition("\n")[0])


def placement_target(name: str, info: InfoReply, load: int) -> LiveDaemon:
    """Worker ``name`` as placement weighs it: the labels and host of its info reply, and ``load``
    nodes on it (at the start, those its info lists; when a lost worker's nodes move, those and
    this run's placed there)."""
    return LiveDaemon(name, frozenset(info.labels), load, info.host)
