"""A link's producer end (retriever/backends/zenoh/link/server.py): its messages reach consumers
in processes of their own in order, inline and through the ring; a consumer that withholds its
acks holds it up, a killed one is dropped, and a hostile one (raw frames written here) is dropped
with an error naming it while the others go on."""

from __future__ import annotations

import os
import queue
import socket
import threading

import numpy as np
import pytest

from retriever.backends.zenoh.link import LinkClient, LinkServer
from retriever.backends.zenoh.link import frames
from retriever.backends.zenoh.link.ring import MAX_SLOTS
from retriever.errors import LinkError
from tests.backends.zenoh.link.link_peers import digest, message

RUN, PRODUCER = "run-1", "camera"
#: sizes below and above the inline bound (64 KiB), more ring messages than its 2 slots
SIZES = [64, 200_000, 16, 1 << 20, 70_000, 65_535, 65_536, 8, 1 << 20, 300_000, 100]


def _expected(sizes: list[int]) -> list[dict]:
    return [{"kind": i % 3, "index": i, "len": size, "sha": digest(i, size)} for i, size in enumerate(sizes)]


def _server(folder, **options) -> tuple[LinkServer, queue.Queue]:
    dropped: queue.Queue = queue.Queue()
    options = {"slots": 2, "capacity": 1 << 20, **options}
    return LinkServer(folder / "p.sock", RUN, PRODUCER, on_dropped=dropped.put, **options), dropped


def _send_all(server: LinkServer, sizes: list[int], start: int = 0) -> None:
    for index, size in enumerate(sizes, start):
        server.send(message(index, size), kind=index % 3)


def test_every_consumer_gets_every_message_in_order_inline_and_through_the_ring(folder, peers):
    server, dropped = _server(folder)
    with server:
        consumers = [peers("consume", folder / "p.sock", RUN, PRODUCER, f"sink{i}") for i in range(3)]
        assert [c.line() for c in consumers] == ["ready"] * 3
        assert server.wait_for(3, 30)
        assert sorted(server.consumers) == ["sink0", "sink1", "sink2"]
        _send_all(server, SIZES)
        for consumer in consumers:
            assert consumer.lines(len(SIZES)) == _expected(SIZES)
            assert consumer.end() == 0
    assert dropped.empty()


def _raw_consumer(folder, name: str = "raw", run: str = RUN, producer: str = PRODUCER) -> tuple[socket.socket, int]:
    """A consumer written by hand: its socket after the handshake, and the ring's fd it was given."""
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_SEQPACKET)
    sock.connect(str(folder / "p.sock"))
    sock.send(frames.hello(run, producer, name))
    data, fds, _, _ = socket.recv_fds(sock, 4096, 1)
    assert frames.read_welcome(data, "test")[:2] == (RUN, PRODUCER)
    return sock, fds[0]


def _handle(sock: socket.socket) -> tuple[int, int, int, int]:
    """(kind, slot, generation, length) of the next handle, past the ring the first one comes
    after (a producer's ring is a page until a message needs it: its real ring comes first)."""
    data, fds, _, _ = socket.recv_fds(sock, 64, 1)
    if data[0] == frames.RING and fds:
        assert frames.RING_FRAME.unpack(data)[1] == 2  # (_server's slots)
        os.close(fds[0])
        data = sock.recv(64)
    _, kind, slot, generation, length = frames.HANDLE_FRAME.unpack(data)
    return kind, slot, generation, length


def test_a_consumer_that_withholds_its_acks_holds_the_producer_up_until_it_acks(folder):
    server, dropped = _server(folder, send_timeout=0.2)
    with server:
        sock, fd = _raw_consumer(folder, "slow")
        assert server.wait_for(1, 30)
        big = message(0, 100_000)
        server.send(big)
        server.send(big)
        assert [_handle(sock)[1:3] for _ in range(2)] == [(0, 1), (1, 2)]
        # both slots held by "slow", which acks neither: the third message waits, then gives up
        with pytest.raises(LinkError, match=r"camera: no free slot in its link's ring for 0.2s: consumer 'slow' "
                                            r"\(pid \d+\) did not ack slot 0; a consumer that stopped reading holds"):
            server.send(big)
        sock.send(frames.ack(0, 1))  # the slot it was done with: the send goes on, into that slot
        server.send(big)
        assert _handle(sock)[1:] == (0, 3, 100_000)
        assert dropped.empty()
        sock.close()
        os.close(fd)


