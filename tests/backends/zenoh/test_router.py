"""``retriever router``, run as users run it (a subprocess on a loopback port), with clients of
the namespaces it serves (hub.client_config): what routes through it, whom it refuses, what
each namespace's users may reach, its errors, and how it stops."""

from __future__ import annotations

import os
import re
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import pytest
import zenoh

from retriever.backends.zenoh.access import RunAccess, TlsFiles, watch_user
from retriever.backends.zenoh.hub import client_config, endpoint, free_port
from retriever.backends.zenoh.router import ROUTER_FOLDER
from retriever.backends.zenoh.wire import KeySpace
from tests.backends.zenoh.test_daemon import Worker, _env

ROOT = Path(__file__).resolve().parents[3]
BOUND_S = 60.0  # a bound on any wait, never a speed check
START_S = 120.0  # a bound on a router's start: an interpreter's, its imports' and a session's, on a loaded machine
SECRET = b"a deployment secret of 32 bytes."
A, B = "router-a", "router-b"


class Router(Worker):
    """A ``retriever router`` process, and the lines of its stderr (read on a thread)."""

    COMMAND, WHAT, START_S = "router", "router", START_S

    @staticmethod
    def says_started(line: str) -> bool:
        return line.startswith("retriever router listening on ")


@pytest.fixture
def secret(tmp_path: Path) -> Path:
    path = tmp_path / "lab.key"
    path.write_bytes(SECRET)
    path.chmod(0o600)
    return path


@pytest.fixture
def routers():
    """Start routers (``routers(*args)``); each is stopped by its PID at the end, whatever happened:
    SIGTERM, so that it removes its folder (its dictionary of the namespaces' passwords), then
    SIGKILL if it is still up after BOUND_S."""
    started: list[Router] = []

    def start(*args: str) -> Router:
        started.append(Router(*args))
        return started[-1]

    yield start
    for router in started:
        if router.proc.poll() is None:
            router.proc.terminate()
            try:
                router.proc.wait(BOUND_S)
            except subprocess.TimeoutExpired:
                pass
        router.kill()


@pytest.fixture
def router(routers, secret):
    """A router of namespaces A and B on a free loopback port: (its process, its endpoint)."""
    at = endpoint(free_port())
    return routers("--secret", str(secret), "--listen", at, "--namespace", A, "--namespace", B).wait_started(), at


def client(at: str, namespace: str, secret: bytes = SECRET) -> zenoh.Session:
    """A client session of ``namespace``'s processes, joined through the router at ``at``."""
    return zenoh.open(client_config(connect=[at], access=RunAccess.create(namespace, secret).client_config(namespace),
                                    shared_memory=False))


def watcher(at: str, namespace: str) -> zenoh.Session:
    """A client session with ``namespace``'s watcher password."""
    config = client_config(connect=[at], shared_memory=False)
    password = RunAccess.create(namespace, SECRET).watch_password
    config.insert_json5("transport/auth/usrpwd", f'{{user: "{watch_user(namespace)}", password: "{password}"}}')
    return zenoh.open(config)


def until(condition, what: str, act=lambda: None) -> None:
    """``act()`` until ``condition()`` holds, at most BOUND_S."""
    give_up = time.monotonic() + BOUND_S
    while not condition():
        assert time.monotonic() < give_up, f"{what}: not within {BOUND_S:g} s"
        act()
        time.sleep(0.02)


def keys_seen(session: zenoh.Session, key_expr: str) -> tuple[list[str], zenoh.Subscriber]:
    """The keys of every sample ``session`` receives on ``key_expr``, as they come."""
    seen: list[str] = []
    return seen, session.declare_subscriber(key_expr, lambda sample: seen.append(str(sample.key_expr)))


