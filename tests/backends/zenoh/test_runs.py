"""What a worker daemon does for a run's processes (daemon/runs.py) that the deploy tests cannot show
at will: how a process's output reaches the coordinator (a real child process prints; the
daemon's forwarder, runs.forward_output, reads its pipe; what it would tell is collected in place
of the signed Zenoh put), and what its spawn and signal ops refuse (a real DaemonRuns on a real
Zenoh session, with a run prepared and a real worker process of it)."""

from __future__ import annotations

import os
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

from retriever.backends.zenoh import daemon
from retriever.backends.zenoh.command import GROUP_MODULE
from retriever.backends.zenoh.folders import DAEMON_FOLDER
from retriever.backends.zenoh.access import RunAccess
from retriever.backends.zenoh.hub import client_config, free_port, peer_config
from retriever.backends.zenoh.origin import KEY_BYTES
from retriever.backends.zenoh.protocol import (REQUEST, PrepareRequest, ProcessOutput, RunSpec, SignalRequest,
                                               SpawnRequest, Stream, UsageRequest)
from retriever.backends.zenoh.protocol.schema import pack
from retriever.backends.zenoh.daemon.runs import MAX_LINE_BYTES, OUTPUT_BATCH, DaemonRuns, forward_output
from retriever.backends.zenoh.wire import WIRE_VERSION, KeySpace, WireError
from tests.backends.zenoh.test_router import SECRET, A, routers, secret  # noqa: F401
from tests.log.log_flows import build_small

from .specs import run_spec

BOUND_S = 30.0


def forwarding(code: str):
    """A child running ``code``, and the batches of output lines the daemon would send of it."""
    sent: list[ProcessOutput] = []
    arrived = threading.Condition()

    def tell(event: ProcessOutput) -> None:
        with arrived:
            sent.append(event)
            arrived.notify_all()

    proc = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, stdin=subprocess.DEVNULL)
    thread = threading.Thread(target=forward_output, args=(proc.stdout, tell, "r1", "cam", Stream.STDOUT), daemon=True)
    thread.start()
    return proc, thread, sent, arrived


def lines_of(sent: list[ProcessOutput]) -> list[str]:
    return [line for batch in sent for line in batch.lines]


def test_held_lines_go_though_nothing_follows_them():
    """A stack dump is printed at once and then nothing: its last lines (the telling ones) must
    not wait for more output (they did: only the dump's first line reached the coordinator)."""
    proc, thread, sent, arrived = forwarding(
        "import sys, time\nprint('Thread 1\\n  File a\\n  File b', flush=True)\ntime.sleep(60)")
    try:
        with arrived:
            assert arrived.wait_for(lambda: len(lines_of(sent)) == 3, timeout=BOUND_S), sent
        assert lines_of(sent) == ["Thread 1", "  File a", "  File b"]
        assert proc.poll() is None  # still running, still silent: the batch went by itself
        assert {(b.run, b.node, b.stream) for b in sent} == {("r1", "cam", "stdout")}
    finally:
        proc.kill()
        proc.wait()
        thread.join(BOUND_S)


def test_output_goes_in_batches_and_a_line_without_end_in_pieces():
    many = OUTPUT_BATCH * 3 + 5
    proc, thread, sent, _ = forwarding(
        f"import sys\nfor i in range({many}): print(i)\nsys.stdout.write('x' * {MAX_LINE_BYTES * 2 + 10})")
    proc.wait(BOUND_S)
    thread.join(BOUND_S)
    assert not thread.is_alive()
    lines = lines_of(sent)
    assert lines[:many] == [str(i) for i in range(many)]
    assert all(len(batch.lines) <= OUTPUT_BATCH for batch in sent)
    rest = lines[many:]
    assert "".join(rest) == "x" * (MAX_LINE_BYTES * 2 + 10) and all(len(piece) <= MAX_LINE_BYTES * 2 for piece in rest)


def test_a_process_that_prints_nothing_sends_nothing():
    proc, thread, sent, _ = forwarding("pass")
    proc.wait(BOUND_S)
    thread.join(BOUND_S)
    assert sent == [] and not thread.is_alive()


# -- spawn and signal ----------------------------------------------------------------------------
ROOT = str(Path(__file__).resolve().parents[3])


def prepare_once_the_token_is_seen(runs: DaemonRuns, request: PrepareRequest) -> None:
    """``runs.prepare(request)``, once the daemon's subscriber has seen the coordinator's liveliness
    token (declared just before, seen on a Zenoh thread): until then it refuses, saying so."""
    give_up = time.monotonic() + 10.0
    while True:
        try:
            runs.prepare(request)
            return
        except WireError as e:
            if "liveliness token" not in str(e) or time.monotonic() > give_up:
                raise
            time.sleep(0.05)


