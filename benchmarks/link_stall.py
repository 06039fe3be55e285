"""A process loses a healthy link while Zenoh closes a congested one (the lost reports of issue 40's
partition runs): N trials, each in three processes on this machine, no network namespaces.

``hub`` (a coordinator's session, ``--lease``, 1 s as the partition runs have it) and ``consumer``
run in their own processes; this process is the producer, a flow on a worker daemon: it links to
both (the consumer through gossip, as there), with Zenoh's default lease and ``--blocked-put`` (its
daemon's lease). A thread puts 32 KiB frames to the consumer (BLOCK, every ``--gap`` s, 20 ms: 50
Hz); then the consumer is stopped (SIGSTOP: its host cut off, its socket full). The producer's put
waits ``--blocked-put``, Zenoh closes that link, and its close takes the link's queue lock, on a
thread that also reads links, waiting for each put that holds it before the link leaves the
routes. If that outlasts the hub's lease, the producer's healthy link to the hub expires (nothing
read from it for a lease) and Zenoh does not open it again: a trial counts it **lost**.

    PYTHONPATH=. .venv/bin/python benchmarks/link_stall.py --trials 10
    PYTHONPATH=. .venv/bin/python benchmarks/link_stall.py --trials 10 --blocked-put 0.25

Shared memory is off (on one host it would carry the frames past the full socket).
"""

from __future__ import annotations

import argparse
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import zenoh  # noqa: E402

from retriever.backends.zenoh.hub import free_port, peer_config  # noqa: E402
from retriever.backends.zenoh.wire import RELIABLE  # noqa: E402

#: how long after the consumer stops a trial watches the producer's link to the hub
WATCH_S = 8.0
FRAME = bytes(32 << 10)


def serve(role: str, port: int, lease: float) -> None:
    """The hub (listening on ``port``) or the consumer (joined to it), until killed."""
    if role == "hub":
        session = zenoh.open(peer_config(listen=[f"tcp/127.0.0.1:{port}"], lease=lease, shared_memory=False))
        session.declare_subscriber("stall/report/**", lambda sample: None)
    else:
        session = zenoh.open(peer_config(listen=["tcp/127.0.0.1:0"], connect=[f"tcp/127.0.0.1:{port}"],
                                         shared_memory=False))
        session.declare_subscriber("stall/data/**", lambda sample: None)
    print("up", flush=True)
    signal.pause()


def trial(lease: float, blocked_put: float, gap: float) -> float | None:
    """One trial: when (s after the consumer stopped) the producer lost its link to the hub, or None."""
    port = free_port()
    started = [subprocess.Popen([sys.executable, __file__, "--serve", role, str(port), str(lease)],
                                stdout=subprocess.PIPE, text=True) for role in ("hub", "consumer")]
    stop = threading.Event()
    try:
        for proc in started:
            proc.stdout.readline()
        session = zenoh.open(peer_config(listen=["tcp/127.0.0.1:0"], connect=[f"tcp/127.0.0.1:{port}"],
                                         blocked_put=blocked_put, shared_memory=False))
        try:
            give_up = time.monotonic() + 10
            while len(session.info.peers_zid()) < 2 and time.monotonic() < give_up:
                time.sleep(0.01)
            linked = {str(z) for z in session.info.peers_zid()}
            publisher = session.declare_publisher("stall/data/cam", express=True, congestion_control=RELIABLE)

            def produce() -> None:
                while not stop.is_set():
                    publisher.put(FRAME)
                    time.sleep(gap)

            threading.Thread(target=produce, daemon=True).start()
            time.sleep(0.5)
            os.kill(started[1].pid, signal.SIGSTOP)
            cut = time.monotonic()
            while time.monotonic() - cut < WATCH_S:
                if len(linked - {str(z) for z in session.info.peers_zid()}) == len(linked):  # the hub's too
                    return time.monotonic() - cut
                time.sleep(0.02)
            return None
        finally:
            stop.set()
            os.kill(started[1].pid, signal.SIGKILL)  # before the close: a stopped peer holds it
            session.close()
    finally:
        for proc in started:
            proc.kill()
            proc.wait()


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--trials", type=int, default=10)
    parser.add_argument("--lease", type=float, default=1.0, help="the hub's lease, s")
    parser.add_argument("--blocked-put", type=float, default=1.0, help="the producer's, s")
    parser.add_argument("--gap", type=float, default=0.02, help="s between the producer's puts")
    parser.add_argument("--serve", nargs=3, help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.serve:
        serve(args.serve[0], int(args.serve[1]), float(args.serve[2]))
        return 0
    lost = 0
    for i in range(args.trials):
        at = trial(args.lease, args.blocked_put, args.gap)
        lost += at is not None
        print(f"trial {i + 1}: link to the hub {'lost %.1f s after the cut' % at if at is not None else 'kept'}",
              flush=True)
    print(f"lost {lost} of {args.trials} (hub lease {args.lease:g} s, blocked put {args.blocked_put:g} s, "
          f"a put every {args.gap:g} s)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
