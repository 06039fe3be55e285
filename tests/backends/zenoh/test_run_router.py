"""A worker daemon's router for one run (daemon/run_router.py), linked to a ``retriever router``
on loopback: what routes through the two, and whom the run router refuses."""

from __future__ import annotations

import json
import os
import re
import shutil
import signal
import subprocess
import sys
import tempfile
from pathlib import Path

import pytest
import zenoh

from retriever.backends.zenoh.access import RunAccess, TlsFiles, run_user
from retriever.backends.dora.host import pid_alive
from retriever.backends.zenoh.daemon.router_process import SETTINGS_MAX
from retriever.backends.zenoh.daemon.run_router import (EXIT_FAILED, ROUTER_PROCESS_FOLDER, ROUTER_PROCESS_MODULE,
                                                        open_run_router)
from retriever.backends.zenoh.hub import client_config, free_port, port_is_free
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


def test_a_run_routers_flows_reach_each_other_and_the_upstream_routers_clients(router):
    _, upstream = router
    run_router = open_run_router(A, SECRET, RUN, (upstream,), upstream_ids(upstream))
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


def test_a_run_router_refuses_a_session_without_the_runs_password(router):
    _, upstream = router
    run_router = open_run_router(A, SECRET, RUN, (upstream,), upstream_ids(upstream))
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
    # its dictionary was in memory (or removed once it opened)
    assert not list(Path(tempfile.gettempdir()).glob(f"{ROUTER_PROCESS_FOLDER}-{run_router.pid}-*"))


@pytest.mark.skipif(shutil.which("openssl") is None, reason="the test makes certificates with openssl")
def test_a_run_router_links_to_an_upstream_router_over_mutual_tls(routers, secret, tmp_path):
    files = certificates(tmp_path)
    tls = TlsFiles(files["ca.pem"], files["client.pem"], files["client.key"])
    upstream = f"tls/127.0.0.1:{free_port()}"
    routers("--secret", str(secret), "--listen", upstream, "--namespace", A, *_tls_flags(files)).wait_started()
    run_router = open_run_router(A, SECRET, RUN, (upstream,), upstream_ids(upstream, tls), tls=tls)
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


def test_a_run_router_is_not_opened_while_the_worker_has_no_router():
    with pytest.raises(WireError, match=r"run run-1: the worker has no link to its router \(tcp/127.0.0.1:7447\) now"):
        open_run_router(A, SECRET, RUN, ("tcp/127.0.0.1:7447",), [])


def test_a_run_router_that_gets_no_upstream_link_says_so(router):
    _, upstream = router
    with pytest.raises(WireError, match=r"run run-1: the worker's router for it did not start: it got no link to the "
                                        rf"upstream router \({upstream}\) within 5 s"):
        open_run_router(A, SECRET, RUN, (upstream,), ["123456789abcdef0123456789abcdef"])


#: settings a daemon would write, but for what each case changes
GOOD = {"namespace": A, "run": RUN, "listen": "tcp/127.0.0.1:0", "upstream": ["tcp/127.0.0.1:7447"],
        "upstream_ids": ["123456789abcdef0123456789abcdef"], "run_password": "p", "upstream_password": "q"}


@pytest.mark.parametrize("given, why", [
    ("[" * 100_000, "maximum recursion depth exceeded"),
    (json.dumps({**GOOD, "namespace": "a/**"}), "namespace 'a/**' cannot be a Zenoh key chunk"),
    (json.dumps({**GOOD, "upstream": "tcp/127.0.0.1:7447"}), "upstream and upstream_ids are no lists"),
    (json.dumps({**GOOD, "tls": {"ca": 1, "cert": 2, "key": 3}}), "a value that is no text"),
    (json.dumps({**GOOD, "run_password": "p\nu:x"}), "a password of more than one line"),
    (" " * (SETTINGS_MAX + 1), f"more than {SETTINGS_MAX:,} characters"),
])
def test_a_run_routers_process_refuses_settings_that_are_not_a_daemons_in_a_line(given, why):
    """What its stdin holds if no daemon wrote it: its process says so on stderr and exits,
    never with a traceback (a namespace that is no key chunk was one, from its access control,
    and JSON nested too deep another)."""
    done = subprocess.run([sys.executable, "-m", ROUTER_PROCESS_MODULE], input=given, capture_output=True,
                          text=True, timeout=60)
    assert done.returncode == EXIT_FAILED and done.stdout == ""
    said = rf"the run router's settings are not a daemon's: [^\n]*{re.escape(why)}[^\n]*\n"
    assert re.fullmatch(said, done.stderr), done.stderr