# ---------------------------------------------------------------------------------------------
# Through the router
# ---------------------------------------------------------------------------------------------
def test_clients_of_a_namespace_exchange_puts_queries_and_liveliness_through_it(router):
    proc, at = router
    keys = KeySpace(A)
    with client(at, A) as a1, client(at, A) as a2:
        assert [str(z) for z in a1.info.routers_zid()] and not list(a1.info.peers_zid())  # joined to the router only
        seen, _sub = keys_seen(a2, keys.all_data())
        until(lambda: keys.data("n", "p") in seen, "a put reaching the other client",
              act=lambda: a1.put(keys.data("n", "p"), b"1"))
        _answers = a2.declare_queryable(keys.finished(), lambda q: q.reply(keys.finished(), b"done"))
        until(lambda: [r.ok.payload.to_bytes() for r in a1.get(keys.finished(), timeout=2) if r.ok] == [b"done"],
              "an answer to a query")
        live: list[str] = []
        _lsub = a1.liveliness().declare_subscriber(keys.workers(), lambda s: live.append(str(s.key_expr)), history=True)
        token = a2.liveliness().declare_token(keys.workers("w"))
        until(lambda: {str(r.ok.key_expr) for r in a1.liveliness().get(keys.workers(), timeout=2) if r.ok}
              == {keys.workers("w")}, "a liveliness token seen by a get")
        until(lambda: set(live) == {keys.workers("w")}, "a liveliness token seen by a subscriber")
        token.undeclare()
    assert proc.proc.poll() is None


@pytest.mark.parametrize("who", ["no credentials", "another secret", "a namespace it does not serve"])
def test_a_client_without_the_namespace_s_password_is_refused_at_open(router, who):
    _, at = router
    with pytest.raises(zenoh.ZError):
        if who == "no credentials":
            zenoh.open(client_config(connect=[at], shared_memory=False)).close()
        elif who == "another secret":
            client(at, A, secret=b"another secret, also of 32 bytes").close()
        else:
            client(at, "router-c").close()


def test_a_namespace_reaches_none_of_another_s_keys(router):
    """Deny by default: B's clients neither read A's puts, nor put into A, nor query A, nor
    answer A's queries, nor see A's tokens. Each check ends with a message the same path
    carries after the refused one (a link keeps its order), so none can still be on its way."""
    _, at = router
    a, b = KeySpace(A), KeySpace(B)
    with client(at, A) as a1, client(at, A) as a2, client(at, B) as b1, client(at, B) as b2:
        b_read, _ = keys_seen(b1, f"{a.prefix}/**")
        b_marks, _ = keys_seen(b1, b.all_data())
        a_seen, _ = keys_seen(a2, f"{a.prefix}/**")
        until(lambda: a.data("n", "p") in a_seen, "A's put reaching A", act=lambda: a1.put(a.data("n", "p"), b"1"))
        until(lambda: b.data("m", "1") in b_marks, "B's put reaching B", act=lambda: b2.put(b.data("m", "1"), b"m"))
        assert b_read == []
        for _ in range(3):
            b1.put(a.data("n", "p"), b"from B")
        b2_marks, _ = keys_seen(b2, b.all_data())
        until(lambda: b.data("m", "2") in b2_marks, "B's later put reaching B",
              act=lambda: b1.put(b.data("m", "2"), b"m"))
        until(lambda: a.data("m", "3") in a_seen, "A's later put reaching A", act=lambda: a1.put(a.data("m", "3"), b""))
        assert a.data("n", "p") in a_seen and set(a_seen) <= {a.data("n", "p"), a.data("m", "3")}
        _answers = a2.declare_queryable(a.finished(), lambda q: q.reply(a.finished(), b"done"))
        _b_answers = b1.declare_queryable(a.start(), lambda q: q.reply(a.start(), b"from B"))
        _token = a2.liveliness().declare_token(a.workers("w"))
        until(lambda: any(r.ok for r in a1.get(a.finished(), timeout=2)), "A answering A")
        until(lambda: any(r.ok for r in a1.liveliness().get(a.workers(), timeout=2)), "A seeing A's token")
        assert [r.ok for r in b1.get(a.finished(), timeout=2) if r.ok] == []
        assert [r.ok for r in b1.liveliness().get(a.workers(), timeout=2) if r.ok] == []
        assert [r.ok for r in a1.get(a.start(), timeout=2) if r.ok] == []


