"""A worker daemon takes a deployment's requests only sealed with a key of the secret (issue 40 review, F1).

The namespace's passwords sit in every daemon's dictionary and, in routed deployments, in every
flow's spec; with them alone a session could once send a daemon a prepare naming a live run's id
and a hub of its choosing, then a spawn: the daemon derived that run's passwords and started a
process linked into it. Now every op but ``info`` is sealed by the coordinator with a key derived
from the secret itself (access.daemon_control_key; protocol/seal.py RequestSealer), and the daemon
takes each sealed request once. A real daemon with a secret and a session holding the namespace's
passwords: its requests, unsealed or sealed with another key, are refused and counted, nothing is
prepared or started; a request sealed with the secret's key is taken (the positive control), and
the same request replayed is refused. The normal deployment is test_run_passwords' and test_spawn_key's.
"""

from __future__ import annotations

import tempfile
import time
from pathlib import Path

import pytest
import zenoh

from retriever.backends.zenoh.access import RunAccess, daemon_control_key
from retriever.backends.zenoh.folders import DAEMON_FOLDER
from retriever.backends.zenoh.hub import endpoint, free_port
from retriever.backends.zenoh.origin import sign
from retriever.backends.zenoh.protocol import (EndRequest, InfoRequest, PrepareRequest, Record,
                                               RequestOpener, RequestSealer, SpawnRequest, decode_reply,
                                               error_message)
from retriever.backends.zenoh.protocol.seal import NONCE_BYTES, REQUEST_MAX_AGE_S, REQUEST_NONCES, REQUEST_TIME_BYTES
from retriever.backends.zenoh.wire import KeySpace, WireError
from tests.backends.zenoh.test_daemon import (BOUND_S, ROOT, SECRET, _client, _ir_doc, namespace,  # noqa: F401
                                              workers)

from .specs import run_spec

KEY = daemon_control_key(SECRET.encode(), "lab")
AT = "retriever/lab/ctl/w1"


class Clock:
    """Logical time, in ns since the epoch."""

    def __init__(self, now: int = 1_700_000_000 * 10**9):
        self.now = now

    def __call__(self) -> int:
        return self.now


def test_a_sealed_request_opens_once_with_the_secrets_key_alone():
    clock = Clock()
    sealer, opener = RequestSealer(KEY, clock), RequestOpener(KEY, clock)
    payload = InfoRequest().encode()
    seal = sealer.seal(AT, payload)
    opener.open(AT, payload, seal)
    with pytest.raises(WireError, match="taken before: a replay"):
        opener.open(AT, payload, seal)
    with pytest.raises(WireError, match="without the coordinator's seal"):
        opener.open(AT, payload, None)
    other = RequestSealer(daemon_control_key(b"another secret of 32 bytes......", "lab"), clock)
    for bad_at, bad_payload, bad_seal in ((AT, payload, other.seal(AT, payload)),  # another secret's key
                                          ("retriever/lab/ctl/w2", payload, sealer.seal(AT, payload)),  # another daemon
                                          (AT, payload + b"x", sealer.seal(AT, payload)),  # altered
                                          (AT, payload, sealer.seal(AT, payload)[:-1] + b"\0")):
        with pytest.raises(WireError, match="no holder of the deployment secret sealed|without the coordinator"):
            opener.open(bad_at, bad_payload, bad_seal)
    # a namespace password's HMAC is no key of the secret: a holder of the password alone forges nothing
    password_key = RunAccess.create("lab", SECRET.encode()).run_password.encode()
    head = bytes(NONCE_BYTES) + clock.now.to_bytes(REQUEST_TIME_BYTES, "big")
    with pytest.raises(WireError, match="no holder of the deployment secret sealed"):
        opener.open(AT, payload, head + sign(password_key, AT, head + payload))
    # too old (a daemon restarted since remembers no nonce): refused by its time
    old = sealer.seal(AT, payload)
    clock.now += int(REQUEST_MAX_AGE_S * 1e9) + 1
    with pytest.raises(WireError, match="from this worker's clock"):
        opener.open(AT, payload, old)


