"""A deployment's run passwords are its run's alone (issue 40 item 8; access.py).

A run's password was once the namespace's (HMAC of the secret and the namespace): one left on
disk by a killed ``retriever deploy`` (its run folder's dictionary), or a watcher's file, let a
stranger join every later deployment of the namespace, and link to every worker daemon. Now a
deployment's are derived for its run id, by the coordinator and by each daemon, from the secret
they hold. A real daemon and two real deployments, one after the other: with everything run 1
left (its flows' spec with the run's passwords, its watcher file), a stranger gets no session
with run 2's hub, its flows or the daemon; nor does a holder of the namespace's passwords with
the hub or the flows, nor one of run 2's with the daemon (no session of one kind links to one of
the other). Each refusal beside its positive control: run 2's own credentials open a session
there. A session is tried in client mode, which ``zenoh.open`` refuses at once when the one
endpoint it connects to admits it not.
"""

from __future__ import annotations

import json
import re
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import pytest
import zenoh

from retriever.backends.zenoh.access import RUN_USER, WATCH_USER, RunAccess, read_secret
from retriever.backends.zenoh.folders import DAEMON_FOLDER
from retriever.backends.zenoh.hub import endpoint, free_port, peer_config
from retriever.backends.zenoh.wire import KeySpace
from tests.backends.zenoh.test_daemon import BOUND_S, ROOT, SECRET, _env, namespace, workers  # noqa: F401

WATCH_LINE = re.compile(r"watch it read-only with zenoh\.Config\.from_file\('([^']+)'\)")


def test_a_deployments_passwords_are_derived_for_its_run():
    secret = SECRET.encode()
    one, two = RunAccess.create("lab", secret, run="r1"), RunAccess.create("lab", secret, run="r2")
    namespace = RunAccess.create("lab", secret)
    assert one == RunAccess.create("lab", secret, run="r1")  # what a daemon derives is the coordinator's
    passwords = [one.run_password, one.watch_password, two.run_password, two.watch_password,
                 namespace.run_password, namespace.watch_password]
    assert len(set(passwords)) == len(passwords), "a password shared by two runs, or a run and its namespace"


class Deploy:
    """``retriever deploy`` of lifecycle_flows' pipeline as a process, its stderr read on a thread."""

    def __init__(self, port: int, namespace: str, secret: Path, duration: float):
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "retriever.cli", "deploy", "tests/backends/zenoh/lifecycle_flows.py:pipe",
             "--connect", endpoint(port), "--namespace", namespace, "--secret", str(secret),
             "--duration", str(duration)],
            cwd=ROOT, env=_env(), stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
        self.lines: list[str] = []
        self.watch: Path | None = None
        self.printed = threading.Event()
        threading.Thread(target=self._read, daemon=True).start()

    def _read(self) -> None:
        for line in self.proc.stderr:
            self.lines.append(line)
            found = WATCH_LINE.search(line)
            if found and self.watch is None:
                self.watch = Path(found.group(1))
                self.printed.set()
        self.printed.set()

    def watch_config(self) -> dict:
        """The watcher file it wrote (JSON after its comment lines), once its hub is up."""
        assert self.printed.wait(BOUND_S) and self.watch is not None, "".join(self.lines)
        return json.loads("".join(line for line in self.watch.read_text().splitlines(True)
                                  if not line.startswith("//")))

    def end(self) -> None:
        if self.proc.poll() is None:
            self.proc.terminate()  # the deployment stops as at Ctrl-C
        try:
            self.proc.wait(timeout=BOUND_S)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait()


def _flow_spec(daemon_pid: int, seen: set[Path]) -> tuple[Path, dict]:
    """The spec the daemon wrote for a run's flows (their passwords) in a run folder not in
    ``seen``: polled for (bounded) until the daemon prepared the run."""
    give_up = time.monotonic() + BOUND_S
    while time.monotonic() < give_up:
        for folder in Path(tempfile.gettempdir()).glob(f"{DAEMON_FOLDER}-{daemon_pid}-run-*"):
            try:
                if folder not in seen:
                    return folder, json.loads((folder / "spec.json").read_text())
            except (OSError, ValueError):  # being written
                pass
        time.sleep(0.05)
    raise AssertionError("the daemon prepared no run")


def _listening_ports(pids: set[int]) -> set[int]:
    """The TCP ports the processes ``pids`` listen on (Linux /proc)."""
    inodes = set()
    for pid in pids:
        for fd in Path(f"/proc/{pid}/fd").iterdir():
            try:
                target = str(fd.readlink())
            except OSError:
                continue
            if target.startswith("socket:["):
                inodes.add(target[8:-1])
    ports = set()
    for table in ("/proc/net/tcp", "/proc/net/tcp6"):
        for row in Path(table).read_text().splitlines()[1:]:
            fields = row.split()
            if fields[3] == "0A" and fields[9] in inodes:  # LISTEN
                ports.add(int(fields[1].rsplit(":", 1)[1], 16))
    return ports


