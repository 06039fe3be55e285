"""``retriever status`` and ``retriever stop``: the queryable a deployment answers them on, what
its status says, and the asker (:func:`ask_deployment`, from any machine)."""

from __future__ import annotations

import zenoh

from ....errors import WorkerError
from ..access import TlsFiles
from ..daemon import QUERY_S, check_security, credentials, in_session, open_access
from ..hub import peer_config
from ..protocol import (ABSENT, DEPLOYMENT_QUERY, DEPLOYMENT_REPLY, DeploymentOp, ErrorReply, NodeStatus, StatusQuery,
                        StatusReply, StopQuery, StopReply, error_message)
from ..reach import REFUSES_LINKS, why_no_session
from ..wire import KeySpace, WireError
from ..coordinator.hosting import HostedRun
from .book import WorkerBook
from .usage import UsagePoller


class DeploymentQueryable:
    """The deployment's answers on its key (``retriever status`` / ``stop``): what runs where,
    from the run's book, the worker book and the usage last polled."""

    def __init__(self, run: HostedRun, book: WorkerBook, usage: UsagePoller):
        self.run, self.book, self.usage = run, book, usage

    def answer(self, query: zenoh.Query) -> None:
        """``status``: the deployment, node by node; ``stop``: end it now, as Ctrl-C here would."""
        run = self.run
        try:
            asked = DEPLOYMENT_QUERY.decode(query.payload.to_bytes() if query.payload is not None else b"",
                                            who="the deployment")
        except WireError as e:
            query.reply_err(ErrorReply(message=str(e)).encode())
            return
        if isinstance(asked, StopQuery):
            run.stop()
            query.reply(run.keys.deployment(), StopReply(pipeline=run.graph.name).encode())
            return
        for _ in range(3):  # read on Zenoh's thread while the run updates it: a copy may collide
            try:
                status = self.status_reply()
                break
            except RuntimeError:
                continue
        else:
            query.reply_err(ErrorReply(message="busy: ask again").encode())
            return
        query.reply(run.keys.deployment(), status.encode())

    def status_reply(self) -> StatusReply:
        """What ``retriever status`` shows: the run's time, and per node its worker, counters and
        the CPU seconds its process used so far (as last read)."""
        run, book = self.run, self.run.book
        used, placed = self.usage.cpu(), self.book.placed
        nodes = {nid: NodeStatus(worker=placed.get(nid), state=book.state.get(nid), ticks=s.ticks,
                                 steps=s.steps, skips=s.skips, errors=s.errors, counts=dict(s.counts),
                                 cpu_s=used.get(nid, ABSENT))
                 for nid, s in sorted(book.stats.items())}
        return StatusReply(pipeline=run.graph.name, run=self.book.run_id, t_ns=min(book.run_time(), book.end_ns),
                           end_ns=book.end_ns, started=book.t0 is not None, nodes=nodes)


def ask_deployment(connect: list[str], namespace: str, op: str, secret=None, insecure: bool = False,
                   tls: TlsFiles | None = None, router: bool = False) -> dict | None:
    """Ask the namespace's running deployment (``op``: a DeploymentOp, status or stop) through the
    peers at ``connect`` (its workers; ``router``: the routers it joined through): the fields of
    its reply (StatusReply or StopReply, exact), or None when no deployment runs there."""
    check_security(secret, insecure, f"retriever {op}")
    keys = KeySpace(namespace)
    request = {DeploymentOp.STATUS: StatusQuery, DeploymentOp.STOP: StopQuery}[DeploymentOp(op)]()
    found: list[dict] = []
    refusing: list[str] = []

    def ask(session: zenoh.Session) -> None:
        for reply in session.get(keys.deployment(), payload=request.encode(), timeout=QUERY_S):
            if reply.ok is None:
                data = reply.err.payload.to_bytes()
                message = error_message(data)
                raise WorkerError(f"the deployment refused {op}: {repr(data[:200]) if message is None else message}")
            try:
                answer = DEPLOYMENT_REPLY.decode(reply.ok.payload.to_bytes())
            except WireError as e:
                raise WorkerError(f"the deployment answered {op} with garbage: {e}") from None
            if answer.NAME != request.NAME:
                raise WorkerError(f"the deployment answered {op} with its '{answer.NAME}' reply")
            found.append(answer.to_fields())
            return

    with open_access(namespace, None if secret is None else str(secret), tls, client=router) as access:
        for endpoint in connect:
            config = peer_config(connect=[endpoint], access=access)
            config.insert_json5("mode", '"client"')
            try:
                in_session(config, ask)
            except zenoh.ZError:  # nothing listens there, it refuses new links, or it wants another secret
                if why_no_session(endpoint, credentials(tls)) == REFUSES_LINKS:
                    refusing.append(endpoint)
                continue
            if found:
                return found[0]
    if refusing:  # not the secret: a stranger's idle connections (hub.ACCEPT_TIMEOUT_S)
        raise WorkerError(f"no session at {', '.join(refusing)}: {REFUSES_LINKS}\n    hint: keep strangers off "
                          "the workers' ports: a firewall, or TLS (docs/security.md)")
    return None
