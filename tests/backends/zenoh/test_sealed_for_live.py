"""Control is sealed for the processes that may still read it, not for every one a run started
(issue 40; protocol/seal.py, coordinator/processes.py).

The coordinator seals each control message with one MAC per process it holds the key of. It
held every key it ever gave: a run that restarts a flow again and again sent bigger and bigger
control messages, and past MAX_SEALED processes its workers refused them. It now drops a
process's key once that process's exit is confirmed: a child of the coordinator reaped, a worker
daemon's said exited by its daemon (one whose daemon was lost may still run, and still gets
control: a ``stop``). Nothing is dropped earlier: a process SIGKILLed but not reaped may yet be
reading.
"""

from __future__ import annotations

import subprocess
import time
from collections import Counter

import pytest

from retriever import Pipeline, Rate
from retriever.backends.base import output_ports
from retriever.backends.zenoh.coordinator import Hosting, RunBook, RunControl, assemble
from retriever.backends.zenoh.host import Host
from retriever.backends.zenoh.origin import MAC_BYTES
from retriever.backends.zenoh.protocol import RUN_CONTROL, Lost, ProcessExit, Stop
from retriever.backends.zenoh.protocol.seal import COUNTER_BYTES
from retriever.backends.zenoh.remote import LOST_CODE
from retriever.backends.zenoh.wire import KeySpace
from retriever.trace import Trace
from tests.backends.zenoh.dying_flows import DiesTimes, RaisesTimes
from tests.backends.zenoh.lifecycle_flows import SOURCE_HZ, Counter as CounterFlow
from tests.backends.zenoh.test_remote_events import daemon_seal, listening

BOUND_S = 60.0  # a bound on any wait, never a speed check
RESTARTS = 5


def sealed_for(attachment: bytes) -> int:
    """How many processes a ctl/run put's attachment is sealed for (one MAC each)."""
    return (len(attachment) - COUNTER_BYTES) // MAC_BYTES


class _Child:
    """A worker process as subprocess.Popen is one: SIGKILLed, it has exited only once reaped
    (poll or wait says how it ended)."""

    def __init__(self, pid: int):
        self.pid = pid
        self.returncode: int | None = None
        self.killed = False

    def poll(self) -> int | None:
        return self.returncode

    def wait(self, timeout: float | None = None) -> int:
        if self.returncode is None and self.killed:
            self.returncode = -9
        if self.returncode is None:
            raise subprocess.TimeoutExpired(str(self.pid), timeout or 0.0)
        return self.returncode

    def send_signal(self, sig: int) -> None:
        pass  # a SIGTERM this one does not heed

    def kill(self) -> None:
        self.killed = True


class _Host(Host):
    """Starts _Child processes, and keeps every one."""

    def __init__(self) -> None:
        super().__init__()
        self.started: list[_Child] = []

    def spawn(self, node, mode=(), key=None):
        proc = _Child(50_000 + len(self.started))
        self.started.append(proc)
        return proc, key


class _Hub:
    """The hub's put, for a coordinator with no Zenoh: the attachment of each."""

    def __init__(self) -> None:
        self.attachments: list[bytes] = []

    def put(self, key: str, payload: bytes, attachment: bytes = b"", **_) -> None:
        self.attachments.append(attachment)


@pytest.fixture
def supervised(tmp_path):
    """A run's supervisor, its processes on a _Host, after the run's start: ``(book, supervisor,
    control, host, hub)``."""
    with Pipeline("sealed") as pipe:
        CounterFlow().configure(on_error="restart") @ Rate(hz=SOURCE_HZ)
    graph = pipe.compile()
    trace = Trace(keep="trace")
    trace.ports = output_ports(graph)
    book = RunBook(graph, Counter())
    host = _Host()
    book.processes.hosts = {"counter": host}
    hub = _Hub()
    parts = assemble(book, trace, tmp_path, RunControl(hub, KeySpace("sealed")), Hosting())
    book.t0 = time.time_ns()
    return book, parts.supervisor, parts.control, host, hub


def _restart_afresh(book, supervisor, times: int) -> None:
    """Start the flow afresh ``times`` times (as after its process died): each old one SIGKILLed."""
    for _ in range(times):
        proc = book.processes.workers["counter"]
        supervisor.start_afresh("counter", {"node": "counter", "at_ns": 0, "pid": proc.pid,
                                            "exit": "was killed by SIGKILL"})


