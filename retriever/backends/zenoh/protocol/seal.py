"""Signed control: a worker takes a control message only if the run's coordinator made it for it.

Every process of a run holds the run's password, and so may an insider: anyone of them can put
on ``ctl/run``, and a ``lost`` or a ``stop`` there ends a process or a run (issue 40). The
statuses and reports a worker sends are signed with its process's key (origin.py); control goes
the other way with the same keys. The coordinator holds the key of every process it started
(it gave it, or the process's daemon answered it to the coordinator alone: remote.py), and no
one else does; so it *seals* each control message with one MAC per live process, and each
process opens it with its own key. No key travels anywhere new: a process's key is its
control key, and a process started after a message was sealed cannot open it. A process whose
exit is confirmed is dropped (coordinator/processes.py): however often a run restarts its flows,
a control message carries a MAC for the processes that may still read it, and no more.

    put on ctl/run     attachment = counter (COUNTER_BYTES, big-endian) + MAC(k, key_expr, counter + payload) for each k
    reply (ctl/start,  query attachment = a nonce (NONCE_BYTES, fresh per question)
     status/finished)  reply attachment = MAC(k, key_expr, nonce + payload) for each k

A MAC is origin.sign's (HMAC-SHA256 of the key expression and the signed bytes, cut to
MAC_BYTES). The counter makes a replay refusable: a process takes each counter once, and none
older than REPLAY_WINDOW behind the newest it took (Zenoh keeps one publisher's puts on one key
in order; the window forgives a reordering all the same). A reply covers the nonce of the
question it answers: an old answer, replayed, answers no new question.

A worker daemon's events (``exit``, ``output`` on workers/<name>/events) go the same way with one
key, the run's (daemon/runs.py seals them with a ControlSigner holding it; the coordinator's RemoteHost
opens them with a ControlOpener): forged, altered, another run's or replayed, they are refused. What it does not prove:
that a message arrived at all (an insider with the run's password can still flood the links it
shares, as it could before).

A coordinator's requests to a worker daemon (ctl/<name>: prepare, spawn, signal, usage, end, which
start processes, link them to a run, or tell of it) are sealed too, with one key derived from the
deployment secret itself (access.daemon_control_key), never from a password: the namespace's
passwords sit in every daemon's dictionary and, routed, in every flow, and a request with a live
run's id would have the daemon derive that run's passwords for a process of the sender's choosing.

    query ctl/<name>   attachment = nonce (NONCE_BYTES) + time (REQUEST_TIME_BYTES, ns since the
                       epoch, big-endian) + MAC(key, key_expr, nonce + time + payload)

The daemon (daemon/core.py) takes a sealed op only with a valid MAC, each nonce once: it keeps the
nonces it took (RequestOpener), at most REQUEST_NONCES; a request older than the newest it forgot
is refused, and so is one whose time lies more than REQUEST_MAX_AGE_S from its clock (a restarted
daemon remembers no nonce). The read-only ``info`` stays unsealed: it tells nothing secret.
"""

from __future__ import annotations

import hmac
import secrets
import threading
import time
from collections import OrderedDict
from collections.abc import Callable
from typing import Any

from ....errors import WireError
from ..origin import MAC_BYTES, sign
from .schema import Record
from .to_worker import RUN_CONTROL

COUNTER_BYTES = 8
NONCE_BYTES = 16
#: how far behind the newest counter a process took a control message may be and still be taken
REPLAY_WINDOW = 1024
#: a sealed request's time: ns since the Unix epoch, big-endian
REQUEST_TIME_BYTES = 8
#: how far from the daemon's clock a sealed request's time may lie (a deployment's clocks agree to
#: within milliseconds: deploy.CLOCK_REFUSE_NS)
REQUEST_MAX_AGE_S = 60.0
#: how many nonces of sealed requests a daemon remembers (a deployment asks each daemon for its
#: usage once a second: over an hour's)
REQUEST_NONCES = 4096
#: a run's live processes, at most, that one control message is sealed for: its attachment stays small
MAX_SEALED = 4096


