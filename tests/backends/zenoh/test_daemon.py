"""Worker daemons (``retriever-worker``) and ``retriever workers`` (issue 18; daemon/).

Daemons run as real processes (``python -m retriever.cli worker``) on loopback ports picked by
the test; a plain Zenoh session stands for a coordinator or a stranger. Every process a test
starts is killed by its PID at the end, and every wait is bounded.
"""

from __future__ import annotations

import copy
import functools
import hashlib
import os
import re
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import pytest
import zenoh

from retriever import read_log
from retriever.backends.zenoh.daemon import (
    CONFIG_KEYS,
    DEFAULT_LISTEN,
    WorkerError,
    ask,
    load_settings,
    module_allowed,
    open_access,
    reap_stale_folders,
    refusal,
)
from retriever.backends.zenoh.hub import endpoint, free_port, peer_config
from retriever.backends.zenoh.origin import KEY_BYTES
from retriever.backends.zenoh.protocol import (PROTOCOL_VERSION, EndRequest, ErrorReply, InfoReply, InfoRequest,
                                               PrepareRequest, RunSpec, SignalRequest, SpawnRequest, error_message)
from retriever.backends.zenoh.protocol.schema import pack
from retriever.backends.zenoh.wire import WIRE_VERSION, KeySpace

from .specs import run_spec

ROOT = Path(__file__).resolve().parents[3]
BOUND_S = 60.0  # a bound on any wait, never a speed check
SECRET = "a deployment secret of 32 bytes."


def _env(first_on_path: Path | None = None) -> dict[str, str]:
    env = {k: v for k, v in os.environ.items() if k not in ("FORCE_COLOR", "PYTHONPATH")}
    path = os.pathsep.join(str(p) for p in (first_on_path, ROOT) if p is not None)
    env.update(PYTHONPATH=path, NO_COLOR="1", PYTHONDONTWRITEBYTECODE="1", COLUMNS="200")
    return env


def _cli(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "retriever.cli", *args], cwd=ROOT, env=_env(),
                          capture_output=True, text=True, timeout=BOUND_S)