def test_a_killed_consumer_is_dropped_and_the_others_go_on(folder, peers):
    server, dropped = _server(folder)
    with server:
        alive, doomed = (peers("consume", folder / "p.sock", RUN, PRODUCER, name) for name in ("alive", "doomed"))
        assert [alive.line(), doomed.line()] == ["ready", "ready"]
        assert server.wait_for(2, 30)
        _send_all(server, SIZES[:2])
        assert doomed.lines(2) == _expected(SIZES[:2])
        doomed.kill()
        _send_all(server, SIZES[2:], start=2)
        assert alive.lines(len(SIZES)) == _expected(SIZES)
        assert server.consumers == ["alive"]
        assert "consumer 'doomed'" in str(dropped.get(timeout=30)) and "is gone" in str(server.dropped[0])
        assert alive.end() == 0


HANDSHAKES = {
    "garbage": (b"\xc1\x00garbage", r"a consumer \(pid \d+\): its hello is not valid msgpack"),
    "not a handshake": (b"\x93\x01\x02\x03", r"its hello is no retriever link handshake"),
    "another version": (frames.hello(RUN, PRODUCER, "x").replace(b"\x01", b"\x07", 1),
                        r"its hello is of link version 7, this process's is 1"),
    "too long": (b"\x00" * 5000, r"its hello is longer than 4096 bytes"),
    "no names": (b"\x95\xaeretriever-link\x01\x01\x02\x03", r"its hello is not \[magic, version, run, producer"),
    "another run": (frames.hello("run-2", PRODUCER, "x"),
                    r"consumer 'x' \(pid \d+\) refused: it asked for producer 'camera' of run 'run-2'"),
    "another producer": (frames.hello(RUN, "lidar", "x"), r"refused: it asked for producer 'lidar' of run 'run-1'"),
}


@pytest.mark.parametrize("case", HANDSHAKES)
def test_a_bad_handshake_is_refused_and_the_others_go_on(folder, peers, case):
    hello, error = HANDSHAKES[case]
    server, dropped = _server(folder)
    with server:
        good = peers("consume", folder / "p.sock", RUN, PRODUCER, "good")
        assert good.line() == "ready" and server.wait_for(1, 30)
        sock = socket.socket(socket.AF_UNIX, socket.SOCK_SEQPACKET)
        sock.connect(str(folder / "p.sock"))
        sock.send(hello)
        assert sock.recv(4096, socket.MSG_PEEK) is not None  # the refusal (if any), then the end
        with pytest.raises(LinkError, match=error):
            raise dropped.get(timeout=30)
        if case.startswith("another ") and case != "another version":
            with pytest.raises(LinkError, match="refused this consumer: it asked for"):
                frames.read_welcome(sock.recv(4096), "test")
        assert sock.recv(4096) == b""  # dropped
        sock.close()
        assert server.consumers == ["good"]
        _send_all(server, SIZES[:4])
        assert good.lines(4) == _expected(SIZES[:4])
        assert good.end() == 0


ACKS = {
    "too short": (b"\x03\x00", r"consumer 'raw' \(pid \d+\): sent a frame of 2 bytes of type 3, not an ack"),
    "too long": (frames.ack(0, 1) + b"\x00", r"sent a frame of 14 bytes of type 3, not an ack"),
    "of an unknown type": (b"\x09" + frames.ack(0, 1)[1:], r"sent a frame of 13 bytes of type 9, not an ack"),
    "of a slot never sent": (frames.ack(1, 1), r"acked slot 1 generation 1, which it does not hold"),
    "of a slot out of range": (frames.ack(99, 1), r"acked slot 99 generation 1, which it does not hold"),
    "of another generation": (frames.ack(0, 7), r"acked slot 0 generation 7, which it does not hold"),
    "twice": (frames.ack(0, 1) * 2, r"acked slot 0 generation 1, which it does not hold \(never sent to it, or "
                                    r"acked before\)"),
}


