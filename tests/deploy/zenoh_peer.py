"""A Zenoh peer on a lab host, and the test's handle on it.

Run inside a host's namespace as ``python -m tests.deploy.zenoh_peer NAME [--listen EP]
[--connect EP] [--access SPEC] [--lease-ms MS]``, it opens a session with the embedded runtime's
own peer config (``hub.peer_config``; with ``--access``, a run's authentication and access
control from ``access.py``), puts its sequence number on ``lab/NAME`` every PERIOD_S, subscribes
to the others' ``lab/**``, and prints one JSON line per event:

    {"ready": zid}                the session is open
    {"sent": seq}                 after each put
    {"peers": n}                  the number of peers it has a link to changed
    {"got": key, "seq": seq}      a put of another peer arrived

It stops when its stdin closes, or after ``--lifetime`` s whatever happens, and closes its
session first: a session still receiving at exit can hang the interpreter (dependencies.md).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import threading
import time
from collections import Counter
from pathlib import Path

from tests.deploy.lab import ROOT, Host

PERIOD_S = 0.05
LIFETIME_S = 60.0  # a peer the test forgot still exits by itself
STOP_S = 5.0  # how long a peer gets to close its session once its stdin closed


# ---------------------------------------------------------------------------------------------
# The peer (in the host's namespace)
# ---------------------------------------------------------------------------------------------
def _main(argv: list[str]) -> None:
    import zenoh

    from retriever.backends.zenoh.access import RunAccess
    from retriever.backends.zenoh.hub import peer_config

    ap = argparse.ArgumentParser(prog="zenoh_peer")
    ap.add_argument("name")
    ap.add_argument("--listen", action="append", default=[])
    ap.add_argument("--connect", action="append", default=[])
    ap.add_argument("--access", type=Path, help="a run's spec (RunAccess.to_spec) as a JSON file")
    ap.add_argument("--lease-ms", type=int)
    ap.add_argument("--lifetime", type=float, default=LIFETIME_S)
    args = ap.parse_args(argv)

    lock = threading.Lock()

    def emit(**event) -> None:  # the subscriber's thread and the main thread both print
        with lock:
            print(json.dumps(event), flush=True)

    access = None
    if args.access:
        run, dictionary = RunAccess.from_spec(json.loads(args.access.read_text()))
        access = run.session_config(dictionary)
    config = peer_config(listen=args.listen, connect=args.connect, access=access)
    if args.lease_ms:
        config.insert_json5("transport/link/tx/lease", str(args.lease_ms))

    stop = threading.Event()
    threading.Thread(target=lambda: (sys.stdin.read(), stop.set()), daemon=True).start()
    give_up = time.monotonic() + args.lifetime
    with zenoh.open(config) as session:
        session.declare_subscriber(
            "lab/**", lambda s: emit(got=str(s.key_expr), seq=int(s.payload.to_bytes())),
            allowed_origin=zenoh.Locality.REMOTE)
        emit(ready=str(session.zid()))
        seq, peers = 0, 0
        while not stop.wait(PERIOD_S) and time.monotonic() < give_up:
            seq += 1
            session.put(f"lab/{args.name}", str(seq))
            emit(sent=seq)
            if (n := len(session.info.peers_zid())) != peers:
                peers = n
                emit(peers=n)


# ---------------------------------------------------------------------------------------------
# The test's handle
# ---------------------------------------------------------------------------------------------
class Peer:
    """A zenoh_peer process on ``host``, and the events it printed so far (read on a thread)."""

    def __init__(self, host: Host, name: str, *, listen: list[str] = (), connect: list[str] = (),
                 access: Path | None = None, lease_ms: int | None = None):
        self.name = name
        argv = [sys.executable, "-m", "tests.deploy.zenoh_peer", name]
        argv += [f"--listen={e}" for e in listen] + [f"--connect={e}" for e in connect]
        if access:
            argv.append(f"--access={access}")
        if lease_ms:
            argv.append(f"--lease-ms={lease_ms}")
        env = {k: v for k, v in os.environ.items() if k not in ("FORCE_COLOR", "PYTHONPATH")}
        env.update(PYTHONPATH=str(ROOT), PYTHONDONTWRITEBYTECODE="1")
        self.proc = host.popen(argv, cwd=ROOT, env=env, stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                               stderr=subprocess.STDOUT, text=True)
        self.events: list[dict] = []
        self.other: list[str] = []  # anything that is not an event: a traceback, a Zenoh log line
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()

    def _read(self) -> None:
        for line in self.proc.stdout:
            try:
                event = json.loads(line)
            except ValueError:
                event = None
            if isinstance(event, dict):
                self.events.append(event)
            else:
                self.other.append(line)

    def ready(self) -> bool:
        return any("ready" in e for e in self.events)

    def peers(self) -> int:
        return next((e["peers"] for e in reversed(self.events) if "peers" in e), 0)

    def got(self, key: str, since: int = 0) -> list[int]:
        """The seqs of ``key``'s puts that arrived, in order, from event ``since`` on."""
        return [e["seq"] for e in self.events[since:] if e.get("got") == key]

    def keys(self) -> set[str]:
        return {e["got"] for e in self.events if "got" in e}

    def sent(self, since: int = 0) -> list[int]:
        return [e["sent"] for e in self.events[since:] if "sent" in e]

    def stop(self) -> int:
        """Close its stdin and wait for it to close its session and exit; its exit status."""
        self.proc.stdin.close()
        code = self.proc.wait(STOP_S)
        self._reader.join(STOP_S)
        return code

    def __repr__(self) -> str:
        got = Counter(e["got"] for e in self.events if "got" in e)
        return (f"<peer {self.name}: exit {self.proc.poll()}, ready {self.ready()}, peers {self.peers()}, "
                f"sent {max(self.sent(), default=0)}, got {dict(got)}, other output {''.join(self.other)[-2000:]!r}>")


if __name__ == "__main__":
    _main(sys.argv[1:])