# ---------------------------------------------------------------------------------------------
# Its process
# ---------------------------------------------------------------------------------------------
def test_a_run_router_is_a_process_that_ends_when_closed(router):
    _, upstream = router
    run_router = open_run_router(A, SECRET, RUN, (upstream,), upstream_ids(upstream))
    ended = []
    run_router.watch(ended.append)
    try:
        assert pid_alive(run_router.pid) and run_router.pid != os.getpid()
        with run_client(run_router.endpoint) as flow:
            assert list(flow.info.routers_zid())
    finally:
        run_router.close()
    assert run_router.process.returncode == 0  # it closed its session and exited, on SIGTERM
    assert not pid_alive(run_router.pid)
    assert port_is_free(int(run_router.endpoint.rsplit(":", 1)[1]))
    assert run_router.ended() is None and not ended  # a close is no crash


def test_a_crashed_run_router_is_told_with_how_it_ended(router):
    _, upstream = router
    run_router = open_run_router(A, SECRET, RUN, (upstream,), upstream_ids(upstream))
    ended = []
    run_router.watch(ended.append)
    try:
        os.kill(run_router.pid, signal.SIGKILL)
        until(lambda: ended, "the run router's end told")
    finally:
        run_router.close()
    assert ended == [f"run run-1: the worker's router for it (pid {run_router.pid}, {run_router.endpoint}) was killed "
                     "by SIGKILL; the run's flows on this machine have no link to anyone"]


#: a stand-in for a worker daemon: starts a run router from its main thread, as a daemon does from
#: its spawner thread (both live as long as the process), says its pid, and waits to be killed
DAEMON = """
import sys
from retriever.backends.zenoh.daemon.run_router import open_run_router
run_router = open_run_router(sys.argv[1], bytes.fromhex(sys.argv[2]), "run-1", (sys.argv[3],), sys.argv[4:])
print(run_router.pid, flush=True)
sys.stdin.read()
"""


def test_a_run_router_dies_with_its_sigkilled_daemon(router):
    _, upstream = router
    daemon = subprocess.Popen([sys.executable, "-c", DAEMON, A, SECRET.hex(), upstream, *upstream_ids(upstream)],
                              stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    try:
        pid = int(daemon.stdout.readline())
        assert pid_alive(pid)
        daemon.kill()
        daemon.wait()
        until(lambda: not pid_alive(pid), "the run router's end after its daemon's")
    finally:
        daemon.kill()
        daemon.wait()
        daemon.stdin.close()
        daemon.stdout.close()


def test_a_big_message_between_two_flows_of_a_run_router_goes_through_shared_memory(router):
    """A 1 MiB put of a flow reaches the other flow on this machine as a shared-memory buffer:
    the run router maps the sender's pool and forwards the buffer, not its bytes."""
    _, upstream = router
    run_router = open_run_router(A, SECRET, RUN, (upstream,), upstream_ids(upstream))
    keys = KeySpace(A)
    access = RunAccess.create(A, SECRET, run=RUN).client_config(A)
    got = []
    try:
        with zenoh.open(client_config(connect=[run_router.endpoint], access=access)) as camera, \
                zenoh.open(client_config(connect=[run_router.endpoint], access=access)) as controller:
            _sub = controller.declare_subscriber(
                keys.data("camera", "frame"), lambda s: got.append(s.payload.as_shm() is not None))
            # the sender makes its pool at its first big message, which goes over TCP, and a loaded
            # machine may send a few more so while the pool is made: one of them comes through it
            until(lambda: any(got), "a frame of 1 MiB between two flows through shared memory",
                  act=lambda: camera.put(keys.data("camera", "frame"), bytes(1 << 20)))
    finally:
        run_router.close()
