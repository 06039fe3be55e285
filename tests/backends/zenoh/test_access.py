"""Only a run's own processes write to its key space (issue 17 §2; access.py).

A run is started as users start one (a script, its endpoint line on stderr). Beside it, an
attacker connected to the run's endpoint sends everything that steered a run before: values a
flow would consume (by the next seqs), ``ctl/run stop``, a forged ``failed`` status, a progress
message whose frontier is 2^64−1, and forged reports with step records. As a stranger (no
credentials, or a guessed password) it gets no link at all; as a watcher (the run's watcher
config file) it reads the data stream, and its writes are dropped by Zenoh's access control. In
every case the run makes all its ticks, exits 0, counts no garbage (nothing arrived), and its log
replays identically. The watcher's config and the run's secrets are files only their owner reads.
"""

from __future__ import annotations

import contextlib
import json
import os
import re
import stat
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest
import zenoh

import retriever
from retriever.backends.zenoh.access import RUN_USER
from retriever.backends.zenoh.hub import endpoint, free_port, peer_config
from retriever.backends.zenoh import protocol as p
from retriever.backends.zenoh.wire import KeySpace, WireEncoder
from retriever.replay import replay

ROOT = Path(__file__).resolve().parents[3]
BOUND_S = 60.0  # a bound on any wait, never a speed check
RUN_S = 3.0

RUN = r"""
import json, sys
from tests.backends.zenoh.lifecycle_flows import Sink, two_node_pipeline

pipe = two_node_pipeline("guarded", source_hz=10, sink_hz=5, sink=Sink)
pipe.run(duration=float(sys.argv[3]), backend="zenoh", namespace=sys.argv[1], hub_port=int(sys.argv[2]),
         log=sys.argv[4], secret=sys.argv[5] if len(sys.argv) > 5 else None)
print(json.dumps({"stats": {n: [s.ticks, s.steps, s.errors] for n, s in pipe.stats().items()},
                  "counts": pipe.counts()}), flush=True)
"""

#: the run on Zenoh for its edges too (same_host_links=False): an insider's data and progress
#: claims reach its consumer there (over a same-host link the consumer hears its producer only)
RUN_ON_ZENOH = RUN.replace("else None)", "else None, same_host_links=False)")

WATCH_LINE = re.compile(r"watch it read-only with zenoh\.Config\.from_file\('([^']+)'\)")


def _env() -> dict[str, str]:
    env = {k: v for k, v in os.environ.items() if k not in ("FORCE_COLOR", "PYTHONPATH")}
    env.update(PYTHONPATH=str(ROOT), NO_COLOR="1", PYTHONDONTWRITEBYTECODE="1")
    return env