def test_control_is_sealed_for_the_processes_whose_exit_is_not_confirmed(supervised):
    book, supervisor, control, host, hub = supervised
    supervisor.spawn("counter")
    _restart_afresh(book, supervisor, RESTARTS)
    assert len(host.started) == RESTARTS + 1
    supervisor.check()
    control.put(Stop())
    # SIGKILLed, none reaped yet: each may still be reading, and must be able to take a stop
    assert sealed_for(hub.attachments[-1]) == RESTARTS + 1
    for proc in host.started[:-1]:
        proc.wait()  # reaped: its exit is confirmed
    supervisor.check()
    control.put(Stop())
    assert sealed_for(hub.attachments[-1]) == 1
    assert control.signer.holders() == [book.processes.workers["counter"]]


def test_once_the_runs_processes_are_reaped_control_is_sealed_for_none(supervised):
    book, supervisor, control, host, hub = supervised
    supervisor.spawn("counter")
    _restart_afresh(book, supervisor, RESTARTS)
    supervisor.reap(grace=0.0)
    assert all(proc.returncode is not None for proc in host.started)
    assert control.signer.holders() == []


def test_a_daemons_process_is_sealed_for_until_its_daemon_says_it_exited(supervised, session):
    """A worker daemon lost (its liveliness token went): its processes count as killed, yet may
    run on (a daemon cut off from the coordinator, not dead); control is still sealed for them
    until the daemon's sealed ``exit`` event says one ended."""
    _, supervisor, control, _, _ = supervised
    with listening(session, "sealed-remote") as (host, proc, events, run_key):
        control.signer.add(proc, proc.key)
        host.lost()
        assert proc.poll() == LOST_CODE
        supervisor.forget_ended()
        assert control.signer.holders() == [proc]
        genuine = ProcessExit(run="r1", node="cam", pid=4242, code=0).encode()
        session.put(events, genuine, attachment=daemon_seal(run_key).seal(events, genuine))
        assert proc.wait_confirmed(BOUND_S)  # (the event's delivery)
        supervisor.forget_ended()
        assert control.signer.holders() == []


class _Recording:
    """The coordinator's hub, for its control puts: each record's name and how many processes
    it was sealed for."""

    def __init__(self, hub):
        self.hub = hub
        self.sealed: list[tuple[str, int]] = []

    def put(self, key_expr, payload, **options):
        self.sealed.append((RUN_CONTROL.decode(payload).NAME, sealed_for(options["attachment"])))
        self.hub.put(key_expr, payload, **options)


def _run_recorded(flow: type, name: str, tmp_path, at: int = 3):
    """A run of ``flow`` (dying_flows: RESTARTS failures, then the end) restarting as it fails,
    with each control put recorded: ``(pipe, session, recording)`` once it ended."""
    failures = tmp_path / "failures"
    failures.mkdir()
    with Pipeline(name) as pipe:
        flow(str(failures), RESTARTS, at=at).configure(name=name, on_error="restart",
                                                       max_restarts=RESTARTS) @ Rate(hz=10)
    session = pipe.open("zenoh", quiet=True)
    recording = session.control.hub = _Recording(session.control.hub)
    pipe.run(duration=BOUND_S, backend="zenoh")
    return pipe, session, recording


def test_a_flow_restarted_again_and_again_gets_control_sealed_for_its_live_processes(tmp_path):
    """Real processes: a flow whose process dies at its third step is started afresh RESTARTS
    times, then ends the run (sys.exit(0); the duration is a bound, never reached). Each control
    message is sealed for at most the dead process and its replacement: by the next death the
    one before is forgotten, and once the run's processes are reaped, every one is."""
    pipe, session, recording = _run_recorded(DiesTimes, "dying", tmp_path)
    assert session.ended_by == "dying"
    assert pipe.stats()["dying"].counts["crash_restarts"] == RESTARTS
    lost = [n for name, n in recording.sealed if name == Lost.NAME]
    assert len(lost) == RESTARTS and max(lost) <= 1, recording.sealed
    assert max(n for _, n in recording.sealed) <= 2, recording.sealed
    assert session.control.signer.holders() == []


def test_a_flow_that_hands_over_again_and_again_leaves_no_old_process_running(tmp_path):
    """Real processes: a flow whose step raises at its tenth step of each process is restarted
    RESTARTS times by hand-over, then ends the run. Each old process exits once the coordinator
    has its reports (the ``finished`` answer's handed_over), not at the run's end: so control is
    sealed for a few processes at a time, not for every one the run started."""
    pipe, session, recording = _run_recorded(RaisesTimes, "raising", tmp_path, at=10)
    assert session.ended_by == "raising"
    assert pipe.stats()["raising"].counts["restarts"] == RESTARTS
    assert max(n for _, n in recording.sealed) <= 3, recording.sealed
    assert session.control.signer.holders() == []