def test_a_request_whose_nonce_was_forgotten_is_refused_by_its_time():
    clock = Clock()
    sealer, opener = RequestSealer(KEY, clock), RequestOpener(KEY, clock)
    payload = InfoRequest().encode()
    first = sealer.seal(AT, payload)
    opener.open(AT, payload, first)
    for _ in range(REQUEST_NONCES):  # the first nonce is forgotten
        clock.now += 1
        opener.open(AT, payload, sealer.seal(AT, payload))
    with pytest.raises(WireError, match="taken before: a replay"):
        opener.open(AT, payload, first)
    clock.now += 1
    opener.open(AT, payload, sealer.seal(AT, payload))  # a new one still is taken


def _ask(session: zenoh.Session, keys: KeySpace, name: str, request: Record, seal: bytes | None) -> Record:
    """``request`` to daemon ``name`` with ``seal`` as its attachment: its reply, or WireError with its refusal."""
    replies = list(session.get(keys.ctl(name), payload=request.encode(), attachment=seal, timeout=BOUND_S))
    assert replies, f"worker '{name}' did not answer {request.NAME}"
    if replies[0].ok is None:
        raise WireError(error_message(replies[0].err.payload.to_bytes()))
    return decode_reply(replies[0].ok.payload.to_bytes(), request.NAME)


def _run_folders(pid: int) -> list[Path]:
    return list(Path(tempfile.gettempdir()).glob(f"{DAEMON_FOLDER}-{pid}-run-*"))


def _children(parent: int) -> set[int]:
    return {int(pid) for task in Path(f"/proc/{parent}/task").iterdir()
            for pid in (task / "children").read_text().split()}


def test_the_namespaces_password_alone_prepares_and_starts_nothing(workers, namespace, tmp_path):
    secret = tmp_path / "secret"
    secret.write_text(SECRET)
    secret.chmod(0o600)
    port = free_port()
    daemon = workers("--name", "w1", "--listen", endpoint(port), "--namespace", namespace,
                     "--path", str(ROOT / "tests" / "deploy"), "--secret", str(secret)).wait_started()
    keys = KeySpace(namespace)
    ctl = keys.ctl("w1")
    insider_hub = endpoint(free_port())  # where the insider would have the run's process link
    prepare = PrepareRequest(run="5f3a9c0d1e2b", spec=run_spec(_ir_doc(), namespace, hub=insider_hub),
                             nodes=("counter",))
    spawn = SpawnRequest(run="5f3a9c0d1e2b", node="counter", mode=())
    wrong = RequestSealer(daemon_control_key(b"not the deployment's secret.....", namespace))
    access = RunAccess.create(namespace, SECRET.encode())  # the namespace's passwords: what every daemon holds
    with _client(port, access.session_config(access.write_dictionary(tmp_path))) as insider:
        token = insider.liveliness().declare_token(keys.deployment())  # as a coordinator would
        for request in (prepare, spawn, EndRequest(run="5f3a9c0d1e2b")):
            with pytest.raises(WireError, match="without the coordinator's seal"):
                _ask(insider, keys, "w1", request, None)
            with pytest.raises(WireError, match="no holder of the deployment secret sealed"):
                _ask(insider, keys, "w1", request, wrong.seal(ctl, request.encode()))
        info = _ask(insider, keys, "w1", InfoRequest(), None)  # info stays unsealed: it tells nothing secret
        assert info.counts.get("refused") == 6 and info.nodes == (), info.counts
        assert _run_folders(daemon.proc.pid) == [] and _children(daemon.proc.pid) == set()

        # positive control: sealed with the secret's key, the same prepare is taken; replayed, refused
        sealer = RequestSealer(daemon_control_key(SECRET.encode(), namespace))
        give_up = time.monotonic() + BOUND_S
        while True:
            seal = sealer.seal(ctl, prepare.encode())
            try:
                assert _ask(insider, keys, "w1", prepare, seal).nodes == ("counter",)
                break
            except WireError as e:  # the daemon has not seen the token yet (it travels in ms)
                assert "liveliness token" in str(e) and time.monotonic() < give_up, str(e)
        assert len(_run_folders(daemon.proc.pid)) == 1
        with pytest.raises(WireError, match="taken before: a replay"):
            _ask(insider, keys, "w1", prepare, seal)
        _ask(insider, keys, "w1", EndRequest(run=prepare.run), sealer.seal(ctl, EndRequest(run=prepare.run).encode()))
        token.undeclare()
    assert _children(daemon.proc.pid) == set()
    assert daemon.stop() == 0
    assert "it refused 7 control message(s)" in daemon.stderr(), daemon.stderr()
