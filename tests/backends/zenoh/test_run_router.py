"""A worker daemon's router for one run (daemon/run_router.py), linked to a ``retriever router``
on loopback: what routes through the two, and whom the run router refuses."""

from __future__ import annotations

import json
import shutil

import pytest
import zenoh

from retriever.backends.zenoh.access import RunAccess, TlsFiles, run_user
from retriever.backends.zenoh.daemon.run_router import open_run_router
from retriever.backends.zenoh.hub import client_config, free_port
from retriever.backends.zenoh.wire import KeySpace, WireError
from tests.backends.zenoh.test_router import (SECRET, A, B, _tls_flags, certificates, client, keys_seen, router,  # noqa: F401
                                              routers, secret, until)

RUN = "run-1"
USRPWD = "transport/auth/usrpwd"


def run_client(at: str, run: str = RUN, secret: bytes = SECRET, namespace: str = A,
               user: str | None = None) -> zenoh.Session:
    """A client with the passwords of ``run`` of ``namespace`` (a flow of that run; A's by
    default), under ``user`` if given (else its namespace's run user)."""
    access = RunAccess.create(namespace, secret, run=run).client_config(namespace)
    if user is not None:
        pair = json.loads(access[USRPWD])
        access = {USRPWD: json.dumps({**pair, "user": user})}
    return zenoh.open(client_config(connect=[at], access=access, shared_memory=False))


def upstream_ids(at: str, tls: TlsFiles | None = None) -> list[str]:
    """The Zenoh id of the router at ``at``, as a daemon's session joined to it knows it."""
    access = {**RunAccess.create(A, SECRET).client_config(A), **(tls.session_config() if tls else {})}
    with zenoh.open(client_config(connect=[at], access=access, shared_memory=False)) as daemon:
        return [str(z) for z in daemon.info.routers_zid()]


def test_a_run_routers_flows_reach_each_other_and_the_upstream_routers_clients(router, tmp_path):
    _, upstream = router
    run_router = open_run_router(A, SECRET, RUN, (upstream,), upstream_ids(upstream), tmp_path)
    keys = KeySpace(A)
    try:
        with run_client(run_router.endpoint) as camera, run_client(run_router.endpoint) as controller, \
                client(upstream, A) as policy:
            local, _local_sub = keys_seen(controller, keys.data("camera", "**"))
            far, _far_sub = keys_seen(policy, keys.data("camera", "**"))
            until(lambda: local and far, "a put reaching a flow beside it and one beyond the upstream router",
                  act=lambda: camera.put(keys.data("camera", "frame"), b"1"))
            back, _back_sub = keys_seen(controller, keys.data("policy", "**"))
            until(lambda: back, "a put from beyond the upstream router", act=lambda: policy.put(keys.data("policy", "a"), b"2"))
            _answers = policy.declare_queryable(keys.finished(), lambda q: q.reply(keys.finished(), b"done"))
            until(lambda: [r.ok.payload.to_bytes() for r in camera.get(keys.finished(), timeout=2) if r.ok] == [b"done"],
                  "an answer to a query across both routers")
    finally:
        run_router.close()


def test_a_run_router_refuses_a_session_without_the_runs_password(router, tmp_path):
    _, upstream = router
    folder = tmp_path / "run"
    folder.mkdir()
    run_router = open_run_router(A, SECRET, RUN, (upstream,), upstream_ids(upstream), folder)
    try:
        for stranger in (lambda: run_client(run_router.endpoint, run="run-2"),  # another run's flow
                         # the same run id in another namespace of the secret, under its user or A's
                         lambda: run_client(run_router.endpoint, namespace=B),
                         lambda: run_client(run_router.endpoint, namespace=B, user=run_user(A)),
                         lambda: client(run_router.endpoint, A),  # the namespace's passwords: a daemon's
                         lambda: zenoh.open(client_config(connect=[run_router.endpoint], shared_memory=False))):
            try:
                session = stranger()
            except zenoh.ZError:
                continue
            session.close()
            raise AssertionError("the run router admitted a session without the run's password")
        with run_client(run_router.endpoint) as flow:
            assert list(flow.info.routers_zid())
    finally:
        run_router.close()
    assert not list(folder.iterdir())  # its dictionary was in memory (or removed once it opened)


@pytest.mark.skipif(shutil.which("openssl") is None, reason="the test makes certificates with openssl")
def test_a_run_router_links_to_an_upstream_router_over_mutual_tls(routers, secret, tmp_path):
    files = certificates(tmp_path)
    tls = TlsFiles(files["ca.pem"], files["client.pem"], files["client.key"])
    upstream = f"tls/127.0.0.1:{free_port()}"
    routers("--secret", str(secret), "--listen", upstream, "--namespace", A, *_tls_flags(files)).wait_started()
    folder = tmp_path / "run"
    folder.mkdir()
    run_router = open_run_router(A, SECRET, RUN, (upstream,), upstream_ids(upstream, tls), folder, tls=tls)
    keys = KeySpace(A)
    try:
        far_access = {**RunAccess.create(A, SECRET).client_config(A), **tls.session_config()}
        with run_client(run_router.endpoint) as camera, \
                zenoh.open(client_config(connect=[upstream], access=far_access, shared_memory=False)) as policy:
            far, _far_sub = keys_seen(policy, keys.data("camera", "**"))
            until(lambda: far, "a put reaching beyond the upstream router over TLS",
                  act=lambda: camera.put(keys.data("camera", "frame"), b"1"))
    finally:
        run_router.close()


def test_a_run_router_is_not_opened_while_the_worker_has_no_router(tmp_path):
    with pytest.raises(WireError, match=r"run run-1: the worker has no link to its router \(tcp/127.0.0.1:7447\) now"):
        open_run_router(A, SECRET, RUN, ("tcp/127.0.0.1:7447",), [], tmp_path)
