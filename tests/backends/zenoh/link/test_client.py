"""A link's consumer end (retriever/backends/zenoh/link/client.py): it gets a producer's
messages in order from a process of its own, sees a killed producer's end, and refuses a hostile
producer (a raw one written here: a bad welcome, a file that is no sealed memfd of the announced
size, a frame too short or too long or of an unknown type, a handle out of the ring or stale),
naming what and whom, without reading out of bounds."""

from __future__ import annotations

import fcntl
import os
import queue
import socket
import threading

import pytest

from retriever.backends.zenoh.link import LinkClient
from retriever.backends.zenoh.link import frames
from retriever.backends.zenoh.link.ring import Ring, stride_for
from retriever.errors import LinkError
from tests.backends.zenoh.link.link_peers import digest

RUN, PRODUCER = "run-1", "camera"
SIZES = [64, 200_000, 16, 1 << 20, 70_000, 8]
INLINE_BELOW = 65_536


def test_a_killed_producers_consumer_is_told_and_only_its_socket_file_is_left(folder, peers):
    producer = peers("produce", folder / "p.sock", RUN, PRODUCER, 1, *SIZES)
    assert producer.line() == "ready"
    got: queue.Queue = queue.Queue()
    closed: queue.Queue = queue.Queue()
    client = LinkClient(folder / "p.sock", RUN, PRODUCER, "sink",
                        lambda kind, data: got.put((kind, int.from_bytes(data[:8], "little"), len(data),
                                                    __import__("hashlib").sha256(data).hexdigest())), closed.put)
    assert producer.line() == "sent"
    assert [got.get(timeout=30) for _ in SIZES] == [(i % 3, i, size, digest(i, size)) for i, size in enumerate(SIZES)]
    producer.kill()
    with pytest.raises(LinkError, match=r"producer 'camera' \(pid \d+, p.sock\) closed the connection"):
        raise closed.get(timeout=30)
    client.close()
    assert os.listdir(folder) == ["p.sock"]  # a SIGKILLed producer's socket: the run folder's cleanup removes it
    os.unlink(folder / "p.sock")


class RawProducer:
    """A producer written by hand, on a thread: it takes one connection, answers the hello with
    ``welcome`` (and ``fds``), sends ``sent`` frames, waits for an ack (kept) if ``then`` is
    given, then sends ``then``'s."""

    def __init__(self, folder, welcome: bytes, fds: list[int], sent: list[bytes], then: list[bytes] = ()):
        self.listener = socket.socket(socket.AF_UNIX, socket.SOCK_SEQPACKET)
        self.listener.bind(str(folder / "p.sock"))
        self.listener.listen()
        self.acks: list[bytes] = []
        self.thread = threading.Thread(target=self._serve, args=(welcome, fds, sent, then))
        self.thread.start()
        self.path = folder / "p.sock"

    def _serve(self, welcome: bytes, fds: list[int], sent: list, then: list) -> None:
        sock, _ = self.listener.accept()
        with sock:
            assert frames.read_hello(sock.recv(4096), "test") == (RUN, PRODUCER, "sink")
            socket.send_fds(sock, [welcome], fds) if fds else sock.send(welcome)
            for frame in sent:
                sock.send(frame)
            if then:
                self.acks.append(sock.recv(64))
            try:
                for frame in then:  # a frame, or (a frame, its fds)
                    socket.send_fds(sock, [frame[0]], frame[1]) if type(frame) is tuple else sock.send(frame)
                while sock.recv(64):
                    pass
            except (BrokenPipeError, ConnectionResetError):  # the consumer ended (with frames unread)
                pass

    def close(self) -> None:
        self.thread.join()
        self.listener.close()
        os.unlink(self.path)


def _welcome(slots: int = 2, capacity: int = 100_000, run: str = RUN, stride: int | None = None) -> bytes:
    return frames.welcome(run, PRODUCER, slots, capacity, stride or stride_for(capacity), INLINE_BELOW)


def _memfd(size: int, seals: int = fcntl.F_SEAL_SHRINK | fcntl.F_SEAL_GROW | fcntl.F_SEAL_SEAL) -> int:
    fd = os.memfd_create("hostile", os.MFD_ALLOW_SEALING)
    os.ftruncate(fd, size)
    if seals:
        fcntl.fcntl(fd, fcntl.F_ADD_SEALS, seals)
    return fd