def test_a_watcher_reads_the_data_but_writes_nothing_and_sees_no_control(router):
    _, at = router
    a = KeySpace(A)
    with client(at, A) as a1, client(at, A) as a2, watcher(at, A) as w:
        w_seen, _ = keys_seen(w, f"{a.prefix}/**")
        a_seen, _ = keys_seen(a2, f"{a.prefix}/**")
        until(lambda: a.data("n", "p") in w_seen, "A's data reaching the watcher",
              act=lambda: a1.put(a.data("n", "p"), b"1"))
        a1.put(a.run_control(), b"ctl")
        until(lambda: a.data("m", "1") in w_seen, "A's later data reaching the watcher",
              act=lambda: a1.put(a.data("m", "1"), b""))
        assert a.run_control() in a_seen and a.run_control() not in w_seen
        for _ in range(3):
            w.put(a.data("evil", "p"), b"from the watcher")
        flushed, _ = keys_seen(w, a.data("flush", "p"))  # declared after its puts: routed once they were taken
        until(lambda: flushed, "the watcher's later subscription", act=lambda: a1.put(a.data("flush", "p"), b""))
        until(lambda: a.data("m", "2") in a_seen, "A's later put reaching A", act=lambda: a1.put(a.data("m", "2"), b""))
        assert a.data("evil", "p") not in a_seen


def test_routers_linked_by_connect_route_between_their_clients(routers, secret, router):
    _, first = router
    second = endpoint(free_port())
    routers("--secret", str(secret), "--listen", second, "--connect", first, "--namespace", A).wait_started()
    a = KeySpace(A)
    with client(first, A) as c1, client(second, A) as c2:
        seen1, _ = keys_seen(c1, a.all_data())
        seen2, _ = keys_seen(c2, a.all_data())
        until(lambda: a.data("one", "p") in seen2, "a put from the first router's client reaching the second's",
              act=lambda: c1.put(a.data("one", "p"), b""))
        until(lambda: a.data("two", "p") in seen1, "a put from the second router's client reaching the first's",
              act=lambda: c2.put(a.data("two", "p"), b""))


@pytest.mark.skipif(shutil.which("openssl") is None, reason="the test makes certificates with openssl")
def test_over_mutual_tls_clients_with_a_certificate_of_its_ca_exchange_and_others_are_refused(routers, secret,
                                                                                            tmp_path):
    files = certificates(tmp_path)
    at = f"tls/127.0.0.1:{free_port()}"
    routers("--secret", str(secret), "--listen", at, "--namespace", A, *_tls_flags(files)).wait_started()
    a = KeySpace(A)

    def tls_client(cert: str, key: str) -> zenoh.Session:
        access = {**RunAccess.create(A, SECRET).client_config(A),
                  **TlsFiles(files["ca.pem"], files[cert], files[key]).session_config()}
        return zenoh.open(client_config(connect=[at], access=access, shared_memory=False))

    with tls_client("client.pem", "client.key") as c1, tls_client("client.pem", "client.key") as c2:
        seen, _ = keys_seen(c2, a.all_data())
        until(lambda: a.data("n", "p") in seen, "a put over TLS", act=lambda: c1.put(a.data("n", "p"), b""))
    with pytest.raises(zenoh.ZError):
        tls_client("rogue.pem", "rogue.key").close()


def certificates(folder: Path) -> dict[str, str]:
    """A CA; a certificate it signs for 127.0.0.1, the router's and the clients'; a self-signed rogue."""
    def run(*args: str) -> None:
        subprocess.run(args, cwd=folder, check=True, capture_output=True, timeout=BOUND_S)

    run("openssl", "req", "-x509", "-newkey", "rsa:2048", "-nodes", "-keyout", "ca.key", "-out", "ca.pem", "-days", "1",
        "-subj", "/CN=lab-ca")
    (folder / "san.ext").write_text("subjectAltName=IP:127.0.0.1\n")
    run("openssl", "req", "-newkey", "rsa:2048", "-nodes", "-keyout", "client.key", "-out", "client.csr",
        "-subj", "/CN=client")
    run("openssl", "x509", "-req", "-in", "client.csr", "-CA", "ca.pem", "-CAkey", "ca.key", "-CAcreateserial",
        "-out", "client.pem", "-days", "1", "-extfile", "san.ext")
    run("openssl", "req", "-x509", "-newkey", "rsa:2048", "-nodes", "-keyout", "rogue.key", "-out", "rogue.pem",
        "-days", "1", "-subj", "/CN=rogue", "-addext", "subjectAltName=IP:127.0.0.1")
    return {name: str(folder / name) for name in ("ca.pem", "client.pem", "client.key", "rogue.pem", "rogue.key")}


