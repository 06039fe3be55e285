"""A process's key never travels where an insider can read it (issue 40 review; remote.py, origin.py).

A real worker daemon and a real ``retriever deploy`` beside an insider (a session holding the
namespace's secret) with a queryable on ``ctl/**``, which answers spawns as the daemon would,
with a key of its own: Zenoh hands it every query
to the daemon, and the coordinator's spawn requests once carried each process's key, with which
the insider signed an ``exit`` that ended a 30 s deployment at 4 s, recorded as finished. Now
the daemon makes the key and answers it to the coordinator alone, which takes answers from the
daemon's session only: the insider reads no key, and has none of its own taken; its exit is
refused as forged, and the run makes all its ticks.

The namespace's credentials reach the daemons' control alone, not the run (access.py: a run's
passwords are derived for its run id): holding the secret, the insider learns the run id from
the prepare request it reads on ``ctl/**``, derives the run's credentials, and joins the hub
the request names with them, as any process of the run would.
"""

from __future__ import annotations

import contextlib
import os
import subprocess
import sys
import threading
import time
from pathlib import Path

import msgpack

from retriever import read_log
from retriever.backends.zenoh.access import RunAccess, read_secret
from retriever.backends.zenoh.hub import endpoint, free_port, open_peer
from retriever.backends.zenoh.origin import KEY_BYTES, key_of_text, sign
from retriever.backends.zenoh.protocol import DaemonOp, Exit, Report, SpawnReply
from retriever.backends.zenoh.wire import KeySpace
from tests.backends.zenoh.test_daemon import BOUND_S, ROOT, SECRET, _env, namespace, workers  # noqa: F401

DURATION_S = 8
#: total's sink rate in lifecycle_flows (10 Hz): its ticks
SINK_PERIOD_NS = 100_000_000


def test_an_insider_on_ctl_reads_no_process_key_and_its_exit_is_refused(workers, namespace, tmp_path):
    secret = tmp_path / "secret"
    secret.write_text(SECRET)
    secret.chmod(0o600)
    port = free_port()
    daemon = workers("--name", "w1", "--listen", endpoint(port), "--namespace", namespace,
                     "--path", str(ROOT / "tests" / "backends" / "zenoh"), "--secret", str(secret))
    daemon.wait_started()
    keys = KeySpace(namespace)
    spawns: list[dict] = []
    pids: dict[str, int] = {}
    ready = threading.Event()

    own_key = os.urandom(KEY_BYTES)
    prepared: list[dict] = []

    def on_query(query) -> None:  # reads every request, as it came; answers a spawn as if it were the daemon
        _, op, args = msgpack.unpackb(query.payload.to_bytes(), strict_map_key=False)
        if op == DaemonOp.PREPARE:
            prepared.append(args)
        if op == DaemonOp.SPAWN:
            spawns.append(args)
            query.reply(query.key_expr, SpawnReply(pid=os.getpid(), key=own_key).encode())

    def on_status(sample) -> None:
        _, node, state, info = msgpack.unpackb(sample.payload.to_bytes(), strict_map_key=False)
        if state == "ready" and type(info.get("pid")) is int:
            pids[node] = info["pid"]
            ready.set()

    access = RunAccess.create(namespace, read_secret(str(secret)))
    log = tmp_path / "run.mcap"
    with contextlib.ExitStack() as stack:
        control = stack.enter_context(open_peer(endpoint(port), access=access.session_config(
            access.write_dictionary(tmp_path))))
        queryable = control.declare_queryable(f"retriever/{namespace}/ctl/**", on_query)
        deploy = subprocess.Popen(
            [sys.executable, "-m", "retriever.cli", "deploy", "tests/backends/zenoh/lifecycle_flows.py:pipe",
             "--connect", endpoint(port), "--namespace", namespace, "--secret", str(secret),
             "--duration", str(DURATION_S), "--log", str(log)],
            cwd=ROOT, env=_env(), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        try:
            deadline = time.monotonic() + BOUND_S
            while not prepared and time.monotonic() < deadline and deploy.poll() is None:
                time.sleep(0.05)  # a poll for the prepare request's arrival (bounded), no timing
            assert prepared, "the insider saw no prepare request"
            run_access = RunAccess.create(namespace, read_secret(str(secret)), run=prepared[0]["run"])
            insider = stack.enter_context(open_peer(prepared[0]["spec"]["hub"], access=run_access.session_config(
                run_access.write_dictionary(tmp_path, "run-users.txt"))))
            status = insider.declare_subscriber(keys.status("node") + "/**", on_status)
            reporting = threading.Event()  # total's first report: the run is under way
            reports = insider.declare_subscriber(keys.report("total"), lambda sample: reporting.set())
            assert reporting.wait(BOUND_S), "total never reported a step"
            # its pid, which its statuses carry: its ready may have come before the insider
            # linked to it, so also as the daemon's child
            pids.setdefault("total", _child_pid(daemon.proc.pid, "total"))
            seen = [key_of_text(args.get("key")) for args in spawns if args.get("node") == "total"]
            key = next((k for k in seen if k is not None), None) or own_key
            tag = (30 * SINK_PERIOD_NS, 0)  # one of total's ticks (3 s), long before the end
            report = Report(node="total", records=((tag, {}, (), "ok", {"exit": 0}, 0, 0),), events=()).encode()
            insider.put(keys.report("total"), report, attachment=sign(key, keys.report("total"), report))
            exit_status = Exit(node="total", pid=pids["total"], tag=tag).encode()
            insider.put(keys.node_status("total"), exit_status,
                        attachment=sign(key, keys.node_status("total"), exit_status))
            out, err = deploy.communicate(timeout=BOUND_S + DURATION_S)
        finally:
            if deploy.poll() is None:
                deploy.kill()
                deploy.wait()
            queryable.undeclare()  # (the insider's subscribers go with its session)
    assert deploy.returncode == 0, out + err
    end = read_log(log).end
    assert end["status"] == "finished" and end["end_ns"] == str(DURATION_S * 10**9), end
    assert '"forged"' in end.get("counts", ""), end
    steps = [s for s in read_log(log).iter_steps() if s.node == "total"]
    assert len(steps) == DURATION_S * 10, len(steps)
    assert spawns and all("key" not in args for args in spawns), f"a spawn request carried a key: {spawns}"


def _child_pid(parent: int, node: str) -> int:
    """The pid of ``node``'s worker process, a child of the daemon ``parent`` (Linux /proc)."""
    children = [int(pid) for task in Path(f"/proc/{parent}/task").iterdir()
                for pid in (task / "children").read_text().split()]
    for pid in children:
        argv = Path(f"/proc/{pid}/cmdline").read_bytes().split(b"\0")
        if node.encode() in argv:
            return pid
    raise AssertionError(f"no process of node {node!r} among the daemon's children {children}")
