"""A worker daemon's events reach the coordinator signed with the run's key (issue 40; remote.py).

Anyone holding the namespace's secret may put on ``workers/<name>/events``: an ``exit`` there
made the coordinator count a live remote process dead (and restart its flow, or fail the run).
The daemon now signs each event with a key it made for the run and answered in its prepare
reply, which reaches the coordinator alone; the coordinator's RemoteHost takes no other.
"""

from __future__ import annotations

from retriever.backends.zenoh.origin import new_key, sign
from retriever.backends.zenoh.protocol import ProcessExit
from retriever.backends.zenoh.remote import RemoteHost, RemoteProcess
from retriever.backends.zenoh.wire import KeySpace

BOUND_S = 30.0  # a bound on any wait, never a speed check


def test_an_exit_event_the_daemon_did_not_sign_leaves_the_process_alive(session):
    keys = KeySpace("remote-events")
    host = RemoteHost(session, keys, "w1", "r1", zid="0")
    try:
        host.events_key = new_key()
        proc = host.processes[4242] = RemoteProcess(host, "cam", 4242, new_key())
        events = keys.worker_events("w1")
        forged = ProcessExit(run="r1", node="cam", pid=4242, code=-9).encode()
        session.put(events, forged)  # unsigned
        session.put(events, forged, attachment=sign(new_key(), events, forged))  # an insider's own key
        session.put(events, forged, attachment=sign(host.events_key, keys.worker_events("w2"), forged))  # another key
        genuine = ProcessExit(run="r1", node="cam", pid=4242, code=0).encode()
        session.put(events, genuine, attachment=sign(host.events_key, events, genuine))
        # one publisher's puts on one key arrive in order: the forged ones came first
        assert proc.wait(BOUND_S) == 0, "the daemon's own exit event is taken, and only it"
        assert host.garbage == 3
    finally:
        host.close()