@pytest.fixture
def prepared():
    """A daemon's runs with run ``r1`` prepared for the first node of the log tests' pipeline:
    ``(runs, node)``. Its workers link to the session's own endpoint (and wait there)."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        hub = f"tcp/127.0.0.1:{s.getsockname()[1]}"
    namespace = f"runs-test-{id(object())}"
    with zenoh.open(peer_config(listen=[hub], shared_memory=False)) as session:
        runs = DaemonRuns(session, "w", namespace, listen=(), secret=None,
                          allowed=lambda module: daemon.module_allowed(module, [], [ROOT]),
                          refusal=lambda module: daemon.refusal(module, [], [ROOT]), paths=())
        token = session.liveliness().declare_token(KeySpace(namespace).deployment())
        ir = build_small().build_ir().doc
        node = ir["nodes"][0]["id"]
        spec = run_spec(ir, namespace, hub=hub, startup_timeout=600.0)
        try:
            prepare_once_the_token_is_seen(runs, PrepareRequest(run="r1", spec=spec, nodes=(node,)))
            yield runs, node
        finally:
            runs.close()
            token.undeclare()


@pytest.mark.parametrize("field, value", [
    ("node", lambda node: [node]), ("node", lambda node: {node: 1}),
    ("mode", lambda node: ["--join", "\u00b2", "3"]),  # isdigit, but no int: the worker would fail on it
    ("mode", lambda node: ["--fresh", "\u0661\u0662", "3"]),
    # a key in the request (an older coordinator's): every queryable on ctl/<name> reads it
    ("key", lambda node: "ab" * KEY_BYTES),
])
def test_a_spawn_refuses_what_is_no_prepared_node_mode_or_key_and_starts_nothing(prepared, field, value):
    runs, node = prepared
    args = {"run": "r1", "node": node, "mode": [], field: value(node)}
    with pytest.raises(WireError, match=field):
        runs.spawn(request("spawn", args))
    assert runs.run.processes == {}


def request(op: str, fields: dict):
    """A request as the daemon reads it (daemon/core.py, WorkerDaemon.answer: protocol.REQUEST, then the
    op), hand-made as an insider may send it."""
    return REQUEST.decode(pack([WIRE_VERSION, op, fields]))


def test_a_signal_goes_only_to_a_pid_of_the_run_as_an_int_with_an_allowed_signal(prepared):
    runs, node = prepared
    pid = runs.spawn(SpawnRequest(run="r1", node=node, mode=())).pid
    proc = runs.run.processes[pid][1]
    for target, sig in ((float(pid), signal.SIGKILL), ([pid], signal.SIGKILL), ({pid: 1}, signal.SIGKILL),
                        (pid, float(signal.SIGKILL)), (pid, [9]), (True, signal.SIGKILL), (pid, 0)):
        with pytest.raises(WireError, match="field '(pid|signal)' must be an integer"):
            runs.signal(request("signal", {"run": "r1", "pid": target,
                                           "signal": int(sig) if type(sig) is signal.Signals else sig}))
    for target, sig in ((pid, 19), (pid + 1, signal.SIGKILL)):
        with pytest.raises(WireError, match="not a process of run r1 or not a signal"):
            runs.signal(SignalRequest(run="r1", pid=target, signal=int(sig)))
    assert proc.poll() is None, "a refused signal reached the run's process"
    runs.signal(SignalRequest(run="r1", pid=pid, signal=int(signal.SIGKILL)))
    assert proc.wait(timeout=10) == -signal.SIGKILL


def grouped_spec(runs) -> tuple[list[str], object]:
    """The small pipeline's node ids, and a spec of it whose nodes are all one group, "g"."""
    ir = build_small().build_ir().doc
    ids = [n["id"] for n in ir["nodes"]]
    hub = RunSpec.read_file(runs.run.folder / "spec.json").hub  # (run r1's)
    return ids, run_spec(ir, runs.keys.namespace, hub=hub, startup_timeout=600.0,
                         zids=dict.fromkeys(ids, "1a2b"), groups={"g": tuple(ids)})


def test_a_group_starts_as_one_process_only_when_every_member_is_prepared_here(prepared):
    """A spec's groups (flows that share a process, whose members share a Zenoh id): the daemon
    starts a group's one process (worker/group.py) once every member is prepared on it, and
    refuses a group it does not have, one split across workers, and a mode for one."""
    runs, _ = prepared
    ids, spec = grouped_spec(runs)
    runs.prepare(PrepareRequest(run="r2", spec=spec, nodes=(ids[0],)))
    with pytest.raises(WireError, match=rf"group 'g': its node\(s\) {', '.join(sorted(ids[1:]))} were not prepared "
                                        r"on worker 'w' \(a group's nodes run in one process, on one worker\)"):
        runs.spawn(SpawnRequest(run="r2", node="g", mode=(), group=True))
    with pytest.raises(WireError, match=r"'h' is no group of run r2's spec \(its groups: g\)"):
        runs.spawn(SpawnRequest(run="r2", node="h", mode=(), group=True))
    runs.prepare(PrepareRequest(run="r2", spec=spec, nodes=tuple(ids)))  # the others: prepared too
    with pytest.raises(WireError, match="a group's process starts with its run only"):
        runs.spawn(SpawnRequest(run="r2", node="g", mode=("--fresh", "1", "2"), group=True))
    assert runs.run.processes == {}
    pid = runs.spawn(SpawnRequest(run="r2", node="g", mode=(), group=True)).pid
    assert runs.run.processes[pid][1].args[2:5] == [GROUP_MODULE, str(runs.run.folder / "spec.json"), "g"]
    assert runs.nodes() == sorted(ids)  # what the daemon says it runs: the group's members
    assert set(runs.usage(UsageRequest(run="r2")).cpu_s) == set(ids)  # each, its process's CPU


