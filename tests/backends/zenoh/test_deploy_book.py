"""WorkerBook (backends/zenoh/deploy/book.py): a move weighs the workers as the first placement
did, the nodes of other runs each listed when it was found and this run's nodes placed on it."""

from __future__ import annotations

from retriever.backends.zenoh.daemon import DaemonInfo
from retriever.backends.zenoh.deploy.book import WorkerBook
from retriever.backends.zenoh.protocol import PROTOCOL_VERSION, InfoReply
from retriever.placement import ANYWHERE, assign


def found(name: str, nodes: tuple[str, ...]) -> DaemonInfo:
    info = InfoReply(protocol=PROTOCOL_VERSION, name=name, labels=(), host=f"{name}-host", pid=1, python="3.11",
                     packages={}, clock_ns=0, nodes=nodes, counts={})
    return DaemonInfo(name, info, 0, None)


def test_a_move_counts_the_nodes_of_other_runs_as_the_first_placement_did():
    book = WorkerBook(daemons={"busy": found("busy", ("other_a", "other_b", "other_c")), "idle": found("idle", ())})
    book.placed = {"cam": "busy", "ctrl": "idle"}
    up = {w.name: w.nodes for w in book.workers_up()}
    assert up == {"busy": 4, "idle": 1}
    # the lost worker's node goes where the first placement would have put it: the less loaded
    assert assign(["policy"], {"policy": ANYWHERE}, book.workers_up()) == {"policy": "idle"}
