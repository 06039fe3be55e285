"""The producer's end of a link: a SOCK_SEQPACKET socket in the run's private folder that its
same-host consumers connect to, and the ordered stream of messages sent to each of them.

A message below ``inline_below`` bytes goes whole in one frame (``sendmsg`` of its parts: no
join); a bigger one goes into a free slot of the ring (its parts written straight in) and its
handle to every consumer. A slot is written again only after every consumer its handle went to
acked it (or was dropped). The ring is one page until a message needs it (then ``slots`` slots
of ``capacity`` bytes, or of that message); a message bigger than the slots makes a bigger ring (its fd sent
to each consumer in the stream's order) once no slot of the old one is held. No free slot:
:meth:`LinkServer.send` waits for acks, up to ``send_timeout``, then raises (a consumer that
stopped reading backs its producer up, as Zenoh's BLOCK congestion control does: never a lost
message, never a slot rewritten under a reader).

A consumer that sends anything but a well-formed ack for a slot it holds, or that is gone
(EOF, EPIPE), is dropped: its connection closed, its slots released, the error (naming it) on
:attr:`LinkServer.dropped` and given to ``on_dropped`` (one call at a time, whichever thread saw
it); the other consumers go on. A send that failed after its message (or a new ring) reached
some consumers and not others leaves the stream out of order: the link closes before the
LinkError is raised, and every later send raises too; one that reached none (no free slot in
time, the first consumer's socket full) may be tried again.
"""

from __future__ import annotations

import array
import collections
import errno
import os
import select
import socket
import stat
import struct
import threading
import time
from collections.abc import Callable
from pathlib import Path

from ....errors import LinkError
from . import frames
from .ring import MAX_RING_BYTES, Ring, check_geometry, stride_for

#: messages below this many bytes go inline (a frame through the socket), the others through the
#: ring; at most MAX_INLINE_BELOW (a SEQPACKET record must fit the socket's send buffer)
INLINE_BELOW = 64 * 1024
MAX_INLINE_BELOW = 128 * 1024
#: how long a send may wait for a consumer (a free slot, room in its socket), and a handshake
SEND_TIMEOUT = 10.0
HANDSHAKE_TIMEOUT = 5.0
#: at most this many handshakes under way at once (a thread and an fd each, for up to
#: HANDSHAKE_TIMEOUT); an accept that failed (out of fds) is tried again after ACCEPT_RETRY_S
MAX_HANDSHAKES = 64
ACCEPT_RETRY_S = 0.05
#: the dropped consumers' errors kept on LinkServer.dropped
KEPT_DROPS = 64
#: a socket's path must fit sockaddr_un's sun_path (108 bytes with its NUL)
MAX_PATH = 107
#: the most buffers one sendmsg takes (Linux's UIO_MAXIOV)
IOV_MAX = os.sysconf("SC_IOV_MAX")
_CRED = struct.Struct("3i")


class _Consumer:
    __slots__ = ("sock", "name", "peer")

    def __init__(self, sock: socket.socket, name: str, peer: str):
        self.sock, self.name, self.peer = sock, name, peer


