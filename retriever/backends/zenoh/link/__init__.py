"""Same-host links: a producer's ordered messages to its consumers on the same host, over a Unix
socket of its own instead of Zenoh (benchmarks/reports/shm_channel.md, design B).

    frames.py   the messages on a link's socket (handshake, inline, handle, ack), exact decoders
    ring.py     the ring of slots in a sealed memfd: written from a message's parts, copied out
    server.py   the producer's end: its socket in the run folder, consumers admitted, sends in order
    client.py   a consumer's end: connects, checks, a thread that copies out, acks and hands on

Small messages go inline through the socket, big ones through the ring with a handle on the
socket; acks come back over it; a producer waits (bounded) for a slot rather than lose a message
or rewrite one under a reader; a message bigger than the slots makes a bigger ring, passed to each
consumer in the stream's order. A link carries opaque messages with a kind byte in one order, so
a producer's progress can go on the same stream as its data. Everything a peer sends is checked
before use; a bad peer is dropped, never the process. A SIGKILLed process leaves at most its
socket file in the run folder (removed with the folder, folders.py); a ring has no name.

Part 2 (not built yet): wiring links into the node loop.

- Which edges: the coordinator's plan knows which nodes run on which host (``Hosting``: the
  spec gives each node's host); an edge whose producer and consumer one host spawns is a link,
  one across hosts stays on Zenoh. Both ends read the same spec, so they agree without asking.
- Where the socket is: the run folder both ends already share (the coordinator's
  ``retriever-run-PID-…``, a daemon's ``retriever-worker-PID-run-…``), named by the producer
  node (``link-<node>.sock``, short enough for sun_path). The producer's worker makes its
  LinkServer before it says ready; a consumer connects after the start's barrier (every producer
  ready), so no message before T0 is missed; a planned link that cannot connect fails the run,
  naming the edge (no silent fallback: the consumer would wait for data that went elsewhere).
- The sender: ``node/transport.py``'s ``declare_outputs`` gives a port with same-host consumers
  the node's LinkServer; ``node/outputs.py``'s publish hands it ``encoder.data_parts(...)`` (no
  join) with kind DATA. Progress (``WireEncoder.progress``) goes on the same link with kind
  PROGRESS, so a watermark never overtakes the data it covers. Zenoh's put of the joined message
  stays for remote consumers and watchers, made only while the Zenoh publisher's matching status
  says someone matches the key (DESIGN.md: a plain Zenoh client on ``data/**`` can watch a run):
  with only local consumers no join and no Zenoh put.
- The receiver: ``transport.declare_inputs`` does not subscribe to the data and progress keys of
  a same-host producer; it opens a LinkClient whose ``on_message`` hands ``(DATA | PROGRESS,
  stream, bytes)`` to the loop's receive exactly as the Zenoh callback does; ``on_closed`` is
  the producer's end (as the coordinator's loss of a worker is today: the run decides).
- Restarts: a restarted consumer connects anew (its producer admits it; it gets the messages
  from then on, as a restarted Zenoh subscriber does; the hand-over of its state is unchanged);
  a restarted producer makes a new LinkServer at the same path (its consumers' on_closed, then
  reconnect to it on the restart's control message).
- The log: unchanged. The producer's reports still carry its events to the coordinator (the
  report's copy of the message comes from the parts, or from the slot while the reporter holds
  it); replay never meets a link.
- The dora backend, and a group's flows in one process (by reference): untouched.
"""

from __future__ import annotations

from .client import LinkClient
from .server import LinkServer

__all__ = ["LinkClient", "LinkServer"]