RING_BYTES = 2 * stride_for(100_000)
WELCOMES = {
    "garbage": (lambda: (b"\xc1", []), r"producer 'camera' \(pid \d+, p.sock\): its welcome is not valid msgpack"),
    "a refusal": (lambda: (frames.refusal("not you"), []), r"refused this consumer: not you"),
    "of another version": (lambda: (_welcome().replace(b"\x01", b"\x05", 1), []),
                           r"its welcome is of link version 5, this process's is 1"),
    "of another run": (lambda: (_welcome(run="run-2"), [_memfd(RING_BYTES)]),
                       r"it is producer 'camera' of run 'run-2', not 'camera' of run 'run-1'"),
    "with no fd": (lambda: (_welcome(), []), r"its welcome came with 0 fds, not its ring's one"),
    "with two fds": (lambda: (_welcome(), [_memfd(RING_BYTES), _memfd(RING_BYTES)]), r"came with 2 fds"),
    "with a file": (lambda: (_welcome(), [os.open(__file__, os.O_RDONLY)]),
                    r"refused its ring: its fd is no (sealed )?memfd"),
    "with a pipe": (lambda: (_welcome(), [os.pipe()[0]]), r"refused its ring: its fd is no (sealed )?memfd"),
    "with an unsealed memfd": (lambda: (_welcome(), [_memfd(RING_BYTES, seals=0)]),
                               r"its memfd is not sealed against shrinking and growing"),
    "with a smaller memfd": (lambda: (_welcome(), [_memfd(RING_BYTES - 4096)]),
                             rf"its memfd holds {RING_BYTES - 4096} bytes, not the {RING_BYTES} of 2 slots"),
    "with a bad stride": (lambda: (_welcome(stride=4096), [_memfd(2 * 4096)]),
                          r"its geometry \(2 slots of 100000 bytes, stride 4096\) is out of bounds"),
}


@pytest.mark.parametrize("case", WELCOMES)
def test_a_bad_welcome_is_refused_naming_the_producer(folder, case):
    made, error = WELCOMES[case]
    welcome, fds = made()
    producer = RawProducer(folder, welcome, fds, [])
    client = None
    try:
        with pytest.raises(LinkError, match=error):
            client = LinkClient(folder / "p.sock", RUN, PRODUCER, "sink", lambda *_: None, lambda _: None)
    finally:
        if client is not None:  # it should not have been made: end it, or the producer waits forever
            client.close()
        producer.close()
        for fd in fds:
            os.close(fd)


#: frames after a good welcome (a ring of 2 slots of 100000 bytes whose slot 0 holds b"slot0"
#: under generation 5), and the error that ends the connection
FRAMES = {
    "a handle too short": (b"\x02\x00", r"sent a handle frame of 2 bytes \(exactly 22 expected\)"),
    "a handle too long": (frames.handle(0, 0, 5, 5) + b"\x00", r"sent a handle frame of 23 bytes"),
    "a message too short": (b"\x01", r"sent a message frame of 1 bytes \(at least 2 expected\)"),
    "a message too long": (b"\x01\x00" + bytes(INLINE_BELOW), r"sent a frame longer than its welcome allows"),
    "an unknown type": (b"\x07abc", r"sent a frame of unknown type 7 \(4 bytes\)"),
    "a slot out of range": (frames.handle(0, 2, 5, 5), r"a handle names slot 2, out of its ring's 2"),
    "a length past the slot": (frames.handle(0, 0, 5, 100_001),
                               r"a handle says 100001 bytes, past its ring's slots of 100000"),
    "a stale generation": (frames.handle(0, 0, 4, 5), r"a handle of slot 0 says generation 4, the slot holds 5: a "
                                                      r"stale handle, or a slot rewritten before it was read"),
    "a slot never written": (frames.handle(0, 1, 0, 5), r"a handle of slot 1 says generation 0, the slot holds 0"),
}


def _ended_with(folder, producer: RawProducer, ring: Ring, error: str) -> list:
    """What a consumer of ``producer`` got before its connection ended with ``error`` (a pattern
    of what follows the producer's name); the consumer, producer and ``ring`` closed."""
    got, closed = [], queue.Queue()
    client = LinkClient(folder / "p.sock", RUN, PRODUCER, "sink", lambda *message: got.append(message), closed.put)
    with pytest.raises(LinkError, match=rf"producer 'camera' \(pid \d+, p.sock\): {error}"):
        raise closed.get(timeout=30)
    client.close()
    producer.close()
    ring.close()
    return got


@pytest.mark.parametrize("case", FRAMES)
def test_a_bad_frame_ends_the_connection_naming_it_and_the_producer(folder, case):
    frame, error = FRAMES[case]
    ring = Ring(2, 100_000)
    ring.write(0, [b"slot", memoryview(b"0")], 5, 5)
    good = [frames.INLINE_HEADS[1] + b"inline", frames.handle(2, 0, 5, 5)]
    producer = RawProducer(folder, _welcome(), [ring.fd], good, [frame, frames.INLINE_HEADS[0] + b"never"])
    got = _ended_with(folder, producer, ring, error)
    assert got == [(1, b"inline"), (2, b"slot0")]  # what came before, and nothing after
    assert producer.acks == [frames.ack(0, 5)]


def test_close_ends_the_stream_without_on_closed(folder):
    ring = Ring(1, 4096)
    producer = RawProducer(folder, _welcome(1, 4096), [ring.fd], [])
    closed: list = []
    client = LinkClient(folder / "p.sock", RUN, PRODUCER, "sink", lambda *_: None, closed.append)
    client.close()
    client.close()
    producer.close()
    ring.close()
    assert closed == []


