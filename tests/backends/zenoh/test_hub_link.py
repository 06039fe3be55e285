"""A worker says on stderr when its link to the coordinator is gone: while its node runs
(worker/links.py, watch_hub_link) and when it ends (worker/waits.py, await_reports_taken). Zenoh drops a put that no
link carries without an error and does not open a link found by gossip again, so without these
lines a flow that lost that link ended with only "exited with code 0 before it finished" on the
coordinator's side (benchmarks/reports/partition_move.md; benchmarks/link_stall.py makes Zenoh
close such a link)."""

from __future__ import annotations

import time

from retriever.backends.zenoh.hub import new_zid, open_hub, open_peer, wait_for_links
from retriever.backends.zenoh.protocol import ControlOpener
from retriever.backends.zenoh.wire import KeySpace
from retriever.backends.zenoh.worker.links import watch_hub_link
from retriever.backends.zenoh.worker.waits import await_reports_taken

BOUND_S = 20.0  # a bound only: the close is seen within ms


def test_a_worker_says_when_its_link_to_the_coordinator_closes(capfd):
    hub, endpoint = open_hub(0)
    with open_peer(endpoint, shared_memory=False) as session:
        hub_zid = str(hub.zid())
        assert not wait_for_links(session, {hub_zid}, BOUND_S)
        listener = watch_hub_link(session, hub_zid, "camera")
        try:
            assert "lost its link" not in capfd.readouterr().err  # linked: nothing said
            hub.close()
            said, give_up = "", time.monotonic() + BOUND_S
            while "lost its link" not in said and time.monotonic() < give_up:
                said += capfd.readouterr().err
                time.sleep(0.01)
        finally:
            listener.undeclare()
    assert "worker 'camera' lost its link to the coordinator" in said
    assert "does not reach the coordinator" in said


def test_a_worker_without_a_hub_id_watches_nothing():
    hub, endpoint = open_hub(0)
    with hub, open_peer(endpoint, shared_memory=False) as session:
        assert watch_hub_link(session, None, "camera") is None


def test_a_worker_that_ends_with_no_link_to_the_coordinator_says_so(capfd):
    hub, endpoint = open_hub(0)
    with hub, open_peer(endpoint, shared_memory=False) as session:
        await_reports_taken(session, KeySpace("lost"), ControlOpener(None), "camera", new_zid())  # a coordinator it is not linked to
    assert "worker 'camera' has no link to the coordinator at its end" in capfd.readouterr().err