@pytest.mark.parametrize("case", ACKS)
def test_a_bad_ack_drops_its_consumer_and_the_others_go_on(folder, peers, case):
    sent, error = ACKS[case]
    server, dropped = _server(folder)
    with server:
        good = peers("consume", folder / "p.sock", RUN, PRODUCER, "good")
        assert good.line() == "ready"
        sock, fd = _raw_consumer(folder)
        assert server.wait_for(2, 30)
        _send_all(server, [100_000])
        assert _handle(sock)[1:3] == (0, 1)
        for frame in [sent] if case != "twice" else [sent[:13], sent[13:]]:
            sock.send(frame)
        _send_all(server, [100_000, 100_000], start=1)  # the third needs slot 0: its acks are read
        with pytest.raises(LinkError, match=error):
            raise dropped.get(timeout=30)
        assert server.consumers == ["good"]
        assert good.lines(3) == _expected([100_000] * 3)
        assert good.end() == 0
        sock.close()
        os.close(fd)


def test_a_message_bigger_than_the_slots_grows_the_ring_in_the_streams_order(folder, peers):
    server, dropped = _server(folder, capacity=100_000)
    with server:
        early = peers("consume", folder / "p.sock", RUN, PRODUCER, "early")
        assert early.line() == "ready" and server.wait_for(1, 30)
        sizes = [100_000, 300_000, 70_000, 100, 1 << 20, 200_000]  # grows at 300 000 (to 300 000) and 1 MiB
        _send_all(server, sizes[:3])
        late = peers("consume", folder / "p.sock", RUN, PRODUCER, "late")  # joins with the grown ring
        assert late.line() == "ready" and server.wait_for(2, 30)
        _send_all(server, sizes[3:], start=3)
        assert early.lines(6) == _expected(sizes)
        assert late.lines(3) == _expected(sizes)[3:]
        assert early.end() == 0 and late.end() == 0
    assert dropped.empty()


def test_a_ring_grows_only_once_no_slot_of_the_old_one_is_held(folder):
    server, dropped = _server(folder, send_timeout=0.2)
    with server:
        sock, fd = _raw_consumer(folder, "slow")
        assert server.wait_for(1, 30)
        server.send(message(0, 100_000))
        assert _handle(sock)[1:3] == (0, 1)
        with pytest.raises(LinkError, match=r"no free slot in its link's ring for 0.2s: consumer 'slow' \(pid \d+\) "
                                            r"did not ack slot 0"):
            server.send(message(1, 2 << 20))
        sock.send(frames.ack(0, 1))
        server.send(message(1, 2 << 20))
        data, fds, _, _ = socket.recv_fds(sock, 64, 1)  # the new ring first, then its handle
        assert frames.RING_FRAME.unpack(data)[:3] == (frames.RING, 2, 2 << 20) and len(fds) == 1
        assert os.fstat(fds[0]).st_size == 2 * frames.RING_FRAME.unpack(data)[3]
        assert _handle(sock)[1:] == (0, 2, 2 << 20)
        for descriptor in (fd, *fds):
            os.close(descriptor)
        sock.close()
    assert dropped.empty()