class ControlSigner:
    """The coordinator's side: the keys of the run's live processes, and the counter of its puts
    (safe to call from Zenoh's threads: a queryable answers on them)."""

    def __init__(self) -> None:
        self._keys: dict[int, tuple[object, bytes]] = {}
        self._counter = 0
        self._lock = threading.Lock()

    def add(self, process: object, key: bytes | None) -> None:
        """``process`` (just started) opens control with ``key``; None: a process without one,
        which takes no control message."""
        if key is not None:
            with self._lock:
                self._keys[id(process)] = (process, key)

    def drop(self, process: object) -> None:
        """``process`` ended: no more control is sealed for it."""
        with self._lock:
            self._keys.pop(id(process), None)

    def holders(self) -> list[object]:
        """The processes control is sealed for (each added, and not dropped)."""
        with self._lock:
            return [process for process, _ in self._keys.values()]

    def seal(self, key_expr: str, payload: bytes) -> bytes:
        """The attachment of the next control message put on ``key_expr``."""
        with self._lock:
            self._counter += 1
            head = self._counter.to_bytes(COUNTER_BYTES, "big")
            keys = [key for _, key in self._keys.values()]
        signed = head + payload
        return head + b"".join(sign(key, key_expr, signed) for key in keys)

    def seal_reply(self, key_expr: str, payload: bytes, nonce: bytes | None) -> bytes | None:
        """The attachment of a reply to a question that came with ``nonce``; None for a
        question without one (its reply goes unsealed, and no process takes it)."""
        if nonce is None or len(nonce) != NONCE_BYTES:
            return None
        with self._lock:
            keys = [key for _, key in self._keys.values()]
        signed = bytes(nonce) + payload
        return b"".join(sign(key, key_expr, signed) for key in keys)


def new_nonce() -> bytes:
    """A question's nonce (its Zenoh attachment): the reply that covers it answers this question."""
    return secrets.token_bytes(NONCE_BYTES)


class ControlOpener:
    """A worker process's side: it takes a control message only if it opens with its own key,
    and a put only once (safe to call from Zenoh's threads)."""

    def __init__(self, key: bytes | None):
        self._key = key
        self._newest = 0  # the newest counter taken; counter 0 is never used (taken, as it were)
        self._seen = 1  # bit i: counter newest - i was taken
        self._lock = threading.Lock()

    def open(self, key_expr: str, payload: bytes, attachment: Any) -> None:
        """Take a put on ``key_expr`` (ctl/run), or raise WireError saying why not: unsealed,
        not sealed for this process, or a replay."""
        seal = _bytes(attachment)
        if len(seal) < COUNTER_BYTES + MAC_BYTES or (len(seal) - COUNTER_BYTES) % MAC_BYTES:
            raise WireError(f"a control message on {key_expr} without the coordinator's seal")
        head = seal[:COUNTER_BYTES]
        self._check(key_expr, bytes(head) + bytes(payload), seal[COUNTER_BYTES:])
        self._take(int.from_bytes(head, "big"), key_expr)

    def control(self, key_expr: str, payload: bytes, attachment: Any) -> Record:
        """A put on ctl/run, opened (:meth:`open`) and decoded: one of RUN_CONTROL's records."""
        self.open(key_expr, payload, attachment)
        return RUN_CONTROL.decode(payload)

    def reply(self, record: type[Record], key_expr: str, payload: bytes, attachment: Any, nonce: bytes) -> Record:
        """A reply to this process's question (``nonce``), opened and decoded as ``record``
        (a Start on ctl/start, a Finished on status/finished)."""
        self.open_reply(key_expr, payload, attachment, nonce)
        return record.decode(payload)

    def open_reply(self, key_expr: str, payload: bytes, attachment: Any, nonce: bytes) -> None:
        """Take a reply on ``key_expr`` to this process's question of ``nonce``, or raise WireError."""
        seal = _bytes(attachment)
        if not seal or len(seal) % MAC_BYTES:
            raise WireError(f"a reply on {key_expr} without the coordinator's seal")
        self._check(key_expr, bytes(nonce) + bytes(payload), seal)

    def _check(self, key_expr: str, signed: bytes, macs: bytes) -> None:
        if self._key is None:
            raise WireError(f"a control message on {key_expr}: this process has no key to open it with")
        if len(macs) > MAX_SEALED * MAC_BYTES:
            raise WireError(f"a control message on {key_expr} sealed for more processes than a run has")
        mine = sign(self._key, key_expr, signed)
        # every MAC compared (no early exit): how long it takes says nothing of which matched
        found = 0
        for start in range(0, len(macs), MAC_BYTES):
            found |= hmac.compare_digest(mine, macs[start:start + MAC_BYTES])
        if not found:
            raise WireError(f"a control message on {key_expr} that the run's coordinator did not seal for this "
                            "process (forged, altered, or another run's)")

    def _take(self, counter: int, key_expr: str) -> None:
        with self._lock:
            if counter > self._newest:
                shift = counter - self._newest
                self._seen = ((self._seen << shift) | 1) & ((1 << REPLAY_WINDOW) - 1) if shift < REPLAY_WINDOW else 1
                self._newest = counter
                return
            behind = self._newest - counter
            if behind >= REPLAY_WINDOW or self._seen >> behind & 1:
                raise WireError(f"a control message on {key_expr} taken before (counter {counter}): a replay")
            self._seen |= 1 << behind


