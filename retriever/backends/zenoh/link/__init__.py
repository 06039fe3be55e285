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

Wired into the node loop behind the Transport seam (node/linked.py, LinkedTransport):

- Which edges: where every process of the run is on this host (the coordinator's Hosting says
  so: LocalHosting, the spec's ``links``; ``pipe.run(..., same_host_links=False)`` opts out),
  every edge between two processes but a group's (configure(process=): its process keeps Zenoh
  for its edges). A deployment's (worker daemons) stay on Zenoh, those within one daemon too.
  Both ends read it from the same spec (worker/links.py, link_plan), so they agree without
  asking.
- Where the socket is: the run folder both ends share, ``link-<node>.sock`` (``link-<i>.sock``
  where that is too long for sun_path). The producer makes its LinkServer as it declares its
  outputs, before it says ready; its consumers connect after the start's barrier (every
  producer ready), before T0, and its first send waits for them there (worker/starts.py); a
  planned link that cannot connect fails the run, naming the edge and the socket.
- The sender: each output port's publisher and the progress publisher send on the node's one
  LinkServer (kind 1 + the port's index, PROGRESS), so a watermark never overtakes the data it
  covers; a warm-up (timing.py) too. Zenoh gets the message only while the Zenoh publisher's
  matching status says someone matches the key (a ``data/**`` watcher, a consumer on Zenoh):
  the run's linked consumers subscribe to none of it.
- The receiver: no Zenoh subscription to a linked producer's data and progress; a LinkClient
  whose messages go to the loop as the Zenoh callbacks' do (inline on the client's thread where
  the loop may step there).
- Restarts: a restarted consumer connects anew (worker/starts.py, join and start_afresh); a
  restarted producer makes a new LinkServer at the same path, and its consumers, whose link
  closed, connect to it by themselves (a producer whose loop finished says END: not waited for).
- The log: unchanged (the reports carry the events); replay never meets a link.
- The dora backend, and a group's flows in one process (by reference): untouched.
"""

from __future__ import annotations

from .client import LinkClient
from .server import LinkServer

__all__ = ["LinkClient", "LinkServer"]
