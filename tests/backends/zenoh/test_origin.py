"""Only a node's own process speaks for it (issue 40 §3–4; origin.py).

An insider (a session holding the run's deployment secret, as the run's processes do) beside a
real run, started as a user starts one: it puts ``exit`` statuses carrying the pid of a node's
worker process (which ended the run early, exit 0, "finished", and replayed identically), and
floods the coordinator with forged step records of the source (which entered the log and the
table, and grew the coordinator by hundreds of MB). Each is refused and counted as ``forged``:
the run makes all its ticks, the log holds only the run's own records, and the coordinator holds
none of the forgeries.
"""

from __future__ import annotations

import os
import queue
import subprocess
from pathlib import Path

import msgpack
import pytest

import retriever
from retriever.backends.zenoh.protocol import Done, Exit, Report
from retriever.backends.zenoh.wire import RELIABLE
from retriever.replay import replay
from tests.backends.zenoh.test_access import BOUND_S, Run, _insider, _secret_file

#: forged step records the insider floods the coordinator with (today's code held each: ~470 B)
FLOOD_RECORDS = 300_000
#: what the coordinator's memory may grow by while it refuses them (they held ~140 MB)
FLOOD_GROWTH_MAX = 48 << 20


@pytest.fixture
def namespace() -> str:
    return f"origin-{os.getpid()}-{os.urandom(3).hex()}"


def _worker_pid(coordinator: int, node: str) -> int:
    """The pid of ``node``'s worker process, a child of the coordinator (as ``ps`` shows it)."""
    for entry in os.listdir("/proc"):
        if not entry.isdigit():
            continue
        try:
            stat = Path(f"/proc/{entry}/stat").read_text()
            argv = Path(f"/proc/{entry}/cmdline").read_bytes().split(b"\0")
        except OSError:
            continue
        if int(stat.rsplit(")", 1)[1].split()[1]) == coordinator and node.encode() in argv:
            return int(entry)
    raise AssertionError(f"no worker process of {node} under pid {coordinator}")


def _rss(pid: int) -> int:
    """The resident memory of a process (0 once it exited: a zombie has none)."""
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) << 10
    return 0


def _assert_whole(run: Run, result: dict, forged: int) -> None:
    """The run made every tick, and its log holds its own records only and replays identically."""
    assert result["stats"] == {"counter": [30, 30, 0], "total": [15, 15, 0]}, result
    assert result["counts"].get("forged", 0) >= forged, result
    log = retriever.read_log(run.log)
    assert log.end["status"] == "finished", log.end
    steps = list(log.iter_steps())
    assert sorted((s.node, s.tag) for s in steps if s.node == "counter") == \
        [("counter", (k * 100_000_000, 0)) for k in range(30)]
    assert len(steps) == 45, len(steps)
    assert '"forged"' in log.end.get("counts", ""), log.end
    report = replay(log)
    assert report.identical, "\n".join(map(str, report.divergences))
    assert any("refused" in line and "forged" in line for line in run.lines), "".join(run.lines)


def test_a_forged_exit_with_the_nodes_pid_does_not_end_the_run(tmp_path, namespace):
    """`exit` {tag} with total's own pid, then a report of total's step at that tag with status ok
    and detail {exit: 0}, as its process would send: neither ends the run (before, the run ended
    within a second, exit 0, status finished, and replay said identical)."""
    secret = _secret_file(tmp_path)
    run = Run(tmp_path, namespace, secret)
    try:
        with _insider(run, namespace, secret, tmp_path) as (insider, keys):
            pid = _worker_pid(run.proc.pid, "total")
            tag = (400_000_000, 0)  # one of total's ticks (5 Hz)
            insider.put(keys.report("total"), Report(node="total", records=((tag, {}, (), "ok", {"exit": 0}, 0, 0),),
                                                     events=()).encode())
            for status in (Exit(node="total", pid=pid, tag=tag), Done(node="total", pid=pid, counts={}, stopped=True)):
                insider.put(keys.node_status("total"), status.encode())
        result = run.result()
    finally:
        run.kill()
    _assert_whole(run, result, forged=3)


def test_a_replayed_done_of_a_process_is_refused(tmp_path, namespace):
    """An insider puts again, signature and all, the first `done` it sees, three times: a second
    `done` of a process is not taken (it added the process's counts and reports again: the
    coordinator then waited for reports that never came, and the run failed)."""
    secret = _secret_file(tmp_path)
    run = Run(tmp_path, namespace, secret)
    seen: queue.Queue = queue.Queue()
    try:
        with _insider(run, namespace, secret, tmp_path) as (insider, keys):
            sub = insider.declare_subscriber(keys.status("node") + "/**", lambda sample: seen.put(
                (str(sample.key_expr), sample.payload.to_bytes(),
                 None if sample.attachment is None else sample.attachment.to_bytes())))
            while True:
                key, payload, mac = seen.get(timeout=BOUND_S)
                if msgpack.unpackb(payload, strict_map_key=False)[2] == "done":
                    for _ in range(3):
                        insider.put(key, payload, attachment=mac, congestion_control=RELIABLE)
                    break
            sub.undeclare()
        result = run.result()
    finally:
        run.kill()
    assert result["stats"] == {"counter": [30, 30, 0], "total": [15, 15, 0]}, result
    assert result["counts"].get("garbage", 0) >= 3, result
    assert retriever.read_log(run.log).end["status"] == "finished"
    assert any("(a replay)" in line for line in run.lines), "".join(run.lines)