def test_parts_of_any_form_are_written_whole(folder, peers):
    server, _ = _server(folder, capacity=100_000)
    with server:
        sink = peers("consume", folder / "p.sock", RUN, PRODUCER, "sink")
        assert sink.line() == "ready" and server.wait_for(1, 30)
        head = (7).to_bytes(8, "little")
        server.send([memoryview(head), np.full(99_992 // 4, 3, np.float32)])  # a float array's bytes, uncast
        assert sink.line()["sha"] == __import__("hashlib").sha256(
            head + np.full(99_992 // 4, 3, np.float32).tobytes()).hexdigest()
        assert sink.end() == 0


def test_the_socket_wants_a_private_folder(tmp_path):
    open_folder = tmp_path / "open"
    open_folder.mkdir(mode=0o755)
    open_folder.chmod(0o755)
    with pytest.raises(LinkError, match=r"a link socket's folder must be this user's alone \(mode 0700\)"):
        LinkServer(open_folder / "p.sock", RUN, PRODUCER)
    with pytest.raises(LinkError, match="a link socket's path is longer than 107 bytes"):
        LinkServer(tmp_path / ("x" * 120), RUN, PRODUCER)


def test_a_connection_that_says_nothing_holds_up_no_other_consumer(folder, peers):
    server, dropped = _server(folder, handshake_timeout=600)  # far past the wait below: only a hold-up would fail
    with server:
        silent = socket.socket(socket.AF_UNIX, socket.SOCK_SEQPACKET)
        silent.connect(str(folder / "p.sock"))
        good = peers("consume", folder / "p.sock", RUN, PRODUCER, "good")
        assert good.line() == "ready" and server.wait_for(1, 30)
        _send_all(server, SIZES[:2])
        assert good.lines(2) == _expected(SIZES[:2])
        assert good.end() == 0
        with pytest.raises(LinkError, match=r"a link message's kind is a byte \(0..255\), not 256"):
            server.send([b"x"], kind=256)
    silent.close()
    assert dropped.empty()


def test_a_consumer_gone_with_slots_unacked_frees_them(folder, peers):
    server, dropped = _server(folder, send_timeout=30)  # a bound on a hang only: the slots free at once
    with server:
        good = peers("consume", folder / "p.sock", RUN, PRODUCER, "good")
        assert good.line() == "ready"
        sock, fd = _raw_consumer(folder, "gone")
        assert server.wait_for(2, 30)
        _send_all(server, [100_000, 100_000])  # both slots: "gone" acks neither
        assert [_handle(sock)[1:3] for _ in range(2)] == [(0, 1), (1, 2)]
        sock.close()  # as the kernel does for a killed process
        os.close(fd)
        _send_all(server, [100_000, 100_000], start=2)  # slot 0 again: its holder's end is read, the slot freed
        with pytest.raises(LinkError, match=r"camera: consumer 'gone' \(pid \d+\) is gone \(closed its connection\): "
                                            r"dropped"):
            raise dropped.get(timeout=30)
        assert server.consumers == ["good"]
        assert good.lines(4) == _expected([100_000] * 4)
        assert good.end() == 0


def test_a_consumer_that_acks_every_slot_at_once_is_never_held_up_by_the_most_slots(folder):
    """Acks are read only while a send waits for a slot: up to ``slots`` acks wait unread in a
    consumer's socket, and one more than it holds would block the consumer in its ack, so it read
    no more handles and the link stalled with a healthy consumer (review14: with 1024 slots send
    raised 'took no message' after ~550 of 2048; with 512 the last ~270 messages never came).
    The most slots a ring may have (MAX_SLOTS) stay below that; more are refused."""
    with pytest.raises(LinkError, match="out of bounds"):
        _server(folder, slots=MAX_SLOTS + 1, capacity=1)
    server, dropped = _server(folder, slots=MAX_SLOTS, capacity=1, inline_below=0, send_timeout=10)
    got: queue.Queue = queue.Queue()
    closed: queue.Queue = queue.Queue()
    total = 32 * MAX_SLOTS
    with server:
        client = LinkClient(folder / "p.sock", RUN, PRODUCER, "sink", lambda kind, data: got.put(data), closed.put)
        assert server.wait_for(1, 30)
        for index in range(total):
            server.send([bytes([index % 256])])
        assert [got.get(timeout=30) for _ in range(total)] == [bytes([index % 256]) for index in range(total)]
        client.close()
    assert dropped.empty() and closed.empty()


def test_a_stale_socket_file_of_a_killed_producer_is_replaced(folder):
    """A SIGKILLed producer leaves its socket file (link/__init__.py), and its restart makes a new
    LinkServer at the same path: a socket no one listens on is stale, replaced; the bind's bare
    'Address already in use' refused it."""
    stale = socket.socket(socket.AF_UNIX, socket.SOCK_SEQPACKET)
    stale.bind(str(folder / "p.sock"))
    stale.close()  # as the kernel closes a killed process's: the file stays
    try:
        server, dropped = _server(folder)
    except BaseException:
        os.unlink(folder / "p.sock")
        raise
    with server:
        sock, fd = _raw_consumer(folder, "after")
        assert server.wait_for(1, 30)
        sock.close()
        os.close(fd)
    assert dropped.empty()


@pytest.mark.parametrize("what", ["a live producer's socket", "a symlink", "a file"])
def test_a_path_taken_by_something_else_is_a_link_error_naming_it(folder, what):
    path = folder / "p.sock"
    other = None
    if what == "a live producer's socket":
        other = socket.socket(socket.AF_UNIX, socket.SOCK_SEQPACKET)
        other.bind(str(path))
        other.listen()
    elif what == "a symlink":
        os.symlink(folder / "elsewhere.sock", path)
    else:
        path.write_bytes(b"")
    try:
        with pytest.raises(LinkError, match=r"p\.sock"):
            LinkServer(path, RUN, PRODUCER)
        assert os.path.lexists(path)  # what was there is left as it was
    finally:
        if other is not None:
            other.close()
        os.unlink(path)


def test_running_out_of_fds_while_connections_pile_up_leaves_a_later_consumer_admitted(folder, peers):
    """Each connection is accepted at once and holds an fd (and a thread) for its handshake, with
    no bound: connections that say nothing use up the producer's fds, and accept's EMFILE was
    taken for the listener's close, ending the acceptor: no consumer was admitted again, and
    nothing said so. Once the silent ones time out (1 s), a consumer must get through."""
    producer = peers("short-of-fds", folder / "p.sock", RUN, PRODUCER, 4)
    assert producer.line() == "ready"
    silent = []
    for _ in range(12):  # more than its 4 spare fds (and the free numbers below its highest), fewer than the backlog
        sock = socket.socket(socket.AF_UNIX, socket.SOCK_SEQPACKET)
        sock.connect(str(folder / "p.sock"))
        silent.append(sock)
    closed: queue.Queue = queue.Queue()
    try:
        client = LinkClient(folder / "p.sock", RUN, PRODUCER, "late", lambda *_: None, closed.put, timeout=30)
        assert producer.line() == "admitted"
        client.close()
    except BaseException:
        producer.kill()  # its socket file stays: removed here, as a run folder's cleanup would
        os.unlink(folder / "p.sock")
        raise
    finally:
        for sock in silent:
            sock.close()
    assert producer.end() == 0
    assert closed.empty()


def test_a_ring_growth_that_times_out_leaves_no_ring_open(folder):
    """A growth whose RING frame a consumer does not take in time raises (send's LinkError), the
    new ring in place: the old one (its memfd and mapping, up to slots x capacity) was left open
    for the process's life, close() closing only the new."""
    open_before = sorted(os.listdir("/proc/self/fd"))
    server, dropped = _server(folder, capacity=4096, send_timeout=0.2)
    with server:
        sock, fd = _raw_consumer(folder, "stuck")  # reads nothing from here on
        assert server.wait_for(1, 30)
        with pytest.raises(LinkError, match="took no message for 0.2s"):
            for _ in range(100_000):  # until its socket is full
                server.send([b"x" * 1000])
        with pytest.raises(LinkError, match="took no message for 0.2s"):
            server.send([bytes(100_000)])  # past the slots: a new ring, whose frame it does not take
    sock.close()
    os.close(fd)
    assert sorted(os.listdir("/proc/self/fd")) == open_before


def test_connections_past_the_handshakes_bound_are_closed_at_once(folder):
    """Each connection under way holds a thread and an fd for up to its handshake's timeout: past
    MAX_HANDSHAKES of them a connection is closed at once, and said (there was no bound)."""
    from retriever.backends.zenoh.link.server import MAX_HANDSHAKES

    server, dropped = _server(folder, handshake_timeout=600)  # only close() ends the silent ones
    silent = []
    with server:
        for _ in range(MAX_HANDSHAKES + 1):
            sock = socket.socket(socket.AF_UNIX, socket.SOCK_SEQPACKET)
            sock.connect(str(folder / "p.sock"))
            silent.append(sock)
        with pytest.raises(LinkError, match=rf"camera: a connection closed at once: {MAX_HANDSHAKES} handshakes are "
                                            r"under way \(connections that say nothing\?\)"):
            raise dropped.get(timeout=30)
        assert silent[-1].recv(16) == b""  # the last one, closed
    for sock in silent:
        sock.close()


def test_a_message_of_more_parts_than_a_sendmsg_takes_reaches_every_consumer(folder):
    """An inline message went as one sendmsg of its parts: past IOV_MAX (1024) of them, as the wire
    encoder makes of a value with 510 arrays and more, sendmsg's EMSGSIZE was taken for a gone
    consumer: every consumer was dropped ('is gone (Message too long)')."""
    server, dropped = _server(folder)
    got: queue.Queue = queue.Queue()
    closed: queue.Queue = queue.Queue()
    with server:
        client = LinkClient(folder / "p.sock", RUN, PRODUCER, "sink", lambda kind, data: got.put(data), closed.put)
        assert server.wait_for(1, 30)
        server.send([b"ab"] * 1100)
        assert got.get(timeout=30) == b"ab" * 1100
        client.close()
    assert dropped.empty() and closed.empty()


def test_a_send_that_reached_some_consumers_only_closes_the_link(folder):
    """"good" took the message, "stuck" (its socket full) did not in time: the stream is out of
    order between them, so the link closes, its socket goes, and every later send raises."""
    server, _ = _server(folder, send_timeout=0.2)
    with server:
        good, good_fd = _raw_consumer(folder, "good")
        assert server.wait_for(1, 30)
        stuck, stuck_fd = _raw_consumer(folder, "stuck")  # reads nothing from here on
        assert server.wait_for(2, 30)
        reading = threading.Event()

        def drain() -> None:
            good.settimeout(5)
            while not reading.is_set():
                try:
                    if not good.recv(70_000):
                        return
                except OSError:
                    return

        drainer = threading.Thread(target=drain)
        drainer.start()
        try:
            with pytest.raises(LinkError, match="'stuck' .* took no message for 0.2s"):
                for _ in range(100_000):  # until stuck's socket is full
                    server.send([b"x" * 1000])
            assert not (folder / "p.sock").exists(), "the link closed"
            with pytest.raises(LinkError, match=r"camera: its link is closed"):
                server.send([b"x"])
        finally:
            reading.set()
            good.close()
            drainer.join()
    for fd in (good_fd, stuck_fd):
        os.close(fd)
    stuck.close()


def test_a_send_after_close_raises_a_link_error_not_a_bare_one(folder):
    server, _ = _server(folder)
    sock, fd = _raw_consumer(folder, "late")
    assert server.wait_for(1, 30)
    server.close()
    with pytest.raises(LinkError, match=r"camera: its link is closed"):
        server.send([bytes(100_000)])
    sock.close()
    os.close(fd)


def test_the_ring_is_a_page_until_a_message_needs_it(folder):
    """A producer of small messages maps one page, not its slots' bytes (8 x 4 MiB by default,
    every page written: 32 MiB of memory each): its ring comes with its first big message."""
    import mmap

    server = LinkServer(folder / "p.sock", RUN, PRODUCER)
    with server:
        sock, fd = _raw_consumer(folder, "small")
        assert server.wait_for(1, 30)
        assert os.fstat(fd).st_size == mmap.PAGESIZE
        server.send(message(0, 1000))  # inline: no ring
        server.send(message(1, 100_000))
        assert sock.recv(64)[0] == frames.INLINE
        data, fds, _, _ = socket.recv_fds(sock, 64, 1)
        assert frames.RING_FRAME.unpack(data)[:3] == (frames.RING, 8, 4 << 20) and len(fds) == 1
        assert frames.HANDLE_FRAME.unpack(sock.recv(64))[2:] == (0, 1, 100_000)
        for descriptor in (fd, *fds):
            os.close(descriptor)
        sock.close()


RING_PAST_THE_FILE_SIZE_LIMIT = """
import resource, tempfile, os
from pathlib import Path
from retriever.backends.zenoh.link import LinkClient, LinkServer
from retriever.errors import LinkError
resource.setrlimit(resource.RLIMIT_FSIZE, (20_000, 20_000))
folder = Path(tempfile.mkdtemp())
with LinkServer(folder / "p.sock", "run-1", "camera") as server:  # a page: within the limit
    client = LinkClient(folder / "p.sock", "run-1", "camera", "sink", lambda kind, data: None, lambda why: None)
    assert server.wait_for(1, 30)
    try:
        server.send([bytes(100_000)])  # the ring of 8 x 4 MiB it needs: past the limit
    except LinkError as e:
        print(e)
    client.close()
os.rmdir(folder)
"""


def test_a_ring_past_the_file_size_limit_is_a_link_error_that_says_so():
    """A memfd counts against RLIMIT_FSIZE (`ulimit -f`): past it the ring cannot be made, said as
    such (it was a bare OSError, File too large: the worker's crash)."""
    import re
    import subprocess
    import sys

    result = subprocess.run([sys.executable, "-c", RING_PAST_THE_FILE_SIZE_LIMIT], capture_output=True, text=True,
                            timeout=60)
    assert result.returncode == 0, result.stderr
    assert re.fullmatch(r"cannot make a link ring of \d+ bytes: File too large \(the process's file size limit, "
                        r"ulimit -f, is below it: a memfd counts as a file\)\n", result.stdout), result.stdout