def _children(parent: int) -> set[int]:
    return {int(pid) for task in Path(f"/proc/{parent}/task").iterdir()
            for pid in (task / "children").read_text().split()}


def _admits(at: str, user: str, password: str) -> bool:
    """Whether the session listening at ``at`` admits a client proving ``user``'s ``password``."""
    config = peer_config(connect=[at])
    config.insert_json5("mode", '"client"')
    config.insert_json5("transport/auth/usrpwd", json.dumps({"user": user, "password": password}))
    try:
        session = zenoh.open(config)
    except zenoh.ZError:
        return False
    session.close()
    return True


def test_a_run_left_behind_opens_no_later_run_nor_a_daemon(workers, namespace, tmp_path):
    secret = tmp_path / "secret"
    secret.write_text(SECRET)
    secret.chmod(0o600)
    port = free_port()
    daemon = workers("--name", "w1", "--listen", endpoint(port), "--namespace", namespace,
                     "--path", str(ROOT / "tests" / "backends" / "zenoh"), "--secret", str(secret)).wait_started()
    first = Deploy(port, namespace, secret, duration=1.0)
    try:
        left_watcher = first.watch_config()  # what a killed run leaves: its watcher file, its flows' spec
        folder, left_spec = _flow_spec(daemon.proc.pid, set())
        left = left_spec["access"]
        assert first.proc.wait(timeout=BOUND_S) == 0, "".join(first.lines)
    finally:
        first.end()
    second = Deploy(port, namespace, secret, duration=60.0)
    try:
        watcher = second.watch_config()
        hub = watcher["connect"]["endpoints"][0]
        _, spec = _flow_spec(daemon.proc.pid, {folder})
        own = spec["access"]
        keys = KeySpace(namespace)
        seen = threading.Event()
        # run 2's own watcher file joins it and sees its data: its flows are up (and linked)
        with zenoh.open(zenoh.Config.from_json5(json.dumps(watcher))) as watching:
            sub = watching.declare_subscriber(keys.all_data(), lambda sample: seen.set())
            assert seen.wait(BOUND_S), "run 2's own watcher saw no data"
            sub.undeclare()
        flows = _listening_ports(_children(daemon.proc.pid))
        assert flows, "run 2's flows listen nowhere"
        daemon_at, flows_at = endpoint(port), [endpoint(p) for p in sorted(flows)]
        secret_bytes = read_secret(secret)
        namespace_access = RunAccess.create(namespace, secret_bytes)

        # positive controls: run 2's own credentials open a session at its hub and at each flow,
        # the namespace's at the daemon
        assert _admits(hub, RUN_USER, own["run_password"])
        assert all(_admits(at, RUN_USER, own["run_password"]) for at in flows_at)
        assert _admits(daemon_at, RUN_USER, namespace_access.run_password)

        # run 1's passwords open nothing: not run 2's hub, flows or watchers' place, nor the daemon
        assert left["run_password"] != own["run_password"]
        for at in (hub, *flows_at, daemon_at):
            assert not _admits(at, RUN_USER, left["run_password"]), f"run 1's password opened {at}"
        assert not _admits(hub, WATCH_USER, left["watch_password"])
        stale = dict(left_watcher, connect={"endpoints": [hub]})  # run 1's watcher file, aimed at run 2
        with pytest.raises(zenoh.ZError):
            zenoh.open(zenoh.Config.from_json5(json.dumps(stale))).close()

        # no session of one kind admits the other: the namespace's passwords open neither the hub
        # nor a flow, run 2's not the daemon
        for at in (hub, *flows_at):
            assert not _admits(at, RUN_USER, namespace_access.run_password), f"the namespace's password opened {at}"
        assert not _admits(hub, WATCH_USER, namespace_access.watch_password)
        assert not _admits(daemon_at, RUN_USER, own["run_password"])
        # which are those the coordinator and the daemon each derived for run 2's id
        assert own["run_password"] == RunAccess.create(namespace, secret_bytes, run=_run_id(second)).run_password
    finally:
        second.end()


def _run_id(deploy: Deploy) -> str:
    """The run id of a running deployment, as ``retriever status`` answers it."""
    return _status(deploy)["run"]


def _status(deploy: Deploy) -> dict:
    from retriever.backends.zenoh.deploy import ask_deployment

    args = deploy.proc.args
    at, namespace, secret = (args[args.index(flag) + 1] for flag in ("--connect", "--namespace", "--secret"))
    answer = ask_deployment([at], namespace, "status", secret=secret)
    assert answer is not None, "no deployment answered status"
    return answer