class LinkServer:
    """Listens at ``path`` (a new file in a folder only this user may enter) for the consumers of
    ``producer``'s messages in ``run``, and sends each message to every connected consumer, in
    order. :meth:`send` is called from one thread; consumers are admitted by a thread of their
    own. :meth:`close` unlinks the socket and closes every connection and the ring."""

    def __init__(self, path: str | os.PathLike, run: str, producer: str, *, slots: int = 8,
                 capacity: int = 4 << 20, inline_below: int = INLINE_BELOW, send_timeout: float = SEND_TIMEOUT,
                 handshake_timeout: float = HANDSHAKE_TIMEOUT,
                 on_dropped: Callable[[LinkError], None] | None = None):
        self.path, self.run, self.producer = Path(path), run, producer
        _check_folder(self.path)
        if not 0 <= inline_below <= MAX_INLINE_BELOW:
            raise LinkError(f"inline_below={inline_below} is out of 0..{MAX_INLINE_BELOW}")
        self.inline_below, self.send_timeout, self.handshake_timeout = inline_below, send_timeout, handshake_timeout
        self.on_dropped = on_dropped
        self.dropped: collections.deque[LinkError] = collections.deque(maxlen=KEPT_DROPS)
        self._partial = False  # whether the message being sent reached some consumer (send's)
        self._noting = threading.Lock()  # on_dropped is called from the sender's and the admitting threads
        check_geometry(slots, capacity)
        # the ring: a page until a message needs it, then ``slots`` slots of ``capacity`` bytes (or
        # the message's): a producer of small messages maps no more, one of big ones what they take
        self._slots, self._capacity = slots, capacity
        self._ring = Ring(1, 1, f"retriever-link-{producer}"[:200])
        self._held: list[set[_Consumer]] = [set()]  # who has not acked each slot
        self._generations = [0]
        self._generation = 0
        self._next = 0
        self._consumers: tuple[_Consumer, ...] = ()  # replaced, never changed in place (send reads it unlocked)
        self._changed = threading.Condition()
        self._closed = False
        self._handshakes: set[socket.socket] = set()  # connections whose handshake is under way
        self._listener = socket.socket(socket.AF_UNIX, socket.SOCK_SEQPACKET | socket.SOCK_CLOEXEC)
        bound = False
        try:
            _clear_stale(self.path)
            try:
                self._listener.bind(str(self.path))
            except OSError as e:
                if e.errno != errno.EADDRINUSE:
                    raise
                raise LinkError(f"a link socket's path was taken meanwhile: {self.path}") from None
            bound = True
            os.chmod(self.path, 0o600)
            self._listener.listen(16)
        except BaseException:
            self._listener.close()
            self._ring.close()
            if bound:  # (ours: no one else's file is removed)
                try:
                    os.unlink(self.path)
                except FileNotFoundError:
                    pass
            raise
        self._acceptor = threading.Thread(target=self._accept, name=f"link-{producer}", daemon=True)
        self._acceptor.start()

    # -----------------------------------------------------------------------------------------
    # Sending
    # -----------------------------------------------------------------------------------------
    @property
    def consumers(self) -> list[str]:
        """The names of the consumers connected now."""
        return [consumer.name for consumer in self._consumers]

    def wait_for(self, count: int, timeout: float) -> bool:
        """Whether ``count`` consumers are connected within ``timeout`` seconds."""
        with self._changed:
            return self._changed.wait_for(lambda: len(self._consumers) >= count, timeout)

    def send(self, parts: list, kind: int = 0) -> None:
        """Send the message made of ``parts`` (bytes-like, as the wire encoder's ``data_parts``)
        to every connected consumer, after the messages sent before it; ``kind`` (0..255) goes
        with it. Raises LinkError when a consumer held up the send past ``send_timeout`` (the
        message may then have reached some consumers and not others: the link is then closed), or
        the ring cannot grow to the message, or the link is closed."""
        consumers = self._consumers
        if self._closed:
            raise LinkError(f"{self.producer}: its link is closed ({self.path})")
        if not consumers:
            return
        if not 0 <= kind < 256:
            raise LinkError(f"{self.producer}: a link message's kind is a byte (0..255), not {kind!r}")
        self._partial = False
        try:
            self._send(consumers, parts, kind)
        except LinkError:
            if self._partial:  # some consumers have it (or the new ring) and others not: out of order
                self.close()
            raise
        except ValueError:  # (close() on another thread meanwhile: the ring or a socket closed under us)
            if not self._closed:
                raise
            raise LinkError(f"{self.producer}: its link closed during a send ({self.path})") from None

    def _send(self, consumers: tuple[_Consumer, ...], parts, kind: int) -> None:
        length = sum(memoryview(part).nbytes for part in parts)
        if length < self.inline_below:
            # one sendmsg of the parts (no join), unless they are more than it takes (EMSGSIZE)
            frame = [frames.INLINE_HEADS[kind], *parts] if len(parts) < IOV_MAX else \
                [frames.INLINE_HEADS[kind], b"".join(parts)]
            for consumer in consumers:
                self._put(consumer, frame)
                self._partial = True
            return
        deadline = time.monotonic() + self.send_timeout
        if length > self._ring.capacity or self._ring.slots != self._slots:
            self._grow(length, deadline)
        slot = self._free_slot(deadline)
        self._generation += 1
        self._generations[slot] = generation = self._generation
        self._ring.write(slot, parts, length, generation)
        frame = [frames.handle(kind, slot, generation, length)]
        held = self._held[slot]
        for consumer in self._consumers:
            if self._put(consumer, frame):
                held.add(consumer)
            self._partial = True

    def _grow(self, length: int, deadline: float) -> None:
        """Replace the ring by one whose slots hold ``length`` bytes (twice the old at least), once
        no consumer holds a slot of the old one; each consumer gets the new one's fd in a RING
        frame, in the stream's order (a consumer joining meanwhile gets it in its welcome)."""
        old, slots = self._ring, self._slots
        capacity = max(length, 2 * old.capacity if old.slots == slots else self._capacity)  # (else the first page's)
        if slots * stride_for(capacity) > MAX_RING_BYTES:
            raise LinkError(f"{self.producer}: a message of {length} bytes is bigger than its link's ring can grow "
                            f"({slots} slots, {MAX_RING_BYTES} bytes in all)")
        for slot in range(old.slots):
            self._wait_free(slot, deadline)
        new = Ring(slots, capacity, f"retriever-link-{self.producer}"[:200])
        if new.slots != len(self._held):  # (every slot free: none held)
            self._held, self._generations, self._next = [set() for _ in range(slots)], [0] * slots, 0
        rights = [(socket.SOL_SOCKET, socket.SCM_RIGHTS, array.array("i", [new.fd]))]
        frame = [frames.ring(new.slots, new.capacity, new.stride)]
        with self._changed:
            self._ring = new
            consumers = self._consumers
        self._partial = True  # (a consumer that took no RING frame would read the next handle in the old ring)
        try:
            for consumer in consumers:
                self._put(consumer, frame, rights)
        finally:  # (a consumer that took no RING frame in time: send raises, the old ring closed all the same)
            old.close()
            self._next = 0

    def _put(self, consumer: _Consumer, frame: list, ancillary: list = ()) -> bool:
        """Send one frame to ``consumer`` (waiting for room in its socket up to ``send_timeout``);
        False if it is gone (then dropped)."""
        deadline = None
        while True:
            try:
                consumer.sock.sendmsg(frame, ancillary, socket.MSG_NOSIGNAL)
                return True
            except OSError as e:
                # no room in its socket (EAGAIN), or the kernel short of buffers for now (ENOBUFS,
                # ENOMEM: no fault of the consumer's): wait, up to send_timeout
                if not isinstance(e, BlockingIOError) and e.errno not in (errno.ENOBUFS, errno.ENOMEM):
                    if self._closed:
                        raise ValueError("closed") from None  # (send's: close() ran meanwhile)
                    self._drop(consumer, f"is gone ({e.strerror})")
                    return False
                deadline = deadline or time.monotonic() + self.send_timeout
                left = deadline - time.monotonic()
                if left <= 0:
                    raise LinkError(f"{self.producer}: {consumer.peer} took no message for {self.send_timeout:g}s: "
                                    "a consumer that stopped reading holds its producer up") from None
                if isinstance(e, BlockingIOError):
                    poll = select.poll()
                    poll.register(consumer.sock, select.POLLOUT)
                    poll.poll(left * 1000)
                else:  # (POLLOUT says nothing of the kernel's buffers: look again soon)
                    time.sleep(min(left, ACCEPT_RETRY_S / 10))

    def _free_slot(self, deadline: float) -> int:
        """The next slot in turn once no consumer holds it."""
        slot = self._next
        self._wait_free(slot, deadline)
        self._next = (slot + 1) % len(self._held)
        return slot

    def _wait_free(self, slot: int, deadline: float) -> None:
        """Until no consumer holds ``slot``: acks read meanwhile, until ``deadline``."""
        while self._held[slot]:
            self._read_acks(self._held[slot])
            if not self._held[slot]:
                break
            left = deadline - time.monotonic()
            if left <= 0:
                names = ", ".join(sorted(consumer.peer for consumer in self._held[slot]))
                raise LinkError(f"{self.producer}: no free slot in its link's ring for {self.send_timeout:g}s: "
                                f"{names} did not ack slot {slot}; a consumer that stopped reading holds its "
                                "producer up")
            poll = select.poll()
            for consumer in self._held[slot]:
                poll.register(consumer.sock, select.POLLIN)
            poll.poll(left * 1000)

    def _read_acks(self, consumers: set[_Consumer]) -> None:
        """Take every ack waiting on these consumers' connections (without waiting)."""
        for consumer in list(consumers):
            try:
                while True:
                    data = consumer.sock.recv(frames.ACK_FRAME.size + 1)
                    if not data:
                        self._drop(consumer, "is gone (closed its connection)")
                        break
                    slot, generation = frames.read_ack(data, consumer.peer)
                    if not 0 <= slot < len(self._held) or consumer not in self._held[slot] \
                            or self._generations[slot] != generation:
                        raise LinkError(f"{consumer.peer}: acked slot {slot} generation {generation}, which it "
                                        "does not hold (never sent to it, or acked before)")
                    self._held[slot].discard(consumer)
            except BlockingIOError:
                continue
            except LinkError as e:
                self._drop(consumer, error=e)
            except OSError as e:
                self._drop(consumer, f"is gone ({e.strerror})")

    def _drop(self, consumer: _Consumer, why: str = "", error: LinkError | None = None) -> None:
        with self._changed:
            if consumer not in self._consumers:
                return
            self._consumers = tuple(c for c in self._consumers if c is not consumer)
        for held in self._held:
            held.discard(consumer)
        consumer.sock.close()
        self._note(error or LinkError(f"{self.producer}: {consumer.peer} {why}: dropped"))

    def _note(self, error: LinkError) -> None:
        with self._noting:
            self.dropped.append(error)
            if self.on_dropped is not None:
                self.on_dropped(error)

    # -----------------------------------------------------------------------------------------
    # Admitting consumers (the acceptor's thread)
    # -----------------------------------------------------------------------------------------
    def _accept(self) -> None:
        """Each connection's handshake on a thread of its own: one that says nothing holds up no
        other. At most MAX_HANDSHAKES under way (one more is closed at once, said); an accept
        that fails (out of fds: EMFILE) is said once and tried again until close()."""
        failing = False
        while True:
            try:
                sock, _ = self._listener.accept()
            except OSError as e:
                with self._changed:
                    if self._closed:  # close() shut the listener down
                        return
                    self._changed.wait(ACCEPT_RETRY_S)  # (the listener stays readable: no poll for it)
                if not failing:
                    failing = True
                    self._note(LinkError(f"{self.producer}: cannot accept a consumer's connection ({e.strerror}): "
                                         f"tried again every {ACCEPT_RETRY_S:g}s"))
                continue
            failing = False
            with self._changed:
                crowded = len(self._handshakes) >= MAX_HANDSHAKES
                if not crowded:
                    self._handshakes.add(sock)
            if crowded:
                sock.close()
                self._note(LinkError(f"{self.producer}: a connection closed at once: {MAX_HANDSHAKES} handshakes "
                                     "are under way (connections that say nothing?)"))
                continue
            try:
                threading.Thread(target=self._admit_or_refuse, args=(sock,), name=f"link-{self.producer}-hello",
                                 daemon=True).start()
            except RuntimeError as e:  # can't start new thread
                with self._changed:
                    self._handshakes.discard(sock)
                sock.close()
                self._note(LinkError(f"{self.producer}: a connection closed at once: {e}"))

    def _admit_or_refuse(self, sock: socket.socket) -> None:
        """(``sock`` is in _handshakes: close() shuts it down)"""
        try:
            name, peer = self._admit(sock)
            with self._changed:  # the welcome and the joining at once: a new ring goes to it or is in it
                self._handshakes.discard(sock)
                if self._closed:
                    sock.close()
                    return
                ring = self._ring
                socket.send_fds(sock, [frames.welcome(self.run, self.producer, ring.slots, ring.capacity,
                                                      ring.stride, self.inline_below)], [ring.fd])
                sock.setblocking(False)  # sends wait in _put, acks are read without waiting
                self._consumers = (*self._consumers, _Consumer(sock, name, peer))
                self._changed.notify_all()
        except (LinkError, OSError) as e:
            sock.close()
            with self._changed:
                self._handshakes.discard(sock)
                if self._closed:  # close() ended it
                    return
            self._note(e if isinstance(e, LinkError) else LinkError(
                f"{self.producer}: a consumer's handshake failed ({type(e).__name__}: {e})"))

    def _admit(self, sock: socket.socket) -> tuple[str, str]:
        """The name and description of the consumer whose hello ``sock`` brings, once checked."""
        pid, uid, _ = _CRED.unpack(sock.getsockopt(socket.SOL_SOCKET, socket.SO_PEERCRED, _CRED.size))
        peer = f"a consumer (pid {pid})"
        if uid != os.getuid():
            raise LinkError(f"{self.producer}: {peer} is of user {uid}, not this process's {os.getuid()}")
        sock.settimeout(self.handshake_timeout)
        data, _, flags, _ = sock.recvmsg(frames.MAX_HANDSHAKE + 1)
        if flags & socket.MSG_TRUNC:
            raise LinkError(f"{self.producer}: {peer}: its hello is longer than {frames.MAX_HANDSHAKE} bytes")
        run, producer, name = frames.read_hello(data, f"{self.producer}: {peer}")
        peer = f"consumer {name!r} (pid {pid})"
        if (run, producer) != (self.run, self.producer):
            reason = (f"it asked for producer {producer!r} of run {run!r}; this is producer {self.producer!r} "
                      f"of run {self.run!r}")
            sock.send(frames.refusal(reason))
            raise LinkError(f"{self.producer}: {peer} refused: {reason}")
        return name, peer

    def close(self) -> None:
        """Stop admitting, unlink the socket, close every connection and the ring (idempotent)."""
        if self._listener.fileno() < 0:
            return
        with self._changed:
            self._closed = True
            self._changed.notify_all()  # (an acceptor waiting to try again)
            for sock in self._handshakes:  # a handshake under way ends now (its thread closes the socket)
                try:
                    sock.shutdown(socket.SHUT_RDWR)
                except OSError:
                    pass
        try:
            self._listener.shutdown(socket.SHUT_RDWR)
        except OSError:
            pass
        self._acceptor.join()
        self._listener.close()
        try:
            os.unlink(self.path)
        except FileNotFoundError:
            pass
        with self._changed:
            consumers, self._consumers = self._consumers, ()
        for consumer in consumers:
            consumer.sock.close()
        self._ring.close()

    def __enter__(self) -> LinkServer:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def _check_folder(path: Path) -> None:
    """The socket's folder must be this user's alone (no one else may connect or squat the
    name), and its path fit a Unix socket's address."""
    if len(os.fsencode(str(path))) > MAX_PATH:
        raise LinkError(f"a link socket's path is longer than {MAX_PATH} bytes: {path}")
    info = os.stat(path.parent)
    if not stat.S_ISDIR(info.st_mode) or info.st_uid != os.getuid() or info.st_mode & 0o077:
        raise LinkError(f"a link socket's folder must be this user's alone (mode 0700), not {oct(info.st_mode)} "
                        f"of user {info.st_uid}: {path.parent}")


def _clear_stale(path: Path) -> None:
    """Remove a socket at ``path`` that no one listens on (a SIGKILLed producer's, whose restart
    binds the same path); anything else there (a live producer's socket, a symlink, a file) is
    a LinkError naming it, left as it is."""
    try:
        info = os.lstat(path)
    except FileNotFoundError:
        return
    if not stat.S_ISSOCK(info.st_mode):
        raise LinkError(f"a link socket's path is taken by something that is no socket (a symlink, a file): {path}; "
                        "remove it, or give the link another path")
    probe = socket.socket(socket.AF_UNIX, socket.SOCK_SEQPACKET | socket.SOCK_CLOEXEC)
    try:
        probe.connect(str(path))
    except ConnectionRefusedError:  # no one listens: a dead producer's
        os.unlink(path)
        return
    except OSError as e:
        raise LinkError(f"a link socket's path is taken by a socket that is no link's ({e.strerror}): {path}") from None
    finally:
        probe.close()
    raise LinkError(f"a link socket's path is taken: a producer listens at {path} (another one of the same node "
                    "and run still running?)")