def test_a_node_runs_in_at_most_two_processes_its_groups_counted(prepared):
    """A node runs in one process, two while it restarts: a group's process counts for each member,
    so a holder of the secret cannot start a member alone beside its group's process twice over."""
    runs, _ = prepared
    ids, spec = grouped_spec(runs)
    runs.prepare(PrepareRequest(run="r2", spec=spec, nodes=tuple(ids)))
    with pytest.raises(WireError, match=rf"'{ids[0]}' is no group of run r2's spec \(its groups: g\)"):
        runs.spawn(SpawnRequest(run="r2", node=ids[0], mode=(), group=True))  # a node, told it is a group
    runs.spawn(SpawnRequest(run="r2", node="g", mode=(), group=True))
    runs.spawn(SpawnRequest(run="r2", node=ids[0], mode=()))
    with pytest.raises(WireError, match=rf"node '{ids[0]}' already runs in 2 processes on worker 'w'"):
        runs.spawn(SpawnRequest(run="r2", node=ids[0], mode=()))
    with pytest.raises(WireError, match=rf"group 'g': its node '{ids[0]}' already runs in 2 processes"):
        runs.spawn(SpawnRequest(run="r2", node="g", mode=(), group=True))
    assert len(runs.run.processes) == 2


@pytest.mark.parametrize("plan", [b"\x00" * 8, {"nodes": b"x"}, {"nodes": [], "extra": 1}, [1, 2, 3]])
def test_a_prepare_with_a_plan_its_ir_contradicts_is_refused_and_makes_no_folder(prepared, plan):
    """The plan in a spec came from the network: the daemon checks it against the IR before it
    makes the run's folder (an unchecked one failed later, in json.dumps, leaving a folder)."""
    runs, node = prepared
    ir = build_small().build_ir().doc
    spec = {**run_spec(ir, "runs-test-plan", hub="tcp/127.0.0.1:1").to_fields(), "plan": plan}
    folders = set(Path(tempfile.gettempdir()).glob(f"{DAEMON_FOLDER}-{os.getpid()}-run-*"))
    with pytest.raises(WireError, match="plan"):  # by the request's decoder, or by prepare
        runs.prepare(request("prepare", {"run": "r2", "spec": spec, "nodes": [node]}))
    assert set(Path(tempfile.gettempdir()).glob(f"{DAEMON_FOLDER}-{os.getpid()}-run-*")) <= folders


# -- a run's router (--local-router) -------------------------------------------------------------
def test_a_run_whose_router_died_has_its_processes_stopped_and_no_new_one_started(routers, secret):
    """A daemon joined through a router with --local-router: its run's router killed mid-run, the
    run's process there is stopped (it has no link to anyone) and a spawn is refused, saying why."""
    upstream = f"tcp/127.0.0.1:{free_port()}"
    routers("--secret", str(secret), "--listen", upstream, "--namespace", A).wait_started()
    own = RunAccess.create(A, SECRET).client_config(A)
    with zenoh.open(client_config(connect=[upstream], access=own, shared_memory=False)) as session:
        runs = DaemonRuns(session, "w", A, listen=(), secret=SECRET,
                          allowed=lambda module: daemon.module_allowed(module, [], [ROOT]),
                          refusal=lambda module: daemon.refusal(module, [], [ROOT]), paths=(),
                          router=(upstream,), local_router=True)
        token = session.liveliness().declare_token(KeySpace(A).deployment())
        ir = build_small().build_ir().doc
        node = ir["nodes"][0]["id"]
        try:
            prepare_once_the_token_is_seen(runs, PrepareRequest(
                run="r1", spec=run_spec(ir, A, hub=None, startup_timeout=600.0), nodes=(node,)))
            router = runs.run.router
            proc = runs.run.processes[runs.spawn(SpawnRequest(run="r1", node=node, mode=())).pid][1]
            os.kill(router.pid, signal.SIGKILL)
            assert proc.wait(timeout=BOUND_S) is not None
            with pytest.raises(WireError, match=rf"worker 'w' cannot start '{node}': run r1: the worker's router for "
                                                rf"it \(pid {router.pid}, tcp/127\.0\.0\.1:\d+\) was killed by SIGKILL; "
                                                "the run's flows on this machine have no link to anyone"):
                runs.spawn(SpawnRequest(run="r1", node=node, mode=()))
        finally:
            runs.close()
            token.undeclare()