def _tls_flags(files: dict[str, str]) -> list[str]:
    return ["--tls-ca", files["ca.pem"], "--tls-cert", files["client.pem"], "--tls-key", files["client.key"]]


# ---------------------------------------------------------------------------------------------
# Errors and stopping
# ---------------------------------------------------------------------------------------------
def _start(*args: str) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "retriever", "router", *args], cwd=ROOT, env=_env(),
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def test_bad_inputs_are_refused_by_name_with_the_fix(secret, tmp_path):
    at = endpoint(free_port())
    readable = tmp_path / "open.key"
    readable.write_bytes(SECRET)
    readable.chmod(0o644)
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        busy = endpoint(taken.getsockname()[1])
        cases = {
            "no secret": (("--listen", at), r"^error: retriever router needs --secret FILE.*\nhint: retriever secret new"),
            "no such secret": (("--secret", str(tmp_path / "none.key"), "--listen", at),
                               r"^error: cannot read the secret file .*none\.key: No such file or directory\n"),
            "a secret others read": (("--secret", str(readable), "--listen", at),
                                     r"^error: the secret file .*open\.key can be read by other users \(mode 644\)\n"
                                     r"hint: chmod 600 "),
            "no endpoint": (("--secret", str(secret), "--listen", "localhost"),
                            r"^error: 'localhost' is no endpoint: write tcp/HOST:PORT"),
            "a port in use": (("--secret", str(secret), "--listen", busy),
                              rf"^error: cannot listen on {re.escape(busy)}: Address already in use\n"
                              r"hint: something else listens on port \d+ .*choose another port with --listen"),
            "a bad namespace": (("--secret", str(secret), "--listen", at, "--namespace", "lab/a"),
                                r"^error: namespace 'lab/a' cannot be a Zenoh key chunk"),
            "a lease out of bounds": (("--secret", str(secret), "--listen", at, "--lease", "0"),
                                      r"^error: --lease must be seconds from 0\.1 to 3600, got 0\n"),
            "a plain endpoint with TLS": (("--secret", str(secret), "--listen", at, *_tls_flags(certificates(tmp_path))),
                                          r"^error: with TLS every endpoint is tls/HOST:PORT, not tcp/"),
            "no router to link to": (("--secret", str(secret), "--listen", at, "--connect", endpoint(free_port())),
                                     r"^error: no router at tcp/127\.0\.0\.1:\d+ admitted this one: nothing listens "
                                     r"there\nhint: start that router first"),
        }
        running = {case: _start(*args) for case, (args, _) in cases.items()}  # at once: each is mostly its start
        for case, (_, expected) in cases.items():
            _, stderr = running[case].communicate(timeout=BOUND_S)
            assert running[case].returncode == 1 and "Traceback" not in stderr, f"{case}: {stderr}"
            assert re.search(expected, stderr, re.S), f"{case}: {stderr}"


def test_sigterm_stops_it_at_once_and_leaves_nothing(router):
    proc, at = router
    folders = set(Path(tempfile.gettempdir()).glob(f"{ROUTER_FOLDER}-{proc.proc.pid}-*"))
    assert folders, "its dictionary's private folder"
    with client(at, A):
        began = time.monotonic()
        os.kill(proc.proc.pid, signal.SIGTERM)
        assert proc.proc.wait(BOUND_S) == 0, proc.stderr()
    assert time.monotonic() - began < 10.0, "a stop within its poll of the signal and Zenoh's close"
    assert proc.stderr().splitlines()[-1] == "retriever router stopped"
    assert not any(folder.exists() for folder in folders)
    with pytest.raises(ProcessLookupError):
        os.kill(proc.proc.pid, 0)
