"""A diagnostic for fig7a_latency.py: raw zenoh-python carrying only a handle, the payload in a
shared-memory ring of our own (benchmarks/reports/shm_channel.md).

The publisher creates a ring file in /dev/shm (``O_EXCL``, its pages touched once), and at each
tick writes the numpy array straight into the next slot (one ``np.copyto``: no intermediate
bytes) under a seqlock (the slot's generation odd while written, even after), then ``put``s a
40-byte handle (ring id, slot, generation, length) over Zenoh with exactly raw-zenoh's session and
publisher settings (latency.py's ``_config``, peer mode, loopback TCP, ``express=False``) and
raw-zenoh's attachment ``[seq, sent_ns]``. The subscriber iterates ``for sample in subscriber:``,
maps the ring read-only the first time it sees its id (the file named from the id, the header's
id and geometry checked), refuses a handle whose slot or length is out of the ring, and then

    copy   copies the slot out (``np.array``: a new array the reader owns), then reads the slot's
           generation again: unchanged = the bytes are the ones published (seqlock); else torn
    view   takes a read-only ``np.frombuffer`` view of the slot, no copy (what dora's receiver
           does); nothing holds the slot: the diagnostic shows the cost only, not a safe design

and takes ``time.time_ns()``. The ring is unlinked by the publisher at its end (also on error),
and by the harness after both processes are gone (a publisher killed): nothing is left in
/dev/shm. Not part of Retriever; nothing in retriever/ uses it.

    python benchmarks/shm_ring.py --selftest     # hostile handles refused, a lapped slot detected

``raw-unix-shm-copy`` (fig7a_latency.py): the copy side with no Zenoh at all, the handles over a
Unix datagram socket: what the handle's own transport costs.

``SHM_RING_EXPRESS=1`` in the environment of fig7a_latency.py: the handle's publisher declared
``express=True``, as Retriever's publishers are (a diagnostic of this diagnostic).
"""

from __future__ import annotations

import json
import mmap
import os
import re
import struct
import subprocess
import sys
import threading
import time
import uuid
from pathlib import Path
from typing import Iterator

import numpy as np

HERE = Path(__file__).resolve().parent
SHM = Path("/dev/shm")
MAGIC = b"RTVRING1"
HEADER = struct.Struct("<8s16sIIQ")  # magic, ring id, slots, reserved, slot capacity (bytes)
HANDLE = struct.Struct("<16sIIQQ")  # ring id, slot, reserved, generation, length: 40 bytes
PAGE = mmap.PAGESIZE
TABLE_AT = 64  # per slot: generation u64, length u64
SLOTS = 8


class RingError(Exception):
    """A handle or ring this reader refuses (never read out of bounds)."""


def ring_path(ring_id: bytes) -> Path:
    return SHM / f"retriever-ring-{ring_id.hex()}"