class RequestSealer:
    """The coordinator's side of ctl/<name>: seals each request it sends a daemon (safe to call
    from any thread). ``clock``: ns since the epoch (time.time_ns; a test's own)."""

    def __init__(self, key: bytes, clock: Callable[[], int] = time.time_ns):
        self._key, self._clock = key, clock

    def seal(self, key_expr: str, payload: bytes) -> bytes:
        """The attachment of a request put on ``key_expr`` (the daemon's ctl/<name>)."""
        head = new_nonce() + self._clock().to_bytes(REQUEST_TIME_BYTES, "big")
        return head + sign(self._key, key_expr, head + payload)


class RequestOpener:
    """A daemon's side of ctl/<name>: takes a sealed request once, or says why not (safe to call
    from Zenoh's threads)."""

    def __init__(self, key: bytes, clock: Callable[[], int] = time.time_ns):
        self._key, self._clock = key, clock
        self._taken: OrderedDict[bytes, int] = OrderedDict()  # nonce -> its request's time, oldest first
        self._floor = -1  # the newest time of a nonce forgotten: a request no newer is refused
        self._lock = threading.Lock()

    def open(self, key_expr: str, payload: bytes, attachment: Any) -> None:
        """Take a request on ``key_expr`` (this daemon's ctl/<name>), or raise WireError."""
        seal = _bytes(attachment)
        head_bytes = NONCE_BYTES + REQUEST_TIME_BYTES
        if len(seal) != head_bytes + MAC_BYTES:
            raise WireError(f"a request on {key_expr} without the coordinator's seal (a deployment's requests "
                            "are sealed with a key derived from its secret; the namespace's password is not enough)")
        head, mac = seal[:head_bytes], seal[head_bytes:]
        if not hmac.compare_digest(sign(self._key, key_expr, head + bytes(payload)), mac):
            raise WireError(f"a request on {key_expr} that no holder of the deployment secret sealed "
                            "(forged, altered, or another namespace's)")
        nonce, stamp = head[:NONCE_BYTES], int.from_bytes(head[NONCE_BYTES:], "big")
        if abs(self._clock() - stamp) > REQUEST_MAX_AGE_S * 1e9:
            raise WireError(f"a request on {key_expr} sealed {(self._clock() - stamp) / 1e9:.1f} s from this "
                            f"worker's clock, past {REQUEST_MAX_AGE_S:g} s: a replay, or clocks that disagree")
        with self._lock:
            if nonce in self._taken or stamp <= self._floor:
                raise WireError(f"a request on {key_expr} taken before: a replay")
            self._taken[nonce] = stamp
            while len(self._taken) > REQUEST_NONCES:
                _, forgotten = self._taken.popitem(last=False)
                self._floor = max(self._floor, forgotten)


def _bytes(attachment: Any) -> bytes:
    """A Zenoh attachment (ZBytes, bytes or None) as bytes."""
    if attachment is None:
        return b""
    if isinstance(attachment, (bytes, bytearray, memoryview)):
        return bytes(attachment)
    return attachment.to_bytes()
