"""A worker daemon's events reach the coordinator sealed with the run's key (issue 40; remote.py).

Anyone holding the namespace's secret may put on ``workers/<name>/events``: an ``exit`` there
made the coordinator count a live remote process dead (and restart its flow, or fail the run).
The daemon now seals each event with a key it made for the run and answered in its prepare
reply, which reaches the coordinator alone, and a counter (seal.py); the coordinator's RemoteHost
takes no other event, and none twice.
"""

from __future__ import annotations

from contextlib import contextmanager

from retriever.backends.zenoh.origin import new_key, sign
from retriever.backends.zenoh.protocol import ControlOpener, ControlSigner, ProcessExit, ProcessOutput, Stream
from retriever.backends.zenoh.remote import RemoteHost, RemoteProcess
from retriever.backends.zenoh.wire import KeySpace

BOUND_S = 30.0  # a bound on any wait, never a speed check


def daemon_seal(key: bytes) -> ControlSigner:
    """What the daemon's run seals its events with (runs.Run)."""
    signer = ControlSigner()
    signer.add(signer, key)
    return signer


@contextmanager
def listening(session, namespace: str):
    """A coordinator's RemoteHost for daemon ``w1``'s run ``r1``, holding the run's key, with one
    process of node ``cam`` (pid 4242): ``(host, process, events key, run key)``."""
    keys = KeySpace(namespace)
    host = RemoteHost(session, keys, "w1", "r1", zid="0")
    try:
        run_key = new_key()
        host.events = ControlOpener(run_key)
        proc = host.processes[4242] = RemoteProcess(host, "cam", 4242, new_key())
        yield host, proc, keys.worker_events("w1"), run_key
    finally:
        host.close()


def test_an_exit_event_the_daemon_did_not_seal_leaves_the_process_alive(session):
    with listening(session, "remote-events") as (host, proc, events, run_key):
        forged = ProcessExit(run="r1", node="cam", pid=4242, code=-9).encode()
        session.put(events, forged)  # unsealed
        session.put(events, forged, attachment=daemon_seal(new_key()).seal(events, forged))  # an insider's own key
        elsewhere = KeySpace("remote-events").worker_events("w2")
        session.put(events, forged, attachment=daemon_seal(run_key).seal(elsewhere, forged))  # another key expression
        session.put(events, forged, attachment=sign(run_key, events, forged))  # signed as before, with no counter
        genuine = ProcessExit(run="r1", node="cam", pid=4242, code=0).encode()
        session.put(events, genuine, attachment=daemon_seal(run_key).seal(events, genuine))
        # one publisher's puts on one key arrive in order: the forged ones came first
        assert proc.wait(BOUND_S) == 0, "the daemon's own exit event is taken, and only it"
        assert host.garbage == 4


def test_a_replayed_output_event_is_refused_and_prints_nothing_twice(session):
    """An insider who captured a sealed event and puts it again (the same bytes, the same seal):
    the counter was taken once; the replay is counted as garbage, its lines are not fed again."""
    with listening(session, "remote-replays") as (host, proc, events, run_key):
        seal = daemon_seal(run_key)
        host.output("cam").forwarding = False  # (kept in its tail only)
        output = ProcessOutput(run="r1", node="cam", stream=Stream.STDERR, lines=("hello",)).encode()
        sealed = seal.seal(events, output)
        session.put(events, output, attachment=sealed)
        session.put(events, output, attachment=sealed)  # the replay
        last = ProcessExit(run="r1", node="cam", pid=4242, code=0).encode()
        session.put(events, last, attachment=seal.seal(events, last))
        assert proc.wait(BOUND_S) == 0  # in order: the output and its replay came before
        assert host.garbage == 1
        assert host.output("cam").stderr_lines == 1 and host.output("cam").tail().strip() == "hello"
