"""Which process sent a status or a report: each worker process signs what it tells the coordinator.

Every process of a run holds the run's password, and so may an insider (a process given the
deployment secret): Zenoh's authentication tells the run's processes from strangers, not one of
them from another, and nothing a message says of itself (its node, the ``pid`` in a status, a
``source_info``) is more than a claim. So the coordinator gives each worker process it starts a
key of its own (KEY_BYTES random bytes), never put on the key space: through a pipe the worker
inherits (its number in KEY_FD_ENV; the worker reads it and closes it before any flow code runs,
so the key is in no process's environment, which /proc/PID/environ keeps for the process's life); a worker daemon makes the key of each process it starts, passes it on the same way,
and answers it in its reply to the spawn request (remote.py: never in a query, which every
queryable on its key receives, an insider's too); in the private spec of a dora run. The worker puts every status and report with a MAC of its key
expression and payload as the Zenoh attachment (:func:`sign`); the coordinator takes a message
on ``status/node/<node>`` or ``status/report/<node>`` only if a key it gave a process of that
node verifies it (:class:`Senders`), and then knows which process sent it. What it proves: the
message was made by a holder of that process's key, i.e. that process (or code it runs, or a
process of the same user on its host, which can read its memory anyway). What it does not: that
the process's flow is honest, nor that a message is not a replay of one that process sent
(the coordinator refuses a second record of a tick and a second event of a seq for that).
An insider that answers as a worker daemon (before it is up, or once it is gone) gives the
coordinator keys of its own, as it would run those processes.
"""

from __future__ import annotations

import hashlib
import hmac
import os
import secrets
import threading

#: a process's key: random bytes, as hex text in a pipe whose descriptor's number is in KEY_FD_ENV
KEY_BYTES = 32
MAC_BYTES = 16
KEY_FD_ENV = "RETRIEVER_PROCESS_KEY_FD"


def new_key() -> bytes:
    return secrets.token_bytes(KEY_BYTES)


def key_text(key: bytes) -> str:
    return key.hex()


def key_of_text(text: object) -> bytes | None:
    """A key from its hex text; None for anything else (a spawn request is the network's)."""
    if type(text) is not str or len(text) != 2 * KEY_BYTES:
        return None
    try:
        key = bytes.fromhex(text)
    except ValueError:
        return None
    return key if len(key) == KEY_BYTES else None  # fromhex skips whitespace: fewer bytes


def key_pipe(key: bytes) -> int:
    """The read end of a pipe holding ``key`` (as hex text), for a child to inherit (``pass_fds``,
    its number in KEY_FD_ENV); the parent closes it once the child started."""
    read, write = os.pipe()
    try:
        os.write(write, key_text(key).encode())  # 64 bytes: within any pipe's buffer
    finally:
        os.close(write)
    return read


def take_key() -> bytes | None:
    """This worker process's key, read from the pipe it inherited, which it closes (its flows'
    subprocesses inherit neither); None when it was started without one."""
    fd_text = os.environ.pop(KEY_FD_ENV, None)
    if fd_text is None or not (fd_text.isascii() and fd_text.isdigit() and len(fd_text) <= 9):
        return None
    fd = int(fd_text)
    try:
        text = os.read(fd, 2 * KEY_BYTES + 1)
    except OSError:
        return None
    finally:
        try:
            os.close(fd)
        except OSError:
            pass
    return key_of_text(text.decode("ascii", errors="replace"))


def sign(key: bytes, key_expr: str, payload: bytes) -> bytes:
    """The MAC of a message put on ``key_expr`` (which it covers: a report cannot move to another
    node's key): HMAC-SHA256, cut to MAC_BYTES (SHA-256 runs on the CPU's SHA instructions where
    it has them: a report may carry big frames inline, and each is hashed on both sides)."""
    mac = hmac.new(key, digestmod=hashlib.sha256)
    mac.update(key_expr.encode())
    mac.update(b"\0")
    mac.update(payload)
    return mac.digest()[:MAC_BYTES]


class Senders:
    """The coordinator's side: per node, the keys of the processes it started for it, and what
    it refused (safe to call from Zenoh's threads)."""

    #: how many refusals are kept to be told (each says why); the count goes on
    KEPT = 3

    def __init__(self) -> None:
        self._keys: dict[str, list[tuple[bytes, object]]] = {}
        self._lock = threading.Lock()
        self.refused = 0
        self.reasons: list[str] = []

    def add(self, node: str, key: bytes | None, process: object) -> None:
        """``process`` (of ``node``) signs with ``key``; None: a process started without one,
        whose messages are never taken."""
        if key is not None:
            self._keys.setdefault(node, []).append((key, process))

    def sender(self, node: str, key_expr: str, payload: bytes, attachment: bytes | None) -> object | None:
        """The process of ``node`` whose key signed this message, or None (counted as refused)."""
        if attachment is not None and len(attachment) == MAC_BYTES:
            for key, process in reversed(self._keys.get(node, ())):  # the newest process first
                if hmac.compare_digest(sign(key, key_expr, payload), attachment):
                    return process
        self.refuse(f"a message on {key_expr} that no process of {node!r:.60} signed")
        return None

    def refuse(self, why: str) -> None:
        with self._lock:
            self.refused += 1
            if len(self.reasons) < self.KEPT:
                self.reasons.append(why)
