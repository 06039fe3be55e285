"""The coordinator's parts with no hub and no process (coordinator/: assemble over a RunBook):
the status machine's table, its stages, and a hosting handed in."""

from __future__ import annotations

import subprocess
import sys
from collections import Counter
from types import SimpleNamespace

import pytest

from retriever import BackendError, Pipeline, Rate
from retriever.backends.base import output_ports
from retriever.backends.zenoh.coordinator import BookView, Hosting, RunBook, RunControl, assemble
from retriever.backends.zenoh.protocol import Done, Failed, Ready, State, Status
from retriever.backends.zenoh.wire import KeySpace
from retriever.trace import Trace
from tests.backends.zenoh.lifecycle_flows import SOURCE_HZ, Counter as CounterFlow

NAMESPACE = "parts"


class _Hub:
    """The hub's put, for a coordinator with no Zenoh: what it was asked to put."""

    def __init__(self) -> None:
        self.puts: list[str] = []

    def put(self, key: str, payload: bytes, **_) -> None:
        self.puts.append(key)


class _Process:
    def __init__(self, pid: int):
        self.pid = pid


class _LostHosting(Hosting):
    """A hosting that says where it is, and records what a host lost meant."""

    def __init__(self) -> None:
        self.lost: list[list[str]] = []

    def host_lost(self, host, nodes: list[str]):
        self.lost.append(nodes)
        return super().host_lost(host, nodes)


@pytest.fixture
def offline(tmp_path):
    with Pipeline("parts") as pipe:
        CounterFlow() @ Rate(hz=SOURCE_HZ)
    graph = pipe.compile()
    trace, counts = Trace(keep="trace"), Counter()
    trace.ports = output_ports(graph)
    book = RunBook(graph, counts)
    book.processes.workers = {"counter": _Process(40_000)}
    book.processes.state = {"counter": "starting"}
    hosting = _LostHosting()
    parts = assemble(book, trace, tmp_path, RunControl(_Hub(), KeySpace(NAMESPACE)), hosting)
    hosting.attach(SimpleNamespace(book=BookView(book)))  # what a hosting reads of its run here (HostedRun)
    return book, parts, hosting


def _status(kind: type[Status], **fields) -> tuple[str, bytes]:
    return KeySpace(NAMESPACE).node_status("counter"), kind(node="counter", pid=40_000, **fields).encode()


def test_every_state_a_worker_may_say_has_one_handler(offline):
    _, parts, _ = offline
    assert sorted(parts.statuses.handlers) == sorted(State)


def test_a_process_goes_from_ready_to_done_once_and_a_replay_is_garbage(offline):
    book, parts, _ = offline
    sender = book.processes.workers["counter"]
    parts.inbox.handle((*_status(Ready), sender))
    assert book.processes.state["counter"] == "ready"
    parts.inbox.handle((*_status(Done, reports=2, counts={"late": 1}), sender))
    assert (book.processes.state["counter"], book.intake.reports_sent["counter"],
            book.intake.stats["counter"].counts) == ("done", 2, {"late": 1})
    parts.inbox.handle((*_status(Done, reports=2, counts={"late": 1}), sender))  # replayed: refused, not counted
    parts.inbox.handle((*_status(Ready), sender))
    assert (book.processes.state["counter"], book.intake.reports_sent["counter"],
            book.counts["garbage"]) == ("done", 2, 2)


def test_a_status_no_process_of_the_node_signed_changes_nothing(offline):
    book, parts, _ = offline
    forged = _status(Failed, error="forged", traceback=None)
    parts.inbox.handle((*forged, _Process(40_000)))  # same pid, another process
    assert (book.ending.failure, book.processes.state["counter"], book.counts["garbage"]) == (None, "starting", 1)


def test_a_host_lost_goes_to_the_hosting_handed_in(offline):
    book, parts, hosting = offline

    class Gone:
        name, alive = "gone-box", False

    book.processes.hosts = {"counter": Gone()}
    with pytest.raises(BackendError, match="zenoh run stopped: worker 'gone-box' was lost"):
        parts.supervisor.check()
    assert hosting.lost == [["counter"]]


class _AskedProcess(subprocess.Popen):
    """A real child process that counts how often it is asked whether it ended."""

    asked = 0

    def poll(self):
        self.asked += 1
        return super().poll()


def test_a_check_asks_each_process_once_whether_it_ended(offline):
    """An idle coordinator checks its processes every pass: each is polled once a check (it was
    twice: once to stop sealing control for it, once to see whether it died), running or ended."""
    book, parts, _ = offline

    class Up:
        name, alive = "box", True

    book.processes.hosts = {"counter": Up()}
    proc = _AskedProcess([sys.executable, "-c", "import sys; sys.stdin.read()"], stdin=subprocess.PIPE)
    try:
        book.processes.workers = {"counter": proc}
        parts.control.signer.add(proc, b"k" * 32)
        parts.supervisor.check()
        assert (proc.asked, parts.control.signer.holders()) == (1, [proc])  # running: control still sealed
    finally:
        proc.stdin.close()
        proc.wait()
    proc.asked = 0
    parts.supervisor.check()  # its own exit (0): its last status may still come; control is no longer sealed
    assert (proc.asked, parts.control.signer.holders()) == (1, [])


def test_out_of_restarts_from_a_flow_that_never_restarts_is_its_step_error(offline):
    """``out_of_restarts`` is said by a group's member restarting in place: from a flow whose
    on_error is not "restart" (the counter's: "stop") it names a budget the flow never had, so
    the run raises the step's own error."""
    from retriever import RestartLimitError, StepError
    from retriever.backends.zenoh.coordinator.diagnostics import failure_error

    book, parts, _ = offline
    sender = book.processes.workers["counter"]
    parts.inbox.handle((*_status(Failed, error="counter.step() raised ValueError: x", traceback=None, tag=(7, 0),
                                 raised="ValueError: x", out_of_restarts=True), sender))
    error = failure_error(book, "zenoh")
    assert isinstance(error, StepError) and not isinstance(error, RestartLimitError), error
    assert "ValueError: x" in str(error)