def _geometry(slots: int, capacity: int) -> tuple[int, int, int]:
    stride = -(-capacity // PAGE) * PAGE
    data_at = -(-(TABLE_AT + 16 * slots) // PAGE) * PAGE
    return stride, data_at, data_at + slots * stride


class Writer:
    """The publisher's end: creates the ring (O_EXCL), writes slots round-robin under a seqlock."""

    def __init__(self, ring_id: bytes, capacity: int, slots: int = SLOTS):
        self.ring_id, self.slots, self.capacity = ring_id, slots, capacity
        self.stride, self.data_at, size = _geometry(slots, capacity)
        self.path = ring_path(ring_id)
        fd = os.open(self.path, os.O_RDWR | os.O_CREAT | os.O_EXCL, 0o600)
        try:
            os.ftruncate(fd, size)
            self.mm = mmap.mmap(fd, size, mmap.MAP_SHARED, mmap.PROT_READ | mmap.PROT_WRITE)
        except BaseException:
            os.close(fd)
            self.path.unlink()
            raise
        os.close(fd)
        self.bytes = np.frombuffer(self.mm, dtype=np.uint8)
        self.bytes[:] = 0  # every page allocated now, not on the first messages
        self.table = self.bytes[TABLE_AT:TABLE_AT + 16 * slots].view(np.uint64).reshape(slots, 2)
        HEADER.pack_into(self.mm, 0, MAGIC, ring_id, slots, 0, capacity)
        self.next = 0

    def write(self, array: np.ndarray) -> bytes:
        """Copy ``array``'s bytes into the next slot; the handle naming them."""
        n = array.nbytes
        if n > self.capacity:
            raise RingError(f"{n} bytes do not fit a slot of {self.capacity}")
        slot = self.next
        self.next = (slot + 1) % self.slots
        row = self.table[slot]
        gen = int(row[0]) + 1
        row[0] = gen  # odd: being written
        at = self.data_at + slot * self.stride
        np.copyto(self.bytes[at:at + n], array.reshape(-1).view(np.uint8))
        row[1] = n
        row[0] = gen + 1  # even: stable
        return HANDLE.pack(self.ring_id, slot, 0, gen + 1, n)

    def close(self) -> None:
        del self.table, self.bytes
        self.mm.close()
        self.path.unlink(missing_ok=True)


class Reader:
    """A subscriber's end: maps each ring read-only once, checks every handle against it."""

    NAME = re.compile(r"retriever-ring-[0-9a-f]{32}")

    def __init__(self, expected_ids: set[bytes] | None = None):
        self.rings: dict[bytes, tuple] = {}
        self.expected = expected_ids  # a run's own rings; None: any (the benchmark names none)

    def _ring(self, ring_id: bytes):
        ring = self.rings.get(ring_id)
        if ring is not None:
            return ring
        if self.expected is not None and ring_id not in self.expected:
            raise RingError(f"ring {ring_id.hex()} is not one of this run's")
        path = ring_path(ring_id)
        assert self.NAME.fullmatch(path.name)
        try:
            fd = os.open(path, os.O_RDONLY | os.O_NOFOLLOW)
        except OSError as e:
            raise RingError(f"ring {ring_id.hex()}: {e.strerror}") from None
        try:
            size = os.fstat(fd).st_size
            if size < PAGE:
                raise RingError(f"ring {ring_id.hex()}: {size} bytes, no header")
            mm = mmap.mmap(fd, size, mmap.MAP_SHARED | mmap.MAP_POPULATE, mmap.PROT_READ)
        finally:
            os.close(fd)
        magic, rid, slots, _, capacity = HEADER.unpack_from(mm, 0)
        stride, data_at, need = _geometry(slots, capacity) if slots else (0, 0, -1)
        if magic != MAGIC or rid != ring_id or not slots or need != size:
            mm.close()
            raise RingError(f"ring {ring_id.hex()}: not a ring of this id and geometry")
        whole = np.frombuffer(mm, dtype=np.uint8)
        table = whole[TABLE_AT:TABLE_AT + 16 * slots].view(np.uint64).reshape(slots, 2)
        ring = self.rings[ring_id] = (mm, whole, table, slots, capacity, stride, data_at)
        return ring

    def _locate(self, handle: bytes):
        if len(handle) != HANDLE.size:
            raise RingError(f"a handle of {len(handle)} bytes, not {HANDLE.size}")
        ring_id, slot, _, gen, n = HANDLE.unpack(handle)
        _, whole, table, slots, capacity, stride, data_at = self._ring(ring_id)
        if slot >= slots or n > capacity or gen & 1:
            raise RingError(f"handle out of ring {ring_id.hex()}: slot {slot} of {slots}, {n} bytes of "
                            f"{capacity}, generation {gen}")
        if int(table[slot, 0]) != gen:
            raise RingError(f"slot {slot} lapped: generation {int(table[slot, 0])}, the handle's {gen}")
        at = data_at + slot * stride
        return whole[at:at + n], table, slot, gen

    def copy(self, handle: bytes) -> np.ndarray:
        src, table, slot, gen = self._locate(handle)
        out = np.array(src)  # the reader's own bytes
        if int(table[slot, 0]) != gen:
            raise RingError(f"slot {slot} rewritten while read: generation {int(table[slot, 0])}, the handle's {gen}")
        return out

    def view(self, handle: bytes) -> np.ndarray:
        return self._locate(handle)[0]  # read-only (the mapping is)

    def copy_bytes(self, handle: bytes) -> bytes:
        """:meth:`copy`, as the bytes a data message is (what ``payload.to_bytes()`` gives)."""
        src, table, slot, gen = self._locate(handle)
        out = src.tobytes()
        if int(table[slot, 0]) != gen:
            raise RingError(f"slot {slot} rewritten while read: generation {int(table[slot, 0])}, the handle's {gen}")
        return out

    def view_memory(self, handle: bytes) -> memoryview:
        """:meth:`view`, as a memoryview (what wire.decode_events takes): nothing holds the slot."""
        return memoryview(self._locate(handle)[0])

    def close(self) -> None:
        maps = [ring[0] for ring in self.rings.values()]
        self.rings.clear()  # the arrays over the maps first: a map with views on it does not close
        for mm in maps:
            mm.close()


# ---------------------------------------------------------------------------------------------
# The two processes (run as this script with --pub / --sub), and the harness's side
# ---------------------------------------------------------------------------------------------
def _serve(arrivals: Iterator[tuple[int, int, int, bytes]], take, total: int, timeout: float) -> dict:
    """A subscriber's side: on a thread, each arrival ``(arrival ns, seq, sent ns, handle)``'s
    slot taken (copied out or viewed) and noted, or the reader's refusal, up to seq ``total`` - 1;
    READY said first; what was got once the last came or ``timeout`` passed."""
    got: list[tuple[int, int, int, int, int]] = []
    errors: list[str] = []
    done = threading.Event()

    def drain() -> None:
        for cb_in, seq, sent, handle in arrivals:
            try:
                arr = take(handle)
            except RingError as e:
                errors.append(str(e))
            else:
                got.append((seq, sent, time.time_ns(), arr.size, cb_in))
                del arr
            if seq == total - 1:
                done.set()
                return
    threading.Thread(target=drain, daemon=True).start()
    print("READY", flush=True)
    done.wait(timeout)
    return {"got": got, "errors": errors}


def shm_sub(key: str, listen: str, total: int, timeout: float, mode: str) -> int:
    import zenoh
    from latency import ATTACH, _config

    reader = Reader()
    with zenoh.open(_config(listen=listen)) as session:
        sub = session.declare_subscriber(key)
        arrivals = ((time.time_ns(), *ATTACH.unpack(sample.attachment.to_bytes()), sample.payload.to_bytes())
                    for sample in sub)
        result = _serve(arrivals, reader.copy if mode == "copy" else reader.view, total, timeout)
        sub.undeclare()
    reader.close()
    print(json.dumps(result), flush=True)
    return 0


def shm_pub(key: str, connect: str, size: int, total: int, hz: float, ring_hex: str) -> int:
    import zenoh
    from latency import ATTACH, _config, paced

    data = np.zeros(size, dtype=np.uint8)
    ring = Writer(bytes.fromhex(ring_hex), size)
    try:
        with zenoh.open(_config(connect=connect)) as session:
            pub = session.declare_publisher(key, express=os.environ.get("SHM_RING_EXPRESS") == "1")
            give_up = time.monotonic() + 20
            while not pub.matching_status.matching and time.monotonic() < give_up:
                time.sleep(0.01)
            time.sleep(0.2)  # let the subscriber's route settle (as raw-zenoh's publisher)
            for seq, sent in paced(data, total, hz):
                pub.put(ring.write(data), attachment=ATTACH.pack(seq, sent))
            time.sleep(0.3)  # let the last samples leave before the session closes
            pub.undeclare()
    finally:
        ring.close()
    print("[]", flush=True)
    return 0


def unix_sub(name: str, total: int, timeout: float) -> int:
    """shm_sub's copy without Zenoh: the handles come over a Unix datagram socket (``name``, in
    the abstract namespace), received by a plain blocking ``recv`` loop on a thread."""
    import socket

    from latency import ATTACH

    reader = Reader()
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    sock.bind("\0" + name)

    def arrivals() -> Iterator[tuple[int, int, int, bytes]]:
        while True:
            message = sock.recv(256)
            yield (time.time_ns(), *ATTACH.unpack_from(message, 0), message[ATTACH.size:])
    result = _serve(arrivals(), reader.copy, total, timeout)
    sock.close()
    reader.close()
    print(json.dumps(result), flush=True)
    return 0


def unix_pub(name: str, size: int, total: int, hz: float, ring_hex: str) -> int:
    import socket

    from latency import ATTACH, paced

    data = np.zeros(size, dtype=np.uint8)
    ring = Writer(bytes.fromhex(ring_hex), size)
    try:
        with socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM) as sock:
            sock.connect("\0" + name)
            for seq, sent in paced(data, total, hz):
                sock.send(ATTACH.pack(seq, sent) + ring.write(data))
    finally:
        ring.close()
    print("[]", flush=True)
    return 0


def run_shm(size: int, total: int, hz: float, warmup: int, mode: str) -> dict:
    """One run of the side ``raw-zenoh-shm-<mode>`` (or, ``mode`` unix, raw-unix-shm-copy): a
    subscriber and a publisher process."""
    from latency import free_port

    key = f"bench/latency-shm/{os.getpid()}/{size}"
    listen = f"tcp/127.0.0.1:{free_port()}" if mode != "unix" else f"retriever-bench-{uuid.uuid4().hex}"
    timeout = total / hz + 30
    ring_id = uuid.uuid4().bytes
    me = [sys.executable, str(Path(__file__).resolve())]
    sub = subprocess.Popen(me + (["--sub", key, listen, str(total), str(timeout), mode] if mode != "unix" else
                                 ["--unix-sub", listen, str(total), str(timeout)]), stdout=subprocess.PIPE, text=True)
    pub = None
    try:
        if sub.stdout.readline().strip() != "READY":
            raise SystemExit("shm subscriber did not start")
        pub = subprocess.Popen(me + (["--pub", key] if mode != "unix" else ["--unix-pub"])
                               + [listen, str(size), str(total), str(hz), ring_id.hex()],
                               stdout=subprocess.PIPE, text=True)
        out = json.loads(sub.communicate(timeout=timeout + 30)[0].strip().splitlines()[-1])
        pub.communicate(timeout=30)
        if pub.returncode or sub.returncode:
            raise SystemExit(f"shm {mode}: publisher exited {pub.returncode}, subscriber {sub.returncode}")
    finally:
        for p in (pub, sub):
            if p is not None and p.poll() is None:
                p.kill()
                p.wait()
        ring_path(ring_id).unlink(missing_ok=True)  # the publisher's, if it died before its own unlink
    if out["errors"]:
        raise SystemExit(f"shm {mode}: {len(out['errors'])} handle(s) refused: {out['errors'][:3]}")
    got = sorted(out["got"])
    if any(n != size for _, _, _, n, _ in got):
        raise SystemExit(f"shm {mode}: a payload of the wrong size")
    return {"lat": [r - s for seq, s, r, _, _ in got if seq >= warmup], "received": len(got)}


def selftest() -> int:
    """Hostile handles are refused with a RingError, a lapped or torn slot detected, nothing left."""
    rid = uuid.uuid4().bytes
    w = Writer(rid, 1000, slots=2)
    try:
        r = Reader()
        h = w.write(np.arange(1000, dtype=np.uint8) % 251)
        assert bytes(r.copy(h)) == bytes(np.arange(1000, dtype=np.uint8) % 251)
        assert not r.view(h).flags.writeable
        ring_id, slot, _, gen, n = HANDLE.unpack(h)
        bad = {
            "slot out of range": HANDLE.pack(ring_id, 2, 0, gen, n),
            "length out of range": HANDLE.pack(ring_id, slot, 0, gen, 1001),
            "huge length": HANDLE.pack(ring_id, slot, 0, gen, 2**63),
            "odd generation": HANDLE.pack(ring_id, slot, 0, gen + 1, n),
            "short handle": h[:-1],
            "another ring": HANDLE.pack(uuid.uuid4().bytes, slot, 0, gen, n),
        }
        for name, handle in bad.items():
            try:
                r.copy(handle)
            except RingError as e:
                print(f"refused, {name}: {e}")
            else:
                raise AssertionError(f"accepted: {name}")
        try:
            Reader(expected_ids={uuid.uuid4().bytes}).copy(h)
        except RingError as e:
            print(f"refused, a ring of another run: {e}")
        w.write(np.zeros(10, dtype=np.uint8))
        w.write(np.zeros(10, dtype=np.uint8))  # slot 0 again: the first handle lapped
        try:
            r.copy(h)
        except RingError as e:
            print(f"refused, lapped: {e}")
        else:
            raise AssertionError("a lapped slot read")
        r.close()
    finally:
        w.close()
    assert not ring_path(rid).exists()
    print("selftest ok")
    return 0


def main(argv: list[str]) -> int:
    sys.path.insert(0, str(HERE))
    if argv[:1] == ["--sub"]:
        return shm_sub(argv[1], argv[2], int(argv[3]), float(argv[4]), argv[5])
    if argv[:1] == ["--pub"]:
        return shm_pub(argv[1], argv[2], int(argv[3]), int(argv[4]), float(argv[5]), argv[6])
    if argv[:1] == ["--unix-sub"]:
        return unix_sub(argv[1], int(argv[2]), float(argv[3]))
    if argv[:1] == ["--unix-pub"]:
        return unix_pub(argv[1], int(argv[2]), int(argv[3]), float(argv[4]), argv[5])
    if argv[:1] == ["--selftest"]:
        return selftest()
    raise SystemExit(__doc__)


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