@pytest.mark.parametrize("last, state, taken", [
    (None, "ready", True), ("ready", "ready", True), ("ready", "done", True), ("ready", "restart", True),
    ("restart", "handed_over", True), ("restart", "done", True), ("restart", "failed", True),
    ("done", "done", False), ("done", "ready", False), ("failed", "ready", False), ("done", "failed", False),
    ("handed_over", "ready", False), ("restart", "ready", False), ("restart", "restart", False),
])
def test_a_process_says_its_states_forward_only_and_a_last_one_once(last, state, taken):
    """A replayed `ready` after the process's `done` moved the node back (the run then failed
    waiting for it); a replayed `done` counted it twice."""
    from retriever.backends.zenoh.coordinator import may_say
    assert may_say(last, state) is taken


def test_forged_source_records_reach_neither_the_log_nor_the_coordinators_memory(tmp_path, namespace):
    """FLOOD_RECORDS step records of the source (10 Hz) put on its report key: between its ticks,
    at its ticks past the end, and at ticks it makes. None is taken: the table and the log have
    its 30 ticks, and the coordinator's memory does not grow with the flood."""
    secret = _secret_file(tmp_path)
    per_report = FLOOD_RECORDS // 3
    forgeries = [  # msgpack of [2, node, records, events], packed once, before the run
        msgpack.packb([2, "counter", [[[t, 0], {}, [], "ok", None, 0, 0] for t in tags], []])
        for tags in (range(1, per_report + 1),  # between its ticks
                     range(40 * 100_000_000, (40 + per_report) * 100_000_000, 100_000_000),  # past its end
                     [k % 30 * 100_000_000 for k in range(per_report)])]  # its own ticks
    run = Run(tmp_path, namespace, secret)
    try:
        with _insider(run, namespace, secret, tmp_path) as (insider, keys):
            before = _rss(run.proc.pid)
            for payload in forgeries:
                insider.put(keys.report("counter"), payload, congestion_control=RELIABLE)  # all of it arrives
            grown = 0
            while True:  # until the run is over (the forgeries all arrived): its most
                try:
                    grown = max(grown, _rss(run.proc.pid) - before)
                    run.proc.wait(timeout=0.05)
                    break
                except subprocess.TimeoutExpired:
                    continue
                except OSError:  # it exited between the two
                    break
        result = run.result()
    finally:
        run.kill()
    _assert_whole(run, result, forged=len(forgeries))
    assert grown < FLOOD_GROWTH_MAX, f"the coordinator grew by {grown >> 20} MiB while refusing the flood"


def test_a_mac_holds_for_its_process_key_expression_and_payload_only(monkeypatch):
    """What the coordinator checks on arrival (origin.Senders): the node's process's key, over the
    key expression and the payload; another process's key, another key, another payload, a cut or
    missing MAC are refused and counted, with why."""
    from retriever.backends.zenoh.origin import KEY_FD_ENV, MAC_BYTES, Senders, key_pipe, new_key, sign, take_key

    old, new, insider = new_key(), new_key(), new_key()
    senders = Senders()
    senders.add("cam", old, "old process")
    senders.add("cam", new, "new process")
    status, report = "retriever/ns/status/node/cam", "retriever/ns/status/report/cam"
    assert senders.sender("cam", status, b"payload", sign(new, status, b"payload")) == "new process"
    assert senders.sender("cam", report, b"payload", sign(old, report, b"payload")) == "old process"
    refused = [(status, b"payload", sign(insider, status, b"payload")),
               (status, b"payload", sign(new, report, b"payload")),  # another key's MAC
               (status, b"payload!", sign(new, status, b"payload")),
               (status, b"payload", sign(new, status, b"payload")[:MAC_BYTES // 2]),
               (status, b"payload", None)]
    assert [senders.sender("cam", *message) for message in refused] == [None] * len(refused)
    assert senders.sender("mic", status, b"payload", sign(new, status, b"payload")) is None  # another node's
    assert senders.refused == len(refused) + 1 and len(senders.reasons) == Senders.KEPT
    assert "no process of 'cam' signed" in senders.reasons[0]
    pipe = key_pipe(new)
    monkeypatch.setenv(KEY_FD_ENV, str(pipe))
    assert take_key() == new and KEY_FD_ENV not in os.environ  # flows inherit neither the number
    with pytest.raises(OSError):  # nor the pipe
        os.fstat(pipe)


def test_no_worker_process_has_its_key_in_its_environment(tmp_path, namespace):
    """/proc/PID/environ shows a process's environment as it started, for its life, whatever it
    later removes from os.environ (to its user and root): the key comes through a pipe instead."""
    secret = _secret_file(tmp_path)
    run = Run(tmp_path, namespace, secret)
    try:
        with _insider(run, namespace, secret, tmp_path):
            environments = [Path(f"/proc/{_worker_pid(run.proc.pid, node)}/environ").read_bytes()
                            for node in ("counter", "total")]
        run.result()
    finally:
        run.kill()
    for environment in environments:
        assert b"RETRIEVER_PROCESS_KEY_FD=" in environment
        assert not any(entry.startswith(b"RETRIEVER_PROCESS_KEY=") for entry in environment.split(b"\0"))
