"""The consumer's end of a link: connects to its producer's socket, checks the handshake and
the ring's memfd, and a thread of its own receives the producer's messages in order: an inline
one as it came, a handle's slot copied out of the ring (its bounds and generation checked) and
acked at once, a new ring (checked as the first) in place of the old. Each message goes to
``on_message(kind, bytes)`` on that thread; the end of the connection, with why, to
``on_closed`` (once; not after :meth:`LinkClient.close`).

Anything the producer sends that is not what frames.py says (a frame too short or too long, of
an unknown type, a handle out of the ring or of a stale generation, an fd with any frame but a
ring's, which it closes) ends the connection with a LinkError naming it and the producer:
nothing out of bounds is ever read.
"""

from __future__ import annotations

import os
import socket
import struct
import threading
from collections.abc import Callable
from pathlib import Path

from ....errors import LinkError
from . import frames
from .ring import RingReader
from .server import HANDSHAKE_TIMEOUT, MAX_INLINE_BELOW

_CRED = struct.Struct("3i")


def _close(fds: list[int]) -> None:
    for fd in fds:
        os.close(fd)


class LinkClient:
    """``consumer``'s connection to ``producer`` of ``run`` at ``path``; raises LinkError when the
    producer cannot be reached or its handshake or ring is refused. :meth:`close` ends it."""

    def __init__(self, path: str | os.PathLike, run: str, producer: str, consumer: str,
                 on_message: Callable[[int, bytes], None], on_closed: Callable[[LinkError], None],
                 *, timeout: float = HANDSHAKE_TIMEOUT):
        self.on_message, self.on_closed = on_message, on_closed
        self.peer = f"producer {producer!r} ({Path(path).name})"
        self._closing = False
        sock = socket.socket(socket.AF_UNIX, socket.SOCK_SEQPACKET | socket.SOCK_CLOEXEC)
        try:
            sock.settimeout(timeout)
            try:
                sock.connect(os.fspath(path))
            except OSError as e:
                raise LinkError(f"{self.peer}: cannot connect to {path} ({e.strerror or e})") from None
            pid, uid, _ = _CRED.unpack(sock.getsockopt(socket.SOL_SOCKET, socket.SO_PEERCRED, _CRED.size))
            self.peer = f"producer {producer!r} (pid {pid}, {Path(path).name})"
            if uid != os.getuid():
                raise LinkError(f"{self.peer} is of user {uid}, not this process's {os.getuid()}")
            try:
                sock.sendall(frames.hello(run, producer, consumer))
            except OSError as e:  # (a timeout too)
                raise LinkError(f"{self.peer}: the connection failed before its welcome ({e.strerror or e})") from None
            self._ring, self._frame_bytes = self._welcome(sock, run, producer)
            sock.settimeout(None)
        except BaseException:
            sock.close()
            raise
        self._sock = sock
        self._thread = threading.Thread(target=self._receive, name=f"link-{producer}-{consumer}", daemon=True)
        self._thread.start()

    def _welcome(self, sock: socket.socket, run: str, producer: str) -> tuple[RingReader, int]:
        try:
            data, fds, flags, _ = socket.recv_fds(sock, frames.MAX_HANDSHAKE + 1, 2)
        except TimeoutError:
            raise LinkError(f"{self.peer}: no welcome within the handshake's timeout") from None
        except OSError as e:  # reset: it closed the connection with the hello unread
            raise LinkError(f"{self.peer}: the connection failed before its welcome ({e.strerror or e})") from None
        try:
            if flags & socket.MSG_TRUNC:
                raise LinkError(f"{self.peer}: its welcome is longer than {frames.MAX_HANDSHAKE} bytes")
            their_run, their_producer, slots, capacity, stride, inline_below = frames.read_welcome(data, self.peer)
            if (their_run, their_producer) != (run, producer):
                raise LinkError(f"{self.peer}: it is producer {their_producer!r} of run {their_run!r}, not "
                                f"{producer!r} of run {run!r}")
            if not 0 <= inline_below <= MAX_INLINE_BELOW:
                raise LinkError(f"{self.peer}: its inline_below={inline_below} is out of 0..{MAX_INLINE_BELOW}")
            if len(fds) != 1 or flags & socket.MSG_CTRUNC:
                raise LinkError(f"{self.peer}: its welcome came with {len(fds)} fds, not its ring's one")
        except BaseException:
            for fd in fds:
                os.close(fd)
            raise
        ring = RingReader(fds[0], slots, capacity, stride, self.peer)  # owns the fd now
        return ring, max(inline_below + 1, frames.HANDLE_FRAME.size, frames.RING_FRAME.size)

    def _receive(self) -> None:
        sock, ring, peer, size = self._sock, self._ring, self.peer, self._frame_bytes
        on_message, unpack, ack = self.on_message, frames.HANDLE_FRAME.unpack, frames.ack
        why, reset = None, False
        try:
            while True:
                try:
                    data, fds, flags, _ = socket.recv_fds(sock, size + 1, 1)
                except ConnectionResetError:  # its process ended with our acks unread: said once,
                    if reset:  # before what it sent until then, which is still to read
                        raise
                    reset = True
                    continue
                if not data:
                    why = LinkError(f"{peer} closed the connection")
                    return
                if flags & socket.MSG_TRUNC or len(data) > size:
                    _close(fds)
                    raise LinkError(f"{peer}: sent a frame longer than its welcome allows ({size} bytes)")
                try:
                    kind = frames.frame_type(data, peer)
                    if (kind == frames.RING) != (len(fds) == 1) or flags & socket.MSG_CTRUNC:
                        raise LinkError(f"{peer}: sent {len(fds)} fds with a frame of type {kind} (a ring frame takes "
                                        "one, the others none)")
                except LinkError:
                    _close(fds)
                    raise
                if kind == frames.INLINE:
                    on_message(data[1], data[2:])
                elif kind == frames.HANDLE:
                    _, kind, slot, generation, length = unpack(data)
                    message = ring.copy(slot, generation, length)
                    try:
                        sock.sendall(ack(slot, generation))
                    except (BrokenPipeError, ConnectionResetError):  # it closed: the copy is ours, no ack is due
                        pass
                    on_message(kind, message)
                else:
                    _, slots, capacity, stride = frames.RING_FRAME.unpack(data)
                    ring.close()
                    ring = self._ring = RingReader(fds[0], slots, capacity, stride, peer)  # owns the fd
        except LinkError as e:
            why = e
        except ConnectionResetError:  # its process ended with our acks unread
            why = LinkError(f"{peer} closed the connection (reset)")
        except OSError as e:
            why = LinkError(f"{peer}: the connection failed ({e.strerror or e})")
        except Exception as e:  # on_message's own error ends the stream: the next message would be out of order
            why = LinkError(f"{peer}: on_message raised {type(e).__name__}: {e}")
        finally:
            sock.close()
            self._ring.close()
            if not self._closing:
                self.on_closed(why)

    def close(self) -> None:
        """End the connection (idempotent); on_closed is not called for it."""
        if self._closing:
            return
        self._closing = True
        try:
            self._sock.shutdown(socket.SHUT_RDWR)
        except OSError:
            pass
        if threading.current_thread() is not self._thread:
            self._thread.join()

    def __enter__(self) -> LinkClient:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
