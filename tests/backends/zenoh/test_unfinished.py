"""What a run that did not finish says of each node it waited for
(issue 40, item 9; coordinator.Diagnostics.unfinished).

A 200 MiB-frame run failed with ``worker(s) big_src did not finish in time`` and an empty stacks
section: whatever keeps a node from finishing, the error shows its stacks or says why there are
none, and names the events that never reached the coordinator.
"""

from __future__ import annotations

import os
import signal
import threading
import time
from types import SimpleNamespace

import pytest
import zenoh

from retriever import BackendError, Pipeline
from retriever.backends.zenoh.worker import waits
from retriever.backends.zenoh.hub import endpoint, free_port, new_zid, peer_config, wait_for_links
from retriever.backends.zenoh.origin import new_key
from retriever.backends.zenoh.protocol import ControlOpener, ControlSigner, Finished
from retriever.backends.zenoh.seen import EventIds
from retriever.backends.zenoh.wire import KeySpace

from .lifecycle_flows import two_node_pipeline

BOUND_S = 60.0  # a bound on any wait, never a speed check


def _worker_pid(pipe: Pipeline, node: str) -> int:
    give_up = time.monotonic() + BOUND_S
    while time.monotonic() < give_up:
        session = pipe.session
        pids = session.worker_pids() if session is not None and hasattr(session, "worker_pids") else {}
        if node in pids and session.t0 is not None:
            return pids[node]
        time.sleep(0.02)
    raise AssertionError(f"no worker process of {node} in a started run within {BOUND_S:g} s")


def test_a_stopped_worker_is_said_to_have_printed_no_stacks_and_why(namespace):
    """SIGSTOP a worker mid-run: it never finishes, and SIGUSR1 asks for stacks it cannot print.
    The section of its stacks was empty; now it says that the process is stopped."""
    pipe = two_node_pipeline("stopped", source_hz=20, sink_hz=10)
    failed: list[BaseException] = []

    def run() -> None:
        try:
            pipe.run(duration=1.0, backend="zenoh", namespace=namespace, quiet=True)
        except BaseException as e:  # the test's thread: looked at below
            failed.append(e)

    thread = threading.Thread(target=run)
    thread.start()
    pid = _worker_pid(pipe, "counter")
    os.kill(pid, signal.SIGSTOP)
    try:
        thread.join(BOUND_S)
    finally:
        try:
            os.kill(pid, signal.SIGCONT)  # if the run did not kill it, it must go on to its end
        except ProcessLookupError:
            pass
        thread.join(BOUND_S)
    assert failed and isinstance(failed[0], BackendError), failed
    message = str(failed[0])
    assert "worker(s) counter" in message and "did not finish in time" in message, message
    assert (f"    counter: no stacks: its process (pid {pid}) printed none within 0.5 s of SIGUSR1: it is stopped "
            "(SIGSTOP, or a debugger)") in message, message
    with pytest.raises(ProcessLookupError):  # the run killed it
        os.kill(pid, 0)


@pytest.fixture
def namespace() -> str:
    return f"unfinished-{os.getpid()}-{time.monotonic_ns() % 10**9}"


# ---------------------------------------------------------------------------------------------
# A worker that said done keeps its session until the coordinator has its reports
# ---------------------------------------------------------------------------------------------
@pytest.fixture
def coordinator_and_worker():
    """Two real sessions linked on loopback: one answering the run's ``finished`` queries as told
    (``answers``: None leaves a query unanswered, else the nodes said complete), sealed for the
    worker's key (``opener`` opens them), one a worker's."""
    port = free_port()
    key, signer = new_key(), ControlSigner()
    signer.add(key, key)
    keys = KeySpace(f"taken-{os.getpid()}-{time.monotonic_ns() % 10**9}")
    answers: list[list[str] | None] = []
    asked: list[int] = []

    def answer(query) -> None:
        asked.append(len(asked))
        said = answers[min(len(asked), len(answers)) - 1]
        if said is not None:
            payload = Finished(nodes=tuple(said), complete=tuple(said), restarting=(), handed_over=()).encode()
            nonce = None if query.attachment is None else query.attachment.to_bytes()
            query.reply(keys.finished(), payload, attachment=signer.seal_reply(keys.finished(), payload, nonce))

    with zenoh.open(peer_config(listen=[endpoint(port)])) as coordinator, \
            zenoh.open(peer_config(connect=[endpoint(port)])) as worker_session:
        queryable = coordinator.declare_queryable(keys.finished(), answer)
        assert wait_for_links(worker_session, {str(coordinator.zid())}, BOUND_S) == set()
        # a link comes before the worker's session knows of the queryable: until one question is
        # answered, a worker's question may find no one to ask
        answers.append([])
        deadline = time.monotonic() + BOUND_S
        while not asked and time.monotonic() < deadline:
            list(worker_session.get(keys.finished(), timeout=0.25))
        assert asked, "the worker's session never reached the coordinator's queryable"
        asked.clear()
        answers.clear()
        yield SimpleNamespace(keys=keys, answers=answers, asked=asked, zid=str(coordinator.zid()),
                              worker=worker_session, coordinator=coordinator, opener=ControlOpener(key))
        queryable.undeclare()


def test_a_done_worker_waits_for_a_coordinator_that_answers_late(coordinator_and_worker):
    """A coordinator busy with its log left a ``finished`` query unanswered: the worker took it
    as gone, closed its session and a report still on its way was lost. It asks again while its
    link to the coordinator is up, and returns once the coordinator has its reports."""
    c = coordinator_and_worker
    c.answers[:] = [None, [], ["src"]]  # no answer, then "not yet", then "every report in"
    waits.await_reports_taken(c.worker, c.keys, c.opener, "src", c.zid)
    assert len(c.asked) == 3


def test_a_done_worker_does_not_wait_for_a_coordinator_it_has_no_link_to(coordinator_and_worker):
    c = coordinator_and_worker
    c.answers[:] = [None]
    waits.await_reports_taken(c.worker, c.keys, c.opener, "src", new_zid())  # a session it is not linked to
    assert len(c.asked) == 1


def test_a_done_node_short_of_reports_is_said_so_naming_the_events_they_held(namespace):
    """The events a node's lost reports held are named from what its ``done`` status says it
    sent ({port: last seq}) and what reached the coordinator. A real run, whose coordinator is
    then told a report and four of the last five events of counter.n were missing (no process
    loses a report on demand: this is the error's text for the state a lost report leaves; the
    netns lab lost two of a 200 MiB source's, issue 40's reproduction)."""
    pipe = two_node_pipeline("short", source_hz=20, sink_hz=10)
    pipe.run(duration=0.5, backend="zenoh", namespace=namespace, quiet=True)
    book = pipe.session.book
    last = book.intake.done_info["counter"]["sent"]["n"]  # what its worker said it sent, in its done status
    assert last == book.intake.have[("counter", "n")] >= 9
    book.intake.reports_sent["counter"] += 1
    book.intake.have[("counter", "n")] = last - 5
    book.intake.event_ids = EventIds()  # of the last five events, the coordinator got the third only
    for seq in [*range(last - 4), last - 2]:
        book.intake.event_ids.add(("counter", "n", seq))
    said = pipe.session.diagnostics.unfinished("counter")
    assert said.startswith(f"    counter said done after {book.intake.reports_sent['counter']} report(s), of which 1 "
                           f"never reached the coordinator; it never got the event(s) counter.n seqs {last - 4}-{last - 3}, "
                           f"{last - 1}-{last}\n"), said
    assert "    counter: no stacks: its process had ended (exited with code 0)" in said, said
