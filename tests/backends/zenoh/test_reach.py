"""A stranger's idle connections against a daemon (issue 40, item 6; hub.ACCEPT_TIMEOUT_S, reach.py).

A real daemon on a loopback port, with a secret; the stranger is a real process holding idle TCP
connections to it (``idle_connections.py``), with no credentials. Below the daemon's accept limit
they keep no one out; past it, `retriever workers` and `retriever deploy` say that the endpoint
refuses new links, not that the secret is wrong. Every process is killed by its pid at the end.
"""

from __future__ import annotations

import resource
import socket
import subprocess
import sys
import threading
from pathlib import Path

import pytest

from retriever.backends.zenoh.hub import ACCEPT_PENDING_MIN, accept_pending, endpoint, free_port
from retriever.backends.zenoh.reach import NOTHING_LISTENS, REFUSES_LINKS, why_no_session

from tests.backends.zenoh.test_daemon import BOUND_S, ROOT, SECRET, _cli, namespace, workers  # noqa: F401 (fixtures)

HOLDER = Path(__file__).with_name("idle_connections.py")


@pytest.fixture
def secret(tmp_path) -> Path:
    path = tmp_path / "lab.key"
    path.write_text(SECRET)
    path.chmod(0o600)
    return path


@pytest.fixture
def stranger():
    """``stranger(port, n)``: a process holding n idle connections to the port, up once it said so."""
    started: list[subprocess.Popen] = []

    def hold(port: int, count: int) -> subprocess.Popen:
        proc = subprocess.Popen([sys.executable, str(HOLDER), "127.0.0.1", str(port), str(count)],
                                stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
        started.append(proc)
        assert proc.stdout.readline().strip() == f"holding {count}"
        return proc

    yield hold
    for proc in started:
        proc.kill()
        proc.wait()


def _guarded_worker(workers, namespace, secret, port: int):  # noqa: F811
    return workers("--name", "w", "--listen", endpoint(port), "--namespace", namespace, "--secret", str(secret),
                   "--path", str(ROOT / "tests" / "deploy")).wait_started()


def test_idle_connections_below_the_accept_limit_keep_no_deployment_out(workers, namespace, secret, stranger,  # noqa: F811
                                                                        tmp_path):
    """250 idle connections filled Zenoh's 100 places of a daemon's handshake (10 s each, taken
    again as soon as they were freed): `retriever workers` and `retriever deploy` got no session
    and blamed the secret. Now the daemon has more places than the stranger holds."""
    port = free_port()
    _guarded_worker(workers, namespace, secret, port)
    stranger(port, 250)
    listed = _cli("workers", "--connect", endpoint(port), "--namespace", namespace, "--secret", str(secret))
    assert listed.returncode == 0 and "│ w " in listed.stdout, listed.stdout + listed.stderr
    log = tmp_path / "run.mcap"
    done = _cli("deploy", "tests/deploy/deploy_flows.py:pipe", "--connect", endpoint(port), "--namespace", namespace,
                "--secret", str(secret), "--duration", "1", "--log", str(log))
    assert done.returncode == 0, done.stderr
    assert log.exists()


def test_past_the_accept_limit_the_endpoint_is_said_to_refuse_links_not_to_want_another_secret(
        workers, namespace, secret, stranger):  # noqa: F811
    port = free_port()
    _guarded_worker(workers, namespace, secret, port)
    # the daemon raised its open-file limit to the hard one (hub.raise_open_file_limit)
    places = accept_pending(resource.getrlimit(resource.RLIMIT_NOFILE)[1])
    stranger(port, places + 50)
    listed = _cli("workers", "--connect", endpoint(port), "--namespace", namespace, "--secret", str(secret))
    assert listed.returncode == 1
    assert f"warning: no session at {endpoint(port)}: {REFUSES_LINKS}" in " ".join(listed.stderr.split()), \
        listed.stderr
    assert "--secret" not in listed.stderr


@pytest.fixture
def refusing_endpoint():
    """A real listener that closes every connection as soon as it took it, before a word: what a
    Zenoh session whose handshake places are all taken does (a deploy's peer session retries its
    link until a place frees, so a flooded daemon lets it in now and then: this one never does)."""
    listener = socket.socket()
    listener.bind(("127.0.0.1", 0))
    listener.listen(64)

    def refuse() -> None:
        while True:
            try:
                conn, _ = listener.accept()
            except OSError:  # closed: the test is over
                return
            conn.close()

    threading.Thread(target=refuse, daemon=True).start()
    yield endpoint(listener.getsockname()[1])
    listener.shutdown(socket.SHUT_RDWR)
    listener.close()


def test_a_deployment_that_reaches_only_an_endpoint_refusing_links_says_so_not_that_the_secret_is_wrong(
        refusing_endpoint, namespace, secret):  # noqa: F811
    done = _cli("deploy", "tests/deploy/deploy_flows.py:pipe", "--connect", refusing_endpoint, "--namespace",
                namespace, "--secret", str(secret), "--duration", "1")
    assert done.returncode == 1
    flat = " ".join(done.stderr.split())
    assert f"error: no worker found in namespace '{namespace}': {refusing_endpoint}: {REFUSES_LINKS}" in flat, \
        done.stderr
    assert f"deployment connecting to {refusing_endpoint}" in flat and "joined" not in flat, done.stderr
    assert "hint: see who holds connections to it" in flat and "TLS (docs/security.md)" in flat
    assert "holds this --secret" not in flat
    stopped = _cli("status", "--connect", refusing_endpoint, "--namespace", namespace, "--secret", str(secret))
    assert stopped.returncode == 1
    assert f"error: no session at {refusing_endpoint}: {REFUSES_LINKS}" in " ".join(stopped.stderr.split())


def test_why_no_session_tells_nothing_listening_a_closed_connection_and_a_held_one():
    assert why_no_session(endpoint(free_port())) == NOTHING_LISTENS
    with socket.socket() as listener:  # takes connections and waits for what they say: credentials
        listener.bind(("127.0.0.1", 0))
        listener.listen(8)
        assert why_no_session(endpoint(listener.getsockname()[1])) == "it wants another --secret"
        assert why_no_session(f"tls/127.0.0.1:{listener.getsockname()[1]}", "--secret or a certificate of "
                              "another CA") == "it wants another --secret or a certificate of another CA"
    assert why_no_session("udp/127.0.0.1:7447") == "it wants another --secret, or nothing listens there"


def test_a_session_admits_more_handshakes_than_zenohs_default_within_its_open_file_limit():
    assert accept_pending(1024) == 512 and accept_pending(1 << 20) == 2000
    assert accept_pending(64) == ACCEPT_PENDING_MIN == 100
    assert accept_pending(resource.RLIM_INFINITY) == 2000