class Worker:
    """A daemon process, and the lines of its stderr (read on a thread). A subclass runs another
    long-running command: its ``COMMAND``, the line it ``says_started`` with, its ``START_S``."""

    COMMAND, WHAT, START_S = "worker", "worker", BOUND_S

    def __init__(self, *args: str, first_on_path: Path | None = None):
        self.proc = subprocess.Popen([sys.executable, "-m", "retriever.cli", self.COMMAND, *args], cwd=ROOT,
                                     env=_env(first_on_path),
                                     stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
        self.lines: list[str] = []
        self.started = threading.Event()  # its start line came, or its stderr ended without one
        self.reader = threading.Thread(target=self._read, daemon=True)
        self.reader.start()

    def _read(self) -> None:
        for line in self.proc.stderr:
            self.lines.append(line)
            if self.says_started(line):
                self.started.set()
        self.started.set()

    @staticmethod
    def says_started(line: str) -> bool:
        return line.startswith("retriever-worker '") and " in namespace '" in line

    def wait_started(self) -> Worker:
        assert self.started.wait(self.START_S) and self.proc.poll() is None, \
            f"the {self.WHAT} did not start:\n" + self.stderr()
        return self

    def stop(self, signum: int = signal.SIGTERM) -> int:
        os.kill(self.proc.pid, signum)
        return self.proc.wait(BOUND_S)

    def stderr(self) -> str:
        if self.proc.poll() is not None:
            self.reader.join(BOUND_S)
        return "".join(self.lines)

    def kill(self) -> None:
        if self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait()


@pytest.fixture
def namespace() -> str:
    return f"daemon-{os.getpid()}-{time.monotonic_ns() % 10**9}"


@pytest.fixture
def workers():
    """Start workers (``workers(*args)``); each is killed at the end."""
    started: list[Worker] = []

    def start(*args: str, first_on_path: Path | None = None) -> Worker:
        started.append(Worker(*args, first_on_path=first_on_path))
        return started[-1]

    yield start
    for worker in started:
        worker.kill()


def _client(port: int, access: dict[str, str] | None = None) -> zenoh.Session:
    config = peer_config(connect=[endpoint(port)], access=access)
    config.insert_json5("mode", '"client"')
    return zenoh.open(config)


def _refused(session: zenoh.Session, namespace: str, name: str, op: str, fields: object) -> str:
    """What worker ``name``'s error reply says to a request no record makes (an op it does not
    know, a field a coordinator never sends): hand-made, as an insider may send it."""
    replies = list(session.get(KeySpace(namespace).ctl(name), payload=pack([WIRE_VERSION, op, fields]),
                               timeout=BOUND_S))
    assert len(replies) == 1 and replies[0].ok is None, f"worker '{name}' took {op} {fields!r:.200}"
    return error_message(replies[0].err.payload.to_bytes())


def _live(session: zenoh.Session, keys: KeySpace) -> list[str]:
    return sorted(str(r.ok.key_expr) for r in session.liveliness().get(keys.workers(), timeout=2.0) if r.ok is not None)


# ---------------------------------------------------------------------------------------------
# A daemon on a real session
# ---------------------------------------------------------------------------------------------
def test_a_daemon_announces_itself_and_answers_info(workers, namespace):
    port = free_port()
    worker = workers("--name", "w1", "--labels", "gpu,arm", "--listen", endpoint(port), "--namespace", namespace,
                     "--insecure").wait_started()
    keys = KeySpace(namespace)
    with _client(port) as session:
        assert _live(session, keys) == [keys.workers("w1")]
        before = time.time_ns()
        info = ask(session, namespace, "w1", InfoRequest())
        after = time.time_ns()
    assert info.protocol == PROTOCOL_VERSION == 2
    assert (info.name, info.labels, info.nodes) == ("w1", ("gpu", "arm"), ())
    assert (info.host, info.pid) == (socket.gethostname(), worker.proc.pid)
    assert info.python == ".".join(map(str, sys.version_info[:3]))
    assert info.packages["retriever"] and info.packages["eclipse-zenoh"]
    assert before - 10**9 < info.clock_ns < after + 10**9, "one host, one clock (a sanity bound, not a speed check)"
    assert worker.stop() == 0
    err = worker.stderr()
    assert "warning: retriever-worker 'w1' runs with --insecure" in err and "trusted network" in err
    assert f"retriever-worker 'w1' in namespace '{namespace}'; listening on {endpoint(port)}; labels gpu, arm; " \
           "flows from retriever" in err


def test_retriever_workers_lists_two_daemons_with_their_labels(workers, namespace):
    """Two daemons, the second linked to the first: `retriever workers` connects to the first
    only, which routes for it, and lists both."""
    first, second = free_port(), free_port()
    a = workers("--name", "alpha", "--labels", "gpu,arm", "--listen", endpoint(first), "--namespace", namespace,
                "--insecure")
    a.wait_started()
    b = workers("--name", "beta", "--labels", "cpu", "--listen", endpoint(second), "--connect", endpoint(first),
                "--namespace", namespace, "--insecure")
    b.wait_started()
    keys = KeySpace(namespace)
    seen, both = set(), threading.Event()

    def on_token(sample) -> None:
        seen.add(str(sample.key_expr))
        if len(seen) == 2:
            both.set()

    with _client(first) as session:  # the first daemon knows the second's token
        session.liveliness().declare_subscriber(keys.workers(), on_token, history=True)
        assert both.wait(BOUND_S), seen
    result = _cli("workers", "--connect", endpoint(first), "--namespace", namespace, "--insecure")
    assert result.returncode == 0, result.stderr
    rows = {line.split("│")[1].strip(): [cell.strip() for cell in line.split("│")[2:-1]]
            for line in result.stdout.splitlines() if line.startswith("│")}
    assert set(rows) == {"alpha", "beta"}, result.stdout
    host = socket.gethostname()
    assert rows["alpha"][:3] == ["gpu, arm", host, str(a.proc.pid)]
    assert rows["beta"][:3] == ["cpu", host, str(b.proc.pid)]
    for labels, _, _, version, offset, nodes in rows.values():
        assert version == "0.1.0" and nodes == "-"
        assert offset.endswith(" ms") and abs(float(offset[:-3])) < 1000, offset  # one host: a sanity bound
    assert "name" in result.stdout and "clock offset" in result.stdout


def test_daemons_that_are_not_linked_are_listed_through_a_connect_each_and_the_listing_says_so(workers, namespace):
    """Daemons find each other only through --connect: through the first of two unlinked ones,
    `retriever workers` lists it alone and says how the others are found; given both, both."""
    first, second = free_port(), free_port()
    for name, port in (("alpha", first), ("beta", second)):
        workers("--name", name, "--listen", endpoint(port), "--namespace", namespace, "--insecure").wait_started()

    def listed(*ports: int) -> tuple[set[str], str]:
        result = _cli("workers", *(arg for port in ports for arg in ("--connect", endpoint(port))),
                      "--namespace", namespace, "--insecure")
        assert result.returncode == 0, result.stderr
        rows = {line.split("│")[1].strip() for line in result.stdout.splitlines() if line.startswith("│")}
        return rows, result.stderr

    names, err = listed(first)
    assert names == {"alpha"}
    assert f"(the workers linked to {endpoint(first)}: a daemon is linked to those its --connect names and those " \
           "whose --connect names it; list the others with a --connect each)" in err, err
    assert listed(first, second)[0] == {"alpha", "beta"}


def test_no_workers_says_how_to_start_one(namespace):
    port = free_port()  # nothing listens there
    result = _cli("workers", "--connect", endpoint(port), "--namespace", namespace, "--insecure")
    assert result.returncode == 1, result.stderr  # found none: a script waiting for its workers can tell
    assert result.stdout.startswith(f"no workers in namespace '{namespace}' at {endpoint(port)}")
    assert "start one: retriever-worker --name NAME" in result.stdout
    assert f"warning: no session at {endpoint(port)}" in result.stderr


def test_a_second_worker_of_one_name_refuses_to_start(workers, namespace):
    first = free_port()
    a = workers("--name", "twin", "--listen", endpoint(first), "--namespace", namespace, "--insecure").wait_started()
    b = workers("--name", "twin", "--listen", endpoint(free_port()), "--connect", endpoint(first),
                "--namespace", namespace, "--insecure")
    assert b.proc.wait(BOUND_S) == 1
    err = b.stderr()
    assert f"error: a worker named 'twin' already runs in namespace '{namespace}' on host {socket.gethostname()}, " \
           f"pid {a.proc.pid}\nhint: pick another --name, or stop that worker first" in err, err
    assert "Traceback" not in err
    with _client(first) as session:  # the first goes on
        assert ask(session, namespace, "twin", InfoRequest()).pid == a.proc.pid


# ---------------------------------------------------------------------------------------------
# Who may join
# ---------------------------------------------------------------------------------------------
def test_a_worker_and_the_listing_need_a_secret_or_insecure(tmp_path):
    for command, args in (("retriever-worker", ["worker", "--name", "w"]), ("retriever workers", ["workers"])):
        result = _cli(*args)
        assert result.returncode == 1
        assert result.stderr.startswith(f"error: {command} needs --secret FILE (a deployment secret"), result.stderr
        assert "or --insecure" in result.stderr and "\nhint: retriever secret new lab.key" in result.stderr
        assert "Traceback" not in result.stderr
    secret = tmp_path / "secret"
    secret.write_text(SECRET)
    result = _cli("worker", "--name", "w", "--secret", str(secret), "--insecure")
    assert result.returncode == 1 and "takes --secret FILE or --insecure, not both" in result.stderr
    secret.chmod(0o644)
    result = _cli("worker", "--name", "w", "--secret", str(secret), "--listen", endpoint(free_port()))
    assert result.returncode == 1
    assert "can be read by other users (mode 644)\nhint: chmod 600" in result.stderr, result.stderr


def test_without_the_secret_a_peer_sees_nothing(workers, namespace, tmp_path):
    """A daemon with --secret admits only sessions that hold it: a plain Zenoh peer or client,
    or one with another secret, gets no session; it sees no token and no answer."""
    secret, other = tmp_path / "secret", tmp_path / "other"
    secret.write_text(SECRET)
    other.write_text(SECRET.upper())
    for path in (secret, other):
        path.chmod(0o600)
    port = free_port()
    workers("--name", "guarded", "--listen", endpoint(port), "--namespace", namespace,
            "--secret", str(secret)).wait_started()
    keys = KeySpace(namespace)
    with zenoh.open(peer_config(connect=[endpoint(port)])) as stranger:  # a peer's open does not fail
        assert _live(stranger, keys) == []
        assert [r for r in stranger.get(keys.ctl("guarded"), payload=InfoRequest().encode(),
                                        timeout=2.0)] == []
        assert list(stranger.info.peers_zid()) == [], "a stranger got a session with the worker"
    with pytest.raises(zenoh.ZError):  # a client's does
        _client(port)
    with open_access(namespace, str(other)) as wrong, pytest.raises(zenoh.ZError):
        _client(port, wrong)
    with open_access(namespace, str(secret)) as access, _client(port, access) as insider:
        assert _live(insider, keys) == [keys.workers("guarded")]
        assert ask(insider, namespace, "guarded", InfoRequest()).name == "guarded"
    listed = _cli("workers", "--connect", endpoint(port), "--namespace", namespace, "--secret", str(secret))
    assert listed.returncode == 0 and "guarded" in listed.stdout, listed.stdout + listed.stderr
    unlisted = _cli("workers", "--connect", endpoint(port), "--namespace", namespace, "--insecure")
    assert unlisted.returncode == 1 and unlisted.stdout.startswith("no workers"), unlisted.stdout
    assert "it wants another --secret" in unlisted.stderr


def test_garbage_and_unknown_ops_get_error_replies_and_the_daemon_goes_on(workers, namespace):
    port = free_port()
    worker = workers("--name", "w", "--listen", endpoint(port), "--namespace", namespace, "--insecure").wait_started()
    keys = KeySpace(namespace)
    unknown = pack([WIRE_VERSION, "frobnicate", {}])
    bad = [b"\xc1 garbage", None, unknown, b"\x93\x01\xa4info\x80",  # wire version 1
           b"\x93\x02\xa4info\x90"]  # args a list
    with _client(port) as session:
        for payload in bad:
            replies = list(session.get(keys.ctl("w"), payload=payload, timeout=BOUND_S))
            assert len(replies) == 1 and replies[0].ok is None, payload
            message = ErrorReply.decode(replies[0].err.payload.to_bytes()).message  # an error reply, exactly
            assert message, payload
            if payload == unknown:
                assert message == ("worker 'w' knows no op 'frobnicate' "
                                   "(it knows info, prepare, spawn, signal, end, usage)")
        assert _refused(session, namespace, "w", "frobnicate", {}).startswith("worker 'w' knows no op")
        info = ask(session, namespace, "w", InfoRequest())
    assert info.counts == {"refused": len(bad) + 1}
    assert worker.stop() == 0
    assert f"retriever-worker 'w' stopped; it refused {len(bad) + 1} control message(s)" in worker.stderr()


def _ir_doc(node_type: str = "deploy_flows:Counter") -> dict:
    """The netns tests' pipeline, as a worker with --path tests/deploy imports it (deploy_flows)."""
    from tests.deploy.deploy_flows import pipe

    doc = pipe.build_ir().doc
    for node in doc["nodes"]:
        node["type"] = node["type"].replace("tests.deploy.deploy_flows:", "deploy_flows:")
        if node["id"] == "counter":
            node["type"] = node_type
    return doc


def _until_token_seen(request):
    """Ask until the daemon has seen the coordinator's liveliness token (it travels in ms)."""
    give_up = time.monotonic() + BOUND_S
    while True:
        try:
            return request()
        except WorkerError as e:
            if "liveliness token" not in str(e) or time.monotonic() > give_up:
                raise
            time.sleep(0.02)


def test_a_coordinators_requests_are_checked_before_anything_is_imported_or_started(workers, namespace, tmp_path):
    """prepare, spawn, signal and end, from a session that may talk to the daemon (here: an
    insecure one) but asks for what a coordinator never would: each refused with an error reply
    that says why, nothing imported (a marker module would write a file), nothing started."""
    marker = tmp_path / "imported"
    (tmp_path / "evil_flows.py").write_text(f"open({str(marker)!r}, 'w').close()\n")
    port = free_port()
    worker = workers("--name", "w", "--listen", endpoint(port), "--namespace", namespace, "--insecure",
                     "--path", str(ROOT / "tests" / "deploy")).wait_started()
    refused = {
        ("prepare", "os:system"): "does not import flow classes from module 'os'",
        ("prepare", "evil_flows:Flow"): "does not import flow classes from module 'evil_flows'",
        ("spawn", None): "has no run",
        ("signal", None): "has no run",
        ("end", None): "has no run",
        ("prepare", "deploy_flows:Nowhere.__init__"): None,  # allowed module: found, not imported here
    }
    with _client(port) as session:
        with pytest.raises(WorkerError, match=r"prepares runs only for a coordinator whose liveliness token"):
            ask(session, namespace, "w", PrepareRequest(run="r0", spec=run_spec(_ir_doc(), namespace), nodes=("counter",)))
        token = session.liveliness().declare_token(KeySpace(namespace).deployment())  # as a coordinator now
        for (op, node_type), expected in refused.items():
            request = {"prepare": lambda: PrepareRequest(run="r1", nodes=("counter",),
                                                         spec=run_spec(_ir_doc(node_type), namespace,
                                                                       hub=endpoint(port))),
                       "spawn": lambda: SpawnRequest(run="never-prepared", node="counter", mode=()),
                       "signal": lambda: SignalRequest(run="never-prepared", pid=1, signal=9),
                       "end": lambda: EndRequest(run="never-prepared")}[op]()
            if expected is None:  # the flow process would find it is no Flow, and say so
                _until_token_seen(lambda: ask(session, namespace, "w", request))
                continue
            with pytest.raises(WorkerError, match=expected):
                ask(session, namespace, "w", request)
        def spec(**fields) -> RunSpec:
            return run_spec(_ir_doc(), namespace, **fields)

        for args in ({"run": "r1", "spec": run_spec({"nodes": "x"}, namespace, plan={"nodes": []}),
                      "nodes": ["counter"]},
                     {"run": "r1", "spec": spec(), "nodes": ["nobody"]},
                     {"run": 7, "spec": spec(), "nodes": []},
                     # what the processes' start and time rest on: ids of Zenoh sessions, the clock's kind
                     {"run": "r1", "spec": spec(zids={"counter": "0bad"}), "nodes": ["counter"]},
                     {"run": "r1", "spec": spec(zids={"counter": "a" * 33}), "nodes": ["counter"]},
                     {"run": "r1", "spec": spec(zids={"ghost": "abc"}), "nodes": ["counter"]},
                     {"run": "r1", "spec": spec(zids={"counter": "abc"}), "nodes": ["counter"]},
                     {"run": "r1", "spec": spec(hub_zid="../etc"), "nodes": ["counter"]},
                     {"run": "r1", "spec": spec(virtual_time="yes"), "nodes": ["counter"]},
                     # the hub its flows join: the coordinator's to say (none, or no endpoint)
                     {"run": "r1", "spec": run_spec(_ir_doc(), namespace), "nodes": ["counter"]},
                     {"run": "r1", "spec": spec(hub="nowhere"), "nodes": ["counter"]}):
            with pytest.raises(WorkerError, match="refused prepare"):
                ask(session, namespace, "w", PrepareRequest(run=args["run"], spec=args["spec"],
                                                            nodes=tuple(args["nodes"])))
        assert "field 'zids' must be a map" in _refused(session, namespace, "w", "prepare", {
            "run": "r1", "spec": {**spec().to_fields(), "zids": ["abc"]}, "nodes": ["counter"]})
        deep = copy.deepcopy(_ir_doc())  # a param nested past Python's recursion limit (fuzz.py's `specs`)
        next(n for n in deep["nodes"] if n["id"] == "counter")["params"]["k"] = functools.reduce(
            lambda inner, _: [inner], range(900), [])
        with pytest.raises(WorkerError, match=r"params\.k nests arrays or objects deeper than Python's recursion"):
            ask(session, namespace, "w", PrepareRequest(run="r-deep", spec=run_spec(deep, namespace, plan=spec().plan),
                                                        nodes=("counter",)))
        ask(session, namespace, "w", PrepareRequest(run="r2", spec=run_spec(_ir_doc(), namespace, hub=endpoint(port)),
                                                    nodes=("counter",)))
        for args, expected in (({"node": "relay", "mode": ()}, "was not prepared"),
                               ({"node": "counter", "mode": ("--join", "1; rm -rf /", "2")}, "spawn mode"),
                               ({"node": "counter", "mode": ("--fresh", "-5", "-1")}, "spawn mode"),
                               ({"node": "counter", "mode": ("--join", "0", "1" + "0" * 26)}, "spawn mode"),
                               ({"node": "counter", "mode": ("--evil", "1", "2")}, "spawn mode")):
            with pytest.raises(WorkerError, match=expected):
                ask(session, namespace, "w", SpawnRequest(run="r2", **args))
        for key in ("ab" * 32, 7):  # the key its process signs with (origin.py) is the worker's to make
            assert "carries no key" in _refused(session, namespace, "w", "spawn",
                                                {"run": "r2", "node": "counter", "mode": [], "key": key})
        with pytest.raises(WorkerError, match="not a process of run r2"):
            ask(session, namespace, "w", SignalRequest(run="r2", pid=os.getpid(), signal=9))
        assert ask(session, namespace, "w", InfoRequest()).nodes == ()
        with pytest.raises(WorkerError, match=r"a message on ctl/<name> of \d+ bytes, past \d+: refused"):
            ask(session, namespace, "w", PrepareRequest(run="r3", spec=spec(argv=("x" * (9 << 20),)), nodes=()))
        ask(session, namespace, "w", EndRequest(run="r2"))
        token.undeclare()
    assert not marker.exists(), "a module named in a request was imported"
    assert worker.stop() == 0


def test_a_worker_refuses_nodes_whose_module_differs_from_the_coordinators_or_warns_when_told(
        workers, namespace, tmp_path):
    """The coordinator's copy of a flow module and a worker's (its --path) differ by a line: the
    deployment is refused before anything starts, naming each node, the module and both sha256;
    a worker started with --code-mismatch warn runs them, and the user of deploy is warned."""
    source = (ROOT / "tests" / "deploy" / "deploy_flows.py").read_text(encoding="utf-8")
    ours, theirs = tmp_path / "coordinator", tmp_path / "worker"
    for folder, line in ((ours, "# the coordinator's copy\n"), (theirs, "# a stale copy\n")):
        folder.mkdir()
        (folder / "drift_flows.py").write_text(source + line, encoding="utf-8")
    run_sha, here_sha = (hashlib.sha256((f / "drift_flows.py").read_bytes()).hexdigest() for f in (ours, theirs))
    mismatch = (f"the code of module drift_flows differs from the run's (run sha256 {run_sha}, here {here_sha} "
                f"in {theirs / 'drift_flows.py'})")
    for mode in ("refuse", "warn"):
        port = free_port()
        worker = workers("--name", f"w-{mode}", "--listen", endpoint(port), "--namespace", f"{namespace}-{mode}",
                         "--insecure", "--path", str(theirs), *(["--code-mismatch", mode] if mode == "warn" else []))
        worker.wait_started()
        log = tmp_path / f"{mode}.mcap"
        done = _cli("deploy", f"{ours / 'drift_flows.py'}:pipe", "--connect", endpoint(port), "--namespace",
                    f"{namespace}-{mode}", "--insecure", "--duration", "0.5", "--log", str(log))
        if mode == "refuse":
            assert done.returncode == 1, done.stderr
            assert "\nerror: worker 'w-refuse' refused prepare: worker 'w-refuse' will not run 3 of its node(s):\n" \
                in done.stderr, done.stderr
            for node in ("counter", "relay", "sink"):
                assert f"  - node '{node}': {mismatch}\n" in done.stderr, done.stderr
            assert ("hint: sync drift_flows on worker 'w-refuse' with the coordinator's copy, or start the worker "
                    "with --code-mismatch warn to run its own copy anyway") in done.stderr, done.stderr
            assert ask_nodes(port, f"{namespace}-{mode}", "w-refuse") == []
        else:
            assert done.returncode == 0, done.stderr
            assert (f"retriever: warning: worker 'w-warn' runs node 'counter': {mismatch}\n    hint: sync drift_flows "
                    "on worker 'w-warn' with the coordinator's copy (it runs its own copy: --code-mismatch warn)"
                    ) in done.stderr, done.stderr
            assert f"retriever-worker w-warn: warning: node 'counter': {mismatch}" in worker.stderr()
            # the log keeps it, and a replay names it first: the run ran other code than its IR's
            replayed = _cli("replay", str(log))
            assert (f"warning: in the run, worker 'w-warn' ran node 'counter': {mismatch}: what the replay finds "
                    "different may come from that change") in replayed.stderr, replayed.stderr
        assert worker.stop() == 0


ARGV_FLOWS = """
import sys

from retriever import Flow, Pipeline, Rate


class Argv(Flow):
    def step(self):
        return {"argv": " ".join(sys.argv)}


class Sink(Flow):
    def step(self, argv):
        return None


with Pipeline("argv") as pipe:
    (Argv() @ Rate(hz=10)).then(Sink() @ Rate(hz=10))
"""


def test_a_workers_flows_see_the_workers_argv_not_the_coordinators(workers, namespace, tmp_path):
    """issue 40: the worker took sys.argv from the spec the network sent, a channel for a stranger's
    arguments to a module that parses them when imported (regrtest wrote a file an insider named)."""
    (tmp_path / "argv_flows.py").write_text(ARGV_FLOWS, encoding="utf-8")
    port = free_port()
    worker = workers("--name", "w-argv", "--listen", endpoint(port), "--namespace", namespace, "--insecure",
                     "--path", str(tmp_path))
    worker.wait_started()
    log = tmp_path / "argv.mcap"
    done = _cli("deploy", f"{tmp_path / 'argv_flows.py'}:pipe", "--connect", endpoint(port), "--namespace", namespace,
                "--insecure", "--duration", "0.5", "--log", str(log), "--keep", "trace")
    assert done.returncode == 0, done.stderr
    seen = {e.value for e in read_log(log).trace().events_of("argv", "argv")}
    # (by word: the checkout's path may hold "deploy" too)
    assert seen and not any("deploy" in argv.split() or namespace in argv for argv in seen), seen
    assert worker.stop() == 0


ENV_FLOWS = """
import os

from retriever import Flow, Pipeline, Rate


class Env(Flow):
    def step(self):
        return {"env": " ".join(sorted(os.environ))}


class Sink(Flow):
    def step(self, env):
        return None


with Pipeline("env") as pipe:
    (Env() @ Rate(hz=10)).then(Sink() @ Rate(hz=10))
"""


def test_a_workers_flows_get_no_credential_from_its_environment_unless_it_is_named(workers, namespace, tmp_path,
                                                                                   monkeypatch):
    """issue 40: the planner of the always-allowed agents package sent the daemon's OPENAI_API_KEY
    to a URL an insider put in its params. A flow process gets the locale, paths and libraries'
    settings, and what --pass-env names."""
    (tmp_path / "env_flows.py").write_text(ENV_FLOWS, encoding="utf-8")
    monkeypatch.setenv("OPENAI_API_KEY", "sk-test-not-for-flows")
    monkeypatch.setenv("AWS_SECRET_ACCESS_KEY", "also-not")
    monkeypatch.setenv("MUJOCO_GL", "egl")
    seen = {}
    for name, extra in (("w-env", ()), ("w-env-pass", ("--pass-env", "OPENAI_API_KEY"))):
        port = free_port()
        worker = workers("--name", name, "--listen", endpoint(port), "--namespace", f"{namespace}-{name}",
                         "--insecure", "--path", str(tmp_path), *extra)
        worker.wait_started()
        log = tmp_path / f"{name}.mcap"
        done = _cli("deploy", f"{tmp_path / 'env_flows.py'}:pipe", "--connect", endpoint(port), "--namespace",
                    f"{namespace}-{name}", "--insecure", "--duration", "0.5", "--log", str(log), "--keep", "trace")
        assert done.returncode == 0, done.stderr
        seen[name] = set(read_log(log).trace().values_of("env", "env")[0].split())
        assert worker.stop() == 0
    assert {"PATH", "MUJOCO_GL"} <= seen["w-env"] and not {"OPENAI_API_KEY", "AWS_SECRET_ACCESS_KEY"} & seen["w-env"]
    assert "OPENAI_API_KEY" in seen["w-env-pass"] and "AWS_SECRET_ACCESS_KEY" not in seen["w-env-pass"]


def test_a_worker_refuses_to_start_a_node_whose_module_changed_after_it_was_prepared(workers, namespace, tmp_path):
    """The check is made again at each spawn (a restart may come long after prepare)."""
    module = tmp_path / "drift_flows.py"
    module.write_text((ROOT / "tests" / "deploy" / "deploy_flows.py").read_text(encoding="utf-8"), encoding="utf-8")
    doc = _ir_doc()
    for node in doc["nodes"]:
        node["type"] = node["type"].replace("deploy_flows:", "drift_flows:")
    run_sha = hashlib.sha256(module.read_bytes()).hexdigest()
    doc["metadata"]["code_sha256"] = {"drift_flows": run_sha}
    port = free_port()
    worker = workers("--name", "w", "--listen", endpoint(port), "--namespace", namespace, "--insecure",
                     "--path", str(tmp_path)).wait_started()
    with _client(port) as session:
        token = session.liveliness().declare_token(KeySpace(namespace).deployment())  # as a coordinator
        request = PrepareRequest(run="r1", spec=run_spec(doc, namespace, hub=endpoint(port)), nodes=("counter",))
        prepared = _until_token_seen(lambda: ask(session, namespace, "w", request))
        assert len(prepared.key) == KEY_BYTES  # its events' signing key (runs.Run)
        assert (prepared.nodes, prepared.warnings) == (("counter",), ())
        module.write_text(module.read_text(encoding="utf-8") + "# edited\n", encoding="utf-8")
        here_sha = hashlib.sha256(module.read_bytes()).hexdigest()
        with pytest.raises(WorkerError, match=re.escape(
                f"worker 'w' will not run node 'counter': the code of module drift_flows differs from the run's "
                f"(run sha256 {run_sha}, here {here_sha} in {module})")):
            ask(session, namespace, "w", SpawnRequest(run="r1", node="counter", mode=()))
        assert ask(session, namespace, "w", InfoRequest()).nodes == ()
        ask(session, namespace, "w", EndRequest(run="r1"))
        token.undeclare()
    assert worker.stop() == 0


def test_a_deployment_warns_of_a_worker_with_other_versions_of_the_runs_packages(workers, namespace, tmp_path):
    """A worker whose Python finds msgpack's metadata in another version first: the deploy runs,
    and says which package differs, in which versions."""
    from importlib.metadata import version

    (tmp_path / "msgpack-0.0.1.dist-info").mkdir()
    (tmp_path / "msgpack-0.0.1.dist-info" / "METADATA").write_text("Metadata-Version: 2.1\nName: msgpack\n"
                                                                     "Version: 0.0.1\n")
    port = free_port()
    worker = workers("--name", "w", "--listen", endpoint(port), "--namespace", namespace, "--insecure",
                     "--path", str(ROOT / "tests" / "deploy"), first_on_path=tmp_path).wait_started()
    done = _cli("deploy", "tests/deploy/deploy_flows.py:pipe", "--connect", endpoint(port), "--namespace", namespace,
                "--insecure", "--duration", "0.5")
    assert done.returncode == 0, done.stderr
    assert (f"retriever: warning: worker 'w' has other versions of the run's packages than this machine: "
            f"msgpack {version('msgpack')} here, 0.0.1 there\n") in done.stderr, done.stderr
    assert worker.stop() == 0


def ask_nodes(port: int, namespace: str, name: str) -> list[str]:
    """The nodes whose processes a worker runs now."""
    with _client(port) as session:
        return list(ask(session, namespace, name, InfoRequest()).nodes)


def _segments(pid: int) -> set[str]:
    with open(f"/proc/{pid}/maps", encoding="utf-8", errors="replace") as maps:
        return {line.rsplit(None, 1)[-1] for line in maps if line.rstrip().endswith(".zenoh")}


@pytest.mark.parametrize("signum", [signal.SIGTERM, signal.SIGINT])
def test_a_signal_stops_the_daemon_cleanly(workers, namespace, signum):
    """SIGTERM or SIGINT: exit 0. Its session has no shared memory, whose segments a process that
    outlives its runs would keep (hub.HUB_SHARED_MEMORY): it maps none."""
    port = free_port()
    worker = workers("--name", "w", "--listen", endpoint(port), "--namespace", namespace, "--insecure").wait_started()
    assert not _segments(worker.proc.pid), "the daemon maps Zenoh shared memory"
    assert worker.stop(signum) == 0, worker.stderr()
    assert "retriever-worker 'w' stopped" in worker.stderr()
    assert "Traceback" not in worker.stderr()


# ---------------------------------------------------------------------------------------------
# Settings
# ---------------------------------------------------------------------------------------------
def test_flags_override_the_config_file(tmp_path):
    (tmp_path / "flows").mkdir()
    config = tmp_path / "worker.toml"
    config.write_text('name = "arm-1"\nlabels = ["gpu", "arm"]\nlisten = ["tcp/0.0.0.0:7448"]\n'
                      'namespace = "lab"\npath = ["flows"]\nallow = ["mylab.*"]\nsecret = "worker.secret"\n')
    settings = load_settings(config)
    assert (settings.name, settings.labels, settings.listen, settings.connect, settings.namespace) == \
           ("arm-1", ("gpu", "arm"), ("tcp/0.0.0.0:7448",), (), "lab")
    # relative paths are the file's folder's, wherever the worker starts
    assert settings.path == (str(tmp_path / "flows"),) and settings.secret == str(tmp_path / "worker.secret")
    assert (settings.allow, settings.insecure, settings.code_mismatch) == (("mylab.*",), False, "refuse")
    assert load_settings(config, code_mismatch="warn").code_mismatch == "warn"
    flagged = load_settings(config, name="arm-2", labels="cpu", connect=["tcp/10.0.0.1:7447"], insecure=True)
    assert (flagged.name, flagged.labels, flagged.connect) == ("arm-2", ("cpu",), ("tcp/10.0.0.1:7447",))
    assert (flagged.secret, flagged.insecure) == (None, True), "a flag's --insecure replaces the file's secret"
    assert flagged.listen == ("tcp/0.0.0.0:7448",) and flagged.allow == ("mylab.*",)
    assert load_settings(name="bare").listen == (DEFAULT_LISTEN,) and load_settings(name="bare").namespace == "default"


def test_a_config_file_with_unknown_keys_or_wrong_values_is_refused(tmp_path):
    config = tmp_path / "worker.toml"
    config.write_text('nmae = "arm-1"\nlabels = "gpu,arm"\nlisten = [7447]\ninsecure = "yes"\npath = ["nowhere"]\n'
                      'code_mismatch = "ignore"\n')
    with pytest.raises(WorkerError) as refused:
        load_settings(config)
    assert str(refused.value) == (
        "the worker's settings have problems:\n"
        f"  - {config}: unknown key 'nmae' (a worker config has {', '.join(CONFIG_KEYS)})\n"
        "  - a worker needs a name: --name NAME (or name = \"...\" in --config)\n"
        "  - 'listen' must be a list of strings, got [7447]\n"
        f"  - --path {tmp_path / 'nowhere'}: no such directory\n"
        "  - 'insecure' must be true or false, got 'yes'\n"
        "  - 'code_mismatch' must be one of refuse, warn, got 'ignore'")
    config.write_text('name = "w"\nlabels = "gpu, arm"\n')
    assert load_settings(config).labels == ("gpu", "arm"), "labels as in --labels"
    with pytest.raises(WorkerError, match=r"a worker may not be named 'start': ctl/start is a run's own key"):
        load_settings(name="start")
    config.write_text("name = ")
    with pytest.raises(WorkerError, match=r"the worker config .* is not valid TOML"):
        load_settings(config)
    config.write_text('name = "w"\nfoo = 1\n')
    result = _cli("worker", "--config", str(config), "--insecure")
    assert result.returncode == 1
    assert result.stderr == (f"error: the worker's settings have problems:\n  - {config}: unknown key 'foo' "
                             f"(a worker config has {', '.join(CONFIG_KEYS)})\n"), result.stderr


def test_the_example_config_and_unit_are_in_deploy():
    import tomllib

    example = tomllib.loads((ROOT / "deploy" / "worker.example.toml").read_text())
    assert set(example) <= set(CONFIG_KEYS) and example["name"]
    unit = (ROOT / "deploy" / "retriever-worker.service").read_text()
    assert "ExecStart=" in unit and "--config" in unit and "Restart=on-failure" in unit and "User=" in unit


def test_retriever_worker_is_the_same_command():
    pyproject = (ROOT / "pyproject.toml").read_text()
    assert 'retriever-worker = "retriever.cli:worker_main"' in pyproject
    run = [sys.executable, "-c", "import sys; from retriever.cli import worker_main; "
                                 "sys.argv[0] = 'retriever-worker'; worker_main()"]
    shown = subprocess.run([*run, "--help"], cwd=ROOT, env=_env(), capture_output=True, text=True, timeout=BOUND_S)
    for flag in ("--name", "--labels", "--listen", "--connect", "--namespace", "--path", "--allow", "--secret",
                 "--insecure", "--config"):
        assert flag in shown.stdout, flag
    refused = subprocess.run([*run, "--name", "w"], cwd=ROOT, env=_env(), capture_output=True, text=True,
                             timeout=BOUND_S)
    assert refused.returncode == 1 and refused.stderr.startswith("error: retriever-worker needs --secret FILE")


# ---------------------------------------------------------------------------------------------
# The allowlist
# ---------------------------------------------------------------------------------------------
@pytest.fixture
def flows_dir(tmp_path) -> str:
    (tmp_path / "mylab").mkdir()
    (tmp_path / "mylab" / "__init__.py").write_text("")
    (tmp_path / "tool.py").write_text("")
    (tmp_path / "fast.cpython-311-x86_64-linux-gnu.so").write_text("")
    (tmp_path / "data.txt").write_text("")
    (tmp_path / "__pycache__").mkdir()
    (tmp_path / "not-a-module").mkdir()
    for shadowing in ("venv", "test"):  # folders without __init__.py: the standard library's package is imported
        (tmp_path / shadowing).mkdir()
        (tmp_path / shadowing / "__main__.py").write_text("")
    (tmp_path / "sys.py").write_text("")  # built in: no folder provides it
    (tmp_path / "os.py").write_text("")  # frozen: likewise
    return str(tmp_path)


@pytest.mark.parametrize("module, allow, on_path, allowed", [
    ("retriever", [], False, True),
    ("retriever.flow.base", [], False, True),
    ("agents.planner", [], False, False),  # issue 40: its planner sends an API key where its params say
    ("agents.planner", ["agents"], False, True),
    ("retrieverx", [], False, False),  # a package allows its modules, not its name's prefix
    ("Retriever", [], False, False),  # module names are case-sensitive
    ("os", [], False, False),
    ("subprocess", [], True, False),
    ("mylab", [], True, True),
    ("mylab.flows.arm", [], True, True),
    ("tool", [], True, True),
    ("fast", [], True, True),  # an extension module
    ("data", [], True, False),  # data.txt is no module
    ("__pycache__", [], True, False),
    ("mylab", [], False, False),  # not without its --path
    ("os.path", ["os"], False, True),
    ("other.x", ["other.*"], False, True),
    ("other", ["other.*"], False, False),  # the pattern says other's modules, not other itself
    ("lab_arm.flows", ["lab_*"], False, True),
    ("anything.at.all", ["*"], False, True),
    ("", ["*"], False, False),
    ("a..b", ["*"], False, False),
    ("os;rm", ["*"], False, False),
    ("venv.__main__", [], True, False),  # issue 40: `venv --clear` emptied a folder an insider chose
    ("test", [], True, False),
    ("test.__main__", [], True, False),  # regrtest wrote a file where an insider said
    ("sys", [], True, False),
    ("os", [], True, False),
    ("mylab.__main__", [], True, False),  # a package's command line, even of an allowed package
    ("retriever.__main__", [], False, False),
    ("mylab.__init__", [], True, False),
])
def test_module_allowed(flows_dir, module, allow, on_path, allowed):
    assert module_allowed(module, allow, [flows_dir] if on_path else []) is allowed


def test_a_refusal_names_the_module_and_the_flags_that_allow_it(flows_dir):
    message = refusal("os.path", ["other.*"], [flows_dir], worker="arm-1")
    assert message == (
        "worker 'arm-1' does not import flow classes from module 'os.path': its allowlist admits retriever "
        f"(always); modules in --path {flows_dir}: fast, mylab, tool; --allow other.*\n"
        "    hint: start the worker with --allow os.path, or with --path DIR for the folder holding os")


def test_retriever_deploy_takes_its_settings_from_a_config_file(workers, namespace, tmp_path):
    port = free_port()
    workers("--name", "w", "--listen", endpoint(port), "--namespace", namespace, "--insecure",
            "--path", str(ROOT / "tests" / "deploy")).wait_started()
    config = tmp_path / "deploy.toml"
    config.write_text(f'connect = "{endpoint(port)}"\nnamespace = "{namespace}"\ninsecure = true\n'
                      'duration = 1.0\nlog = "run.mcap"\n')
    done = _cli("deploy", "tests/deploy/deploy_flows.py:pipe", "--config", str(config))
    assert done.returncode == 0, done.stderr
    assert (tmp_path / "run.mcap").exists(), "the log goes where the file says, relative to it"
    config.write_text('connect = 7447\nlease = "long"\nport = 1\n')
    done = _cli("deploy", "tests/deploy/deploy_flows.py:pipe", "--config", str(config))
    assert done.returncode == 1
    for problem in ("'port' is no setting of retriever deploy", "'connect' must be an endpoint",
                    "'lease' must be a positive number of seconds"):
        assert problem in done.stderr, done.stderr


def test_the_example_deploy_config_reads():
    from retriever.backends.zenoh.deploy import load_deploy_config

    settings = load_deploy_config(ROOT / "deploy" / "deploy.example.toml")
    assert settings["placement"] == str(ROOT / "deploy" / "placement.example.toml")
    assert settings["on_worker_loss"] == "replace" and len(settings["connect"]) == 2


def test_a_deployment_refuses_a_worker_of_another_protocol_and_one_whose_clock_is_off(namespace):
    """Two workers as a coordinator sees them (a liveliness token and an info answer), one from a
    future version, one whose clock reads 50 ms ahead: the deployment is refused before anything
    starts, naming both and what to do."""
    from retriever import BackendError
    from tests.deploy.deploy_flows import pipe

    port = free_port()
    keys = KeySpace(namespace)

    def answer(protocol: int, ahead_ns: int):
        def reply(query: zenoh.Query) -> None:
            name = str(query.key_expr).rsplit("/", 1)[-1]
            info = InfoReply(protocol=protocol, name=name, labels=(), host="elsewhere", pid=1, python="3.12.0",
                             packages={"retriever": "9.9"},
                             clock_ns=session.new_timestamp().get_time_as_ntp64().as_nanos() + ahead_ns, nodes=(),
                             counts={})
            query.reply(keys.ctl(name), info.encode())
        return reply

    with zenoh.open(peer_config(listen=[endpoint(port)])) as session:
        declared = [session.declare_queryable(keys.ctl("future"), answer(PROTOCOL_VERSION + 1, 0)),
                    session.declare_queryable(keys.ctl("skewed"), answer(PROTOCOL_VERSION, 50_000_000)),
                    session.liveliness().declare_token(keys.workers("future")),
                    session.liveliness().declare_token(keys.workers("skewed"))]
        try:
            with pytest.raises(BackendError, match=r"the deployment cannot start:\n"
                                                   r"  - worker 'future' speaks protocol 3, this coordinator 2\n"
                                                   r"    hint: install the same Retriever version .*'9.9'\)\n"
                                                   r"  - worker 'skewed' \(host elsewhere\) has a clock \+[45]\d\.\d+ ms"
                                                   r" off this machine's, past 10 ms\n    hint: sync both clocks"):
                pipe.run(duration=1, backend="zenoh", connect=[endpoint(port)], namespace=namespace, insecure=True,
                         quiet=True)
        finally:
            for item in declared:
                item.undeclare()
            pipe.reset()


def test_a_daemon_that_does_not_answer_is_said_to_not_answer_not_to_refuse(workers, namespace):
    """A hung daemon (SIGSTOP): Zenoh ends the query with an error reply of its own ("Timeout"),
    which is no refusal of the daemon's (it was reported as "refused info: Timeout")."""
    port = free_port()
    worker = workers("--name", "w", "--listen", endpoint(port), "--namespace", namespace, "--insecure").wait_started()
    with _client(port) as session:
        assert ask(session, namespace, "w", InfoRequest()).name == "w"
        os.kill(worker.proc.pid, signal.SIGSTOP)
        try:
            _until_every_thread_stopped(worker.proc.pid)
            with pytest.raises(WorkerError, match=r"^worker 'w' did not answer info within 1 s$"):
                ask(session, namespace, "w", InfoRequest(), timeout=1.0)
        finally:
            os.kill(worker.proc.pid, signal.SIGCONT)
    assert worker.stop() == 0


def _until_every_thread_stopped(pid: int) -> None:
    """SIGSTOP takes each thread as it next enters the kernel, not when kill() returns (one CI run
    had the suspended daemon still answer): the parent learns of the stop once every thread of
    its child has stopped (waitpid WUNTRACED), which does not reap it."""
    _, status = os.waitpid(pid, os.WUNTRACED)
    assert os.WIFSTOPPED(status), f"daemon {pid} ended instead of stopping: status {status}"


def test_the_password_folders_of_dead_daemons_are_reaped_those_of_live_ones_kept(tmp_path, namespace):
    """A SIGKILLed daemon leaves its retriever-worker-PID-* folder (its Zenoh password file):
    the next daemon to open its access removes the folders whose daemon is gone, no other."""
    gone = subprocess.Popen([sys.executable, "-c", "pass"])
    gone.wait()
    secret = tmp_path / "lab.key"
    secret.write_text("s" * 40 + "\n")
    secret.chmod(0o600)
    base = Path(tempfile.gettempdir())
    dead = base / f"retriever-worker-{gone.pid}-test{os.getpid()}"
    alive = base / f"retriever-worker-{os.getpid()}-test{os.getpid()}"
    odd = base / f"retriever-worker-notapid-test{os.getpid()}"
    for folder in (dead, alive, odd):
        folder.mkdir()
    try:
        with open_access(namespace, str(secret)) as access:
            assert access
            assert not dead.exists() and alive.exists() and odd.exists()
        assert alive not in reap_stale_folders()
    finally:
        for folder in (dead, alive, odd):
            if folder.exists():
                folder.rmdir()


def test_a_binary_config_is_named_as_no_text(tmp_path):
    # issue 40 item 12: a binary worker.toml gave a bare UnicodeDecodeError
    config = tmp_path / "worker.toml"
    config.write_bytes(b'name = "w"\n\xff\xfe\x00binary')
    message = (rf"^the worker config .*worker\.toml is not text: TOML is UTF-8, byte 11 is b'\\xff'\n"
               rf"    hint: --config takes a worker\.toml")
    with pytest.raises(WorkerError, match=message):
        load_settings(config)
    result = _cli("worker", "--config", str(config), "--insecure")
    assert result.returncode == 1 and "Traceback" not in result.stderr, result.stderr
    assert re.match(r"^error: the worker config .*worker\.toml is not text: TOML is UTF-8, byte 11 is b'\\xff'\n"
                    r"hint: --config takes a worker\.toml \(name = ", result.stderr), result.stderr


def test_a_deploy_config_reports_every_bad_value_at_once(tmp_path):
    # issue 40 item 12: a bad endpoint, namespace and on_worker_loss came one per invocation
    from retriever.backends.zenoh.deploy import load_deploy_config
    from retriever import BackendError

    config = tmp_path / "deploy.toml"
    config.write_text('connect = ["tcp/arm:7447", "bogus"]\nlisten = "tcp/0.0.0.0:7447"\nnamespace = "lab/a"\n'
                      'on_worker_loss = "retry"\nlease = "long"\nmax_clock_offset = -3\n')
    problems = (r"^the deploy config .*deploy\.toml has problems:\n"
                r"  - 'connect': 'bogus' is no Zenoh endpoint: write PROTOCOL/ADDRESS, e\.g\. tcp/10\.0\.0\.2:7447 "
                r"\(tls/\.\.\. with TLS\)\n"
                r"  - 'namespace' 'lab/a' cannot be a Zenoh key chunk: use letters, digits, '_', '-' and '\.' .*\n"
                r"  - 'on_worker_loss' must be one of replace, wait, stop, got 'retry'\n"
                r"  - 'lease' must be a positive number of seconds \(at most 1e9\), got 'long'\n"
                r"  - 'max_clock_offset' must be a positive number of seconds \(at most 1e9\), got -3$")
    with pytest.raises(BackendError, match=problems):
        load_deploy_config(config)
    done = _cli("deploy", "tests/deploy/deploy_flows.py:pipe", "--config", str(config))
    assert done.returncode == 1 and "Traceback" not in done.stderr, done.stderr
    assert re.match("^error: " + problems[1:-1], done.stderr), done.stderr


@pytest.mark.skipif(shutil.which("openssl") is None, reason="the test makes a certificate with openssl")
def test_no_workers_over_tls_says_how_to_start_one_over_tls(namespace, tmp_path):
    # issue 40 item 12: the hint said --listen tcp/0.0.0.0:7447, which a TLS worker refuses
    subprocess.run(["openssl", "req", "-x509", "-newkey", "rsa:2048", "-nodes", "-days", "1", "-subj", "/CN=lab",
                    "-addext", "subjectAltName=IP:127.0.0.1", "-keyout", "lab.key", "-out", "lab.pem"],
                   cwd=tmp_path, check=True, capture_output=True, timeout=BOUND_S)
    tls = ["--tls-ca", str(tmp_path / "lab.pem"), "--tls-cert", str(tmp_path / "lab.pem"),
           "--tls-key", str(tmp_path / "lab.key")]
    at = f"tls/127.0.0.1:{free_port()}"  # nothing listens there
    result = _cli("workers", "--connect", at, "--namespace", namespace, "--insecure", *tls)
    assert result.returncode == 1, result.stderr
    assert result.stdout == (
        f"no workers in namespace '{namespace}' at {at}\n"
        f"  start one: retriever-worker --name NAME --namespace {namespace} --listen tls/0.0.0.0:7447 --tls-ca CA "
        "--tls-cert CERT --tls-key KEY --secret FILE, then: retriever workers --connect tls/HOST:7447 --tls-ca CA "
        "--tls-cert CERT --tls-key KEY --secret FILE\n"), result.stdout
    assert f"warning: no session at {at}: nothing listens there\n" == result.stderr  # reach.why_no_session


def test_a_worker_joined_through_a_router_listens_nowhere(tmp_path):
    settings = load_settings(name="robot", router=["tcp/10.0.0.1:7447"])
    assert (settings.router, settings.listen, settings.connect) == (("tcp/10.0.0.1:7447",), (), ())
    config = tmp_path / "worker.toml"
    config.write_text('name = "robot"\nrouter = "tcp/10.0.0.1:7447"\n')
    assert load_settings(config).router == ("tcp/10.0.0.1:7447",)
    with pytest.raises(WorkerError, match=r"a worker joined through a router \(--router\) listens nowhere and connects "
                                          r"to the router alone: leave out --listen and --connect"):
        load_settings(name="robot", router=["tcp/10.0.0.1:7447"], listen=["tcp/0.0.0.0:7447"])
    with pytest.raises(WorkerError, match=r"endpoint 'router-box' is no Zenoh endpoint"):
        load_settings(name="robot", router=["router-box"])
    assert load_settings(name="bare").router == ()


def test_a_local_router_needs_a_router_and_a_secret(tmp_path):
    config = tmp_path / "worker.toml"
    config.write_text('name = "robot"\nrouter = "tcp/10.0.0.1:7447"\nlocal_router = true\nsecret = "lab.key"\n')
    assert load_settings(config).local_router and not load_settings(name="bare").local_router
    with pytest.raises(WorkerError, match=r"--local-router links each run's router to the routers of --router: "
                                          r"give --router ENDPOINT"):
        load_settings(name="robot", local_router=True, insecure=True)
    with pytest.raises(WorkerError, match=r"--local-router admits each run's flows by the run's password, derived "
                                          r"from the deployment secret: give --secret FILE \(not --insecure\)"):
        load_settings(name="robot", router=["tcp/10.0.0.1:7447"], local_router=True, insecure=True)
    config.write_text('name = "robot"\nrouter = "tcp/10.0.0.1:7447"\nlocal_router = "yes"\nsecret = "lab.key"\n')
    with pytest.raises(WorkerError, match=r"'local_router' must be true or false, got 'yes'"):
        load_settings(config)


def test_a_deployment_through_a_router_takes_no_connect_or_listen(tmp_path):
    from retriever import BackendError
    from retriever.backends.zenoh.deploy import Deployment, load_deploy_config

    with pytest.raises(BackendError, match=r"joined through a router \(--router\) listens nowhere"):
        Deployment(router=["tcp/10.0.0.1:7447"], connect=["tcp/10.0.0.2:7447"], insecure=True)
    assert "deployment joined through router tcp/10.0.0.1:7447" == \
        Deployment(router=["tcp/10.0.0.1:7447"], insecure=True).where()
    config = tmp_path / "deploy.toml"
    config.write_text('router = "tcp/10.0.0.1:7447"\n')
    assert load_deploy_config(config) == {"router": ["tcp/10.0.0.1:7447"]}