class Run:
    """The run's script as a process, and the lines of its stderr (read on a thread)."""

    def __init__(self, tmp_path: Path, namespace: str, secret: Path | None = None, script: str = RUN,
                 extra: tuple[str, ...] = ()):
        self.port, self.log = free_port(), tmp_path / "run.mcap"
        args = [namespace, str(self.port), str(RUN_S), str(self.log), *([str(secret)] if secret else []), *extra]
        self.proc = subprocess.Popen([sys.executable, "-c", script, *args],
                                     cwd=ROOT, env=_env(), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        self.lines: list[str] = []
        self.watch_path: Path | None = None
        self.printed = threading.Event()  # the watcher config line came, or stderr ended without it
        self.reader = threading.Thread(target=self._read, daemon=True)
        self.reader.start()

    def _read(self) -> None:
        for line in self.proc.stderr:
            self.lines.append(line)
            found = WATCH_LINE.search(line)
            if found and self.watch_path is None:
                self.watch_path = Path(found.group(1))
                self.printed.set()
        self.printed.set()

    def watch_config(self) -> Path:
        """The watcher config file the run printed (once it has: the hub is up)."""
        self.printed.wait(BOUND_S)
        assert self.watch_path is not None, "the run printed no watcher config:\n" + "".join(self.lines)
        return self.watch_path

    def result(self) -> dict:
        # stdout only, after the exit (it prints one line): stderr is the reader thread's, and
        # communicate() would take the lines it had not read yet from it
        self.proc.wait(timeout=BOUND_S + 2 * RUN_S)
        out = self.proc.stdout.read()
        self.reader.join(5)
        assert self.proc.returncode == 0, "".join(self.lines)
        return json.loads(out.splitlines()[-1])

    def kill(self) -> None:
        if self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait()


@pytest.fixture
def namespace() -> str:
    return f"access-{os.getpid()}-{time.monotonic_ns() % 10**9}"


def _subscribe(session: zenoh.Session, keys: KeySpace) -> tuple[list[str], threading.Event, object]:
    """Subscribe to the run's data: the keys seen, an event set at the first, the subscriber."""
    seen: list[str] = []
    first = threading.Event()

    def on_sample(sample) -> None:
        seen.append(str(sample.key_expr))
        first.set()

    return seen, first, session.declare_subscriber(keys.all_data(), on_sample)


def _secret_file(tmp_path: Path) -> Path:
    """A deployment secret the run and the insider share (mode 0600, 32 bytes)."""
    secret = tmp_path / "secret"
    secret.write_text("a deployment secret of 32 bytes.")
    secret.chmod(0o600)
    return secret


@contextlib.contextmanager
def _insider(run: Run, namespace: str, secret: Path, tmp_path: Path, subscribed: Path | None = None):
    """A session holding the run's credentials, once the run is up and its data flows: the
    session, and the run's key space. ``subscribed``: a file made once it is subscribed (a gate
    the run waits at)."""
    from retriever.backends.zenoh.access import RunAccess, read_secret
    from retriever.backends.zenoh.hub import open_peer

    run.watch_config()
    access = RunAccess.create(namespace, read_secret(secret))
    keys = KeySpace(namespace)
    with open_peer(endpoint(run.port), access=access.session_config(access.write_dictionary(tmp_path))) as insider:
        _, first, sub = _subscribe(insider, keys)
        if subscribed is not None:
            subscribed.touch()
        assert first.wait(BOUND_S), "the insider saw no data"
        try:
            yield insider, keys
        finally:
            sub.undeclare()


def _attack(session: zenoh.Session, keys: KeySpace, until: float) -> int:
    """Everything that once steered a run, again and again until ``until``; how many puts."""
    enc, sent, seq = WireEncoder(), 0, 0
    while time.monotonic() < until:
        for k in range(seq, seq + 5):  # the next seqs of counter.n: values total would consume
            session.put(keys.data("counter", "n"), enc.data((k * 100_000_000, 1), k, (k * 100_000_000, 1),
                                                            "counter", "n", {"n": -999}))
        seq += 5
        session.put(keys.run_control(), p.Stop().encode())
        session.put(keys.node_status("total"), p.Failed(node="total", pid=1, error="forged", traceback=None).encode())
        session.put(keys.progress("counter"), enc.progress(((1 << 64) - 1, 0), "counter", {"n": 0}))
        session.put(keys.report("counter"), p.Report(node="counter", records=(((7, 0), {}, (), "ok", None, 0, 0),),
                                                     events=()).encode())
        sent += 9
        time.sleep(0.05)  # pacing over the run's wall time (it runs in real time), not a wait: a
        # flood with no pause would take the 2 cores from the run it attacks
    return sent


def _assert_untouched(run: Run) -> None:
    result = run.result()
    assert result["stats"] == {"counter": [30, 30, 0], "total": [15, 15, 0]}, result
    assert "garbage" not in result["counts"], result  # nothing the attacker sent reached the run
    log = retriever.read_log(run.log)
    assert log.end["status"] == "finished", log.end
    assert {e.node for e in log.iter_events()} == {"counter", "total"}
    report = replay(log)
    assert report.identical, "\n".join(map(str, report.divergences))


@pytest.mark.parametrize("credentials", [None, {"user": RUN_USER, "password": "guessed"}])
def test_a_stranger_gets_no_link_and_cannot_steer_the_run(tmp_path, namespace, credentials):
    run = Run(tmp_path, namespace)
    try:
        hub = endpoint(run.port)
        run.watch_config()  # the hub is up
        config = peer_config(connect=[hub])
        if credentials is not None:
            config.insert_json5("transport/auth/usrpwd", json.dumps(credentials))
        with zenoh.open(config) as stranger:
            sent = _attack(stranger, KeySpace(namespace), time.monotonic() + RUN_S)
            assert sent > 0
            assert list(stranger.info.peers_zid()) == [], "a stranger got a link to the run"
        _assert_untouched(run)
    finally:
        run.kill()


def test_a_watcher_reads_the_data_and_cannot_write(tmp_path, namespace):
    run = Run(tmp_path, namespace)
    try:
        path = run.watch_config()
        assert stat.S_IMODE(path.stat().st_mode) == 0o600
        assert stat.S_IMODE(path.parent.stat().st_mode) == 0o700
        for private in path.parent.iterdir():  # the spec (the run's password), the dictionary
            assert stat.S_IMODE(private.stat().st_mode) & 0o077 == 0, private
        keys = KeySpace(namespace)
        with zenoh.open(zenoh.Config.from_file(str(path))) as watcher:
            seen, first, sub = _subscribe(watcher, keys)
            assert first.wait(BOUND_S), "the watcher saw no data"
            # a query is no read: the coordinator's ctl/start never hears it
            assert [r for r in watcher.get(keys.start(), timeout=1.0) if r.ok is not None] == []
            _attack(watcher, keys, time.monotonic() + RUN_S)
            sub.undeclare()
        assert set(seen) >= {keys.data("counter", "n"), keys.data("total", "n")}, sorted(set(seen))
        _assert_untouched(run)
    finally:
        run.kill()


def test_a_deployment_secret_must_be_private_and_long_enough(tmp_path):
    from retriever import BackendError
    from tests.backends.zenoh.lifecycle_flows import two_node_pipeline

    secret = tmp_path / "secret"
    secret.write_text("0123456789abcdef0123456789abcdef")
    secret.chmod(0o644)
    with pytest.raises(BackendError, match=r"can be read by other users \(mode 644\)\n    hint: chmod 600"):
        two_node_pipeline("secret").run(duration=0.1, backend="zenoh", quiet=True, secret=secret)
    secret.write_text("short")
    secret.chmod(0o600)
    with pytest.raises(BackendError, match=r"holds 5 bytes; a secret needs at least 16"):
        two_node_pipeline("secret").run(duration=0.1, backend="zenoh", quiet=True, secret=secret)


def test_what_an_insider_claims_is_checked_for_sense(tmp_path, namespace):
    """A process holding the run's credentials (a bug, or a compromised host) is still checked: a
    frontier past any tag or past what its producer can promise, a seq from the future, a value
    naming a callable (``os:system``), a status of a node that is not there: each refused and
    counted as garbage, never applied: the consumer makes every tick with no late event."""
    from tests.test_decoding_attacks import _data_message, forged

    secret = _secret_file(tmp_path)
    marker = tmp_path / "pwned"
    run = Run(tmp_path, namespace, secret, script=RUN_ON_ZENOH)
    assert "same_host_links=False" in RUN_ON_ZENOH
    try:
        enc = WireEncoder()
        end = round(RUN_S * 1e9)
        with _insider(run, namespace, secret, tmp_path) as (insider, keys):
            # what a worker that missed the start asks for: the run's T0 and end
            answers = [p.Start.decode(r.ok.payload.to_bytes()) for r in insider.get(keys.start(), timeout=BOUND_S)
                       if r.ok is not None]
            assert [(type(start), start.end) for start in answers] == [(p.Start, end)], answers
            claims = [
                (keys.progress("counter"), enc.progress(((1 << 64) - 1, 0), "counter", {"n": 0})),
                (keys.progress("counter"), enc.progress((end + 10**10, 0), "counter", {"n": 0})),
                (keys.progress("counter"), enc.progress((1, 0), "counter", {"n": 10**6})),
                (keys.data("counter", "n"), enc.data((end + 10**10, 1), 10**6, (end + 10**10, 1), "counter", "n",
                                                    {"n": -999})),
                (keys.data("counter", "n"), _data_message(forged("os:system", marker), "counter", "n")),
                (keys.node_status("ghost"), p.Failed(node="ghost", pid=1, error="forged", traceback=None).encode()),
                (keys.node_status("total"), p.Unanswered(node="total", pid=1, nodes=("ghost",)).encode()),
                # statuses of a real node from a process that is not its own: a `failed` stopped
                # the run, a `done` added its counts (the cold review)
                (keys.node_status("total"), p.Failed(node="total", pid=1, error="forged", traceback=None).encode()),
                (keys.node_status("total"), p.Done(node="total", pid=1, counts={"late": 1000}).encode()),
            ]
            for key, message in claims:
                insider.put(key, message)
            # sense, but not once the run started: no node declares itself again (worker/starts.py, REDECLARE_AFTER_S)
            insider.put(keys.node_status("total"), p.Unanswered(node="total", pid=1, nodes=("counter",)).encode())
        result = run.result()
    finally:
        run.kill()
    assert not marker.exists(), "a decoded value ran code"
    assert result["stats"] == {"counter": [30, 30, 0], "total": [15, 15, 0]}, result
    # (statuses of the coordinator's nodes are refused unsigned, as forged: test_origin.py)
    assert result["counts"].get("garbage", 0) + result["counts"].get("forged", 0) >= len(claims), result
    assert "late" not in result["counts"] and "redeclared" not in result["counts"], result
    # applied, the frontier past every tag made all 15 of total's ticks incomplete (a loaded
    # machine may make a few so on its own)
    assert result["counts"].get("incomplete", 0) < 5, result
    report = replay(retriever.read_log(run.log))
    assert report.identical, "\n".join(map(str, report.divergences))



def test_control_the_coordinator_did_not_seal_is_refused_and_the_run_completes(tmp_path, namespace):
    """An insider's `stop`, `lost` or `end` on ctl/run looked like the coordinator's, and every
    worker obeyed it: a `stop` cut the run short (then failed it: told to stop, and not by this
    coordinator), a `lost` ended a node's process, an `end` moved the run's end. The coordinator
    now seals its control for each process it started (protocol/seal.py): unsealed, or sealed
    with a key no process of the run holds, each is garbage at every worker and the run makes
    every tick."""
    from retriever.backends.zenoh.origin import new_key
    from retriever.backends.zenoh.protocol import ControlSigner

    forger = ControlSigner()
    forger.add(forger, new_key())
    forged = [p.Stop(), p.Lost(node="counter"), p.Lost(node="total"), p.End(at=0)]
    secret = _secret_file(tmp_path)
    run = Run(tmp_path, namespace, secret)
    try:
        with _insider(run, namespace, secret, tmp_path) as (insider, keys):
            for record in forged:
                payload = record.encode()
                insider.put(keys.run_control(), payload)
                insider.put(keys.run_control(), payload, attachment=forger.seal(keys.run_control(), payload))
        result = run.result()
    finally:
        run.kill()
    assert result["stats"] == {"counter": [30, 30, 0], "total": [15, 15, 0]}, result
    assert result["counts"].get("garbage", 0) >= 2 * len(forged), result
    log = retriever.read_log(run.log)
    assert log.end["status"] == "finished", log.end
    report = replay(log)
    assert report.identical, "\n".join(map(str, report.divergences))


def test_retriever_run_takes_the_secret_and_refuses_one_others_can_read(tmp_path):
    secret = tmp_path / "secret"
    secret.write_text("0123456789abcdef0123456789abcdef")

    def run_with_the_secret() -> subprocess.CompletedProcess:
        return subprocess.run([str(Path(sys.executable).parent / "retriever"), "run",
                               "tests/backends/zenoh/lifecycle_flows.py:pipe", "--backend", "zenoh", "--duration",
                               "0.2", "--secret", str(secret), "--namespace", "cli-secret"],
                              cwd=ROOT, env=_env(), capture_output=True, text=True, timeout=BOUND_S)

    secret.chmod(0o644)
    result = run_with_the_secret()
    assert result.returncode == 1, result.stdout + result.stderr
    assert result.stderr.startswith("error: the secret file"), result.stderr
    assert "can be read by other users (mode 644)" in result.stderr and "hint: chmod 600" in result.stderr
    secret.chmod(0o600)
    result = run_with_the_secret()
    assert result.returncode == 0, result.stdout + result.stderr
    assert "namespace 'cli-secret'" in result.stderr


SUSPENDED_WATCHER = r"""
import sys, threading, zenoh
got = threading.Event()
with zenoh.open(zenoh.Config.from_file(sys.argv[1])) as watcher:
    sub = watcher.declare_subscriber(sys.argv[2], lambda sample: got.set())
    got.wait(60)
    print("watching", flush=True)
    sys.stdin.readline()  # SIGSTOPped here; once resumed, told to end: its session closes
    sub.undeclare()
"""

BIG_RUN = r"""
import json, sys
from retriever import Latest, Pipeline, Rate, Trigger
from tests.backends.zenoh.semantics_flows import BigTicker, Echo

with Pipeline("watched") as pipe:
    cam = BigTicker(size=2_000_000).configure(name="cam") @ Rate(hz=25)
    cam.then(Echo().configure(name="sink") @ Trigger("x"), sync=Latest())
pipe.run(duration=4.0, backend="zenoh", namespace=sys.argv[1])
print(json.dumps({n: [s.ticks, s.steps] for n, s in pipe.stats().items()}), flush=True)
"""


def test_a_watcher_that_stops_reading_neither_stalls_nor_fails_the_run(namespace):
    """A watcher suspended (SIGSTOP) while 2 MB frames stream to it fills its socket: the run's
    events go peer to peer and every tick is made; the hub's close, which waits on that link,
    timed out and raised a bare ZError from pipe.run. Now the run ends, saying why it was slow."""
    import signal

    run = subprocess.Popen([sys.executable, "-c", BIG_RUN, namespace], cwd=ROOT, env=_env(),
                           stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    watcher = None
    try:
        path = None
        for line in run.stderr:
            found = WATCH_LINE.search(line)
            if found:
                path = found.group(1)
                break
        assert path, "the run printed no watcher config"
        watcher = subprocess.Popen([sys.executable, "-c", SUSPENDED_WATCHER, path, KeySpace(namespace).all_data()],
                                   stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
        assert watcher.stdout.readline() == "watching\n"
        os.kill(watcher.pid, signal.SIGSTOP)
        out, err = run.communicate(timeout=BOUND_S)
        # resumed and told to end, the watcher closes its session: killed, it would leave its
        # shared-memory segment in /dev/shm
        os.kill(watcher.pid, signal.SIGCONT)
        watcher.communicate(input="end\n", timeout=BOUND_S)
    finally:
        for proc in (run, watcher):
            if proc is not None and proc.poll() is None:
                proc.kill()
                proc.wait()
    assert run.returncode == 0, err
    assert json.loads(out.splitlines()[-1]) == {"cam": [100, 100], "sink": [100, 100]}


GATED_RUN = r"""
import json, sys
from retriever import Latest, Pipeline, Rate
from tests.backends.zenoh.lifecycle_flows import Counter, GatedSink

with Pipeline("guarded") as pipe:
    counter = Counter() @ Rate(hz=10)
    counter.then(GatedSink(gate=sys.argv[6]).configure(name="total") @ Rate(hz=5), sync=Latest())
pipe.run(duration=float(sys.argv[3]), backend="zenoh", namespace=sys.argv[1], hub_port=int(sys.argv[2]),
         log=sys.argv[4], secret=sys.argv[5], virtual_time=True)
print(json.dumps({"stats": {n: [s.ticks, s.steps, s.errors] for n, s in pipe.stats().items()},
                  "counts": pipe.counts()}), flush=True)
"""


def test_in_virtual_time_a_grant_put_by_an_insider_neither_wedges_nor_changes_the_run(tmp_path, namespace):
    """A lockstep run (virtual_time=True): a process holding the run's credentials grants far
    past the coordinator's window. The grant is unsealed: the workers refuse it (protocol/seal.py);
    were one taken, a `reached` past the coordinator's grant counts as reaching its own. Ticks
    still wait for complete inputs: the same ticks, a log that replays.

    In virtual time the run is done in well under a second: its sink waits at its first step for
    the insider to be subscribed and at its third for the grant to be out (GatedSink), or the
    insider could come too late to see any data (it did on CI) or to grant ahead of the run."""
    secret, gate = _secret_file(tmp_path), tmp_path / "gate"
    gate.mkdir()
    run = Run(tmp_path, namespace, secret, script=GATED_RUN, extra=(str(gate),))
    try:
        with _insider(run, namespace, secret, tmp_path, subscribed=gate / "subscribed") as (insider, keys):
            insider.put(keys.run_control(), p.Grant(until=round(2 * 1e9)).encode())
            (gate / "granted").touch()
        result = run.result()
    finally:
        run.kill()
    assert result["stats"] == {"counter": [30, 30, 0], "total": [15, 15, 0]}, result
    report = replay(retriever.read_log(run.log))
    assert report.identical, "\n".join(map(str, report.divergences))