def test_no_producer_listening_is_a_clear_error(folder):
    with pytest.raises(LinkError, match=r"producer 'camera' \(p.sock\): cannot connect to .*p.sock "
                                        r"\(No such file or directory\)"):
        LinkClient(folder / "p.sock", RUN, PRODUCER, "sink", lambda *_: None, lambda _: None)


#: ring frames (and fds) after a good welcome and a good handle, and the error that ends the connection
RINGS = {
    "a ring frame with no fd": (lambda: (frames.ring(2, 100_000, stride_for(100_000)), []),
                                r"sent 0 fds with a frame of type 4 \(a ring frame takes one, the others none\)"),
    "an fd with a message": (lambda: (frames.INLINE_HEADS[0] + b"x", [_memfd(4096)]),
                             r"sent 1 fds with a frame of type 1"),
    "a ring frame with an unsealed memfd": (lambda: (frames.ring(2, 100_000, stride_for(100_000)),
                                                     [_memfd(RING_BYTES, seals=0)]),
                                            r"refused its ring: its memfd is not sealed against shrinking and growing"),
    "a ring frame too short": (lambda: (frames.ring(2, 100_000, stride_for(100_000))[:-1], [_memfd(RING_BYTES)]),
                               r"sent a ring frame of 20 bytes \(exactly 21 expected\)"),
}


@pytest.mark.parametrize("case", RINGS)
def test_a_bad_ring_frame_ends_the_connection_and_leaves_no_fd_open(folder, case):
    open_before = sorted(os.listdir("/proc/self/fd"))
    made, error = RINGS[case]
    frame, fds = made()
    ring = Ring(2, 100_000)
    ring.write(0, [b"slot0"], 5, 5)
    producer = RawProducer(folder, _welcome(), [ring.fd], [frames.handle(2, 0, 5, 5)],
                           [(frame, fds) if fds else frame, frames.INLINE_HEADS[0] + b"never"])
    got = _ended_with(folder, producer, ring, error)
    for fd in fds:
        os.close(fd)
    assert got == [(2, b"slot0")]
    assert sorted(os.listdir("/proc/self/fd")) == open_before  # what the consumer was sent it closed


def test_a_producer_that_closes_without_a_welcome_is_a_link_error(folder):
    """A producer that takes the connection and closes it with the hello unread (a producer
    closing, a hostile one) resets the connection: that is the producer's refusal, a LinkError
    naming it, as its closing before a welcome is, not the socket's bare ConnectionResetError."""
    listener = socket.socket(socket.AF_UNIX, socket.SOCK_SEQPACKET)
    listener.bind(str(folder / "p.sock"))
    listener.listen()

    def take_and_close() -> None:
        sock, _ = listener.accept()
        sock.close()

    taker = threading.Thread(target=take_and_close)
    taker.start()
    try:
        with pytest.raises(LinkError, match=r"producer 'camera' \(pid \d+, p.sock\)"):
            LinkClient(folder / "p.sock", RUN, PRODUCER, "sink", lambda *_: None, lambda _: None)
    finally:
        taker.join()
        listener.close()
        os.unlink(folder / "p.sock")


@pytest.mark.parametrize("first", ["inline", "ring"])
def test_what_a_producer_sent_before_it_closed_is_all_delivered_to_a_consumer_still_busy(folder, first):
    """A producer sends its last messages and END, and closes (its loop finished, or it hands
    over), while its consumer is still busy with an earlier message (a step on the client's
    thread): every message already in the consumer's socket is still delivered, in order, and
    its end is then EOF. Neither the producer's acks left unread at its close (the consumer's
    next read is ECONNRESET) nor the consumer's ack of a ring message after it (EPIPE) loses
    them (review16b: the tail of a stream, END with it, was lost either way)."""
    from retriever.backends.zenoh.link import LinkServer

    server = LinkServer(folder / "p.sock", RUN, PRODUCER)
    inside, release = threading.Event(), threading.Event()
    got: list = []
    closed: queue.Queue = queue.Queue()

    def on_message(kind: int, data: bytes) -> None:
        got.append((kind, len(data)))
        if len(got) == 1:  # busy with the first: the rest waits in the socket
            inside.set()
            release.wait(30)

    client = LinkClient(folder / "p.sock", RUN, PRODUCER, "sink", on_message, closed.put)
    try:
        assert server.wait_for(1, 30)
        server.send([bytes(200_000) if first == "ring" else b"first"], 1)
        assert inside.wait(30)
        server.send([bytes(100_000)], 1)  # through the ring: its ack comes after the close
        server.send([b"tail"], 1)
        server.send([b""], 255)  # END
    finally:
        server.close()
        release.set()
    why = closed.get(timeout=30)
    client.close()
    assert got == [(1, 200_000 if first == "ring" else 5), (1, 100_000), (1, 4), (255, 0)], why
    assert "closed the connection" in str(why) and "reset" not in str(why)
