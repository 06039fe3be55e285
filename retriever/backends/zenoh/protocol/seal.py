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
"""

from __future__ import annotations

import hmac
import secrets
import threading
from typing import Any

from ....errors import WireError
from ..origin import MAC_BYTES, sign
from .schema import Record
from .to_worker import RUN_CONTROL

COUNTER_BYTES = 8
NONCE_BYTES = 16
#: how far behind the newest counter a process took a control message may be and still be taken
REPLAY_WINDOW = 1024
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


def _bytes(attachment: Any) -> bytes:
    """A Zenoh attachment (ZBytes, bytes or None) as bytes."""
    if attachment is None:
        return b""
    if isinstance(attachment, (bytes, bytearray, memoryview)):
        return bytes(attachment)
    return attachment.to_bytes()
