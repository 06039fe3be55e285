"""A ring of slots in a sealed memfd: the producer writes a message's parts into a slot, a
consumer that was handed the fd maps it read-only and copies a slot out.

Nothing has a name in /dev/shm: the memory goes when the last process holding the fd or a
mapping of it exits, so a SIGKILLed producer or consumer leaves no ring behind. The memfd is
sealed against shrinking and growing (and against new seals) before its fd leaves the producer:
no one can truncate it under a reader's mapping, so a read can never fault (SIGBUS).

A slot is ``stride`` bytes: a header (the generation of the message in it, u64 little-endian;
0 while being written) then the message. The producer writes a slot only when no consumer holds
it (its acks, channel.py): the header is a second line, read by the consumer before and after
its copy, that refuses a slot rewritten by something that broke that rule.
"""

from __future__ import annotations

import errno
import fcntl
import mmap
import os
import stat
import struct

from ....errors import LinkError

#: the slot's header: the generation of the message it holds (0: being written, or never)
_HEADER = struct.Struct("<Q")
#: where a slot's message starts: the header, padded to a cache line
HEADER_BYTES = 64
#: the seals every ring has, checked by its readers: no shrink, no grow, no seal changed
SEALS = fcntl.F_SEAL_SHRINK | fcntl.F_SEAL_GROW | fcntl.F_SEAL_SEAL
#: at most this many slots, and this many bytes in all: a geometry announced past them is refused.
#: A consumer acks each slot at once and the producer reads acks only when it needs a slot
#: (server.py): up to ``slots`` acks wait unread in the consumer's socket, and one more would block
#: the consumer in its ack, so it would read no more handles (a healthy link stalled: review14, at
#: ~270 acks, what Linux's default socket buffer holds of them). 64 stays well below that.
MAX_SLOTS = 64
MAX_RING_BYTES = 1 << 36


def stride_for(capacity: int) -> int:
    """A slot's size for messages of up to ``capacity`` bytes: header and message, in whole pages."""
    return -(-(HEADER_BYTES + capacity) // mmap.PAGESIZE) * mmap.PAGESIZE


def check_geometry(slots: int, capacity: int) -> None:
    """LinkError unless a ring of ``slots`` slots of ``capacity`` bytes is within the bounds."""
    if not 1 <= slots <= MAX_SLOTS or capacity < 1 or slots * stride_for(capacity) > MAX_RING_BYTES:
        raise LinkError(f"a link ring of {slots} slots of {capacity} bytes is out of bounds "
                        f"(1..{MAX_SLOTS} slots, {MAX_RING_BYTES} bytes in all)")


def _cannot_make(size: int, e: OSError) -> LinkError:
    why = (" (the process's file size limit, ulimit -f, is below it: a memfd counts as a file)"
           if e.errno == errno.EFBIG else "")
    return LinkError(f"cannot make a link ring of {size} bytes: {e.strerror or e}{why}")


class Ring:
    """The producer's ring: ``slots`` slots of messages up to ``capacity`` bytes, every page
    written once here (so the first messages do not pay the page faults). ``fd`` is what a
    consumer is handed; :meth:`close` closes this process's fd and mapping."""

    def __init__(self, slots: int, capacity: int, name: str = "retriever-link"):
        check_geometry(slots, capacity)
        self.slots, self.capacity, self.stride = slots, capacity, stride_for(capacity)
        self.size = slots * self.stride
        try:
            self.fd = os.memfd_create(name, os.MFD_CLOEXEC | os.MFD_ALLOW_SEALING)
        except OSError as e:
            raise _cannot_make(self.size, e) from None
        try:
            os.ftruncate(self.fd, self.size)
            fcntl.fcntl(self.fd, fcntl.F_ADD_SEALS, SEALS)
            self._map = mmap.mmap(self.fd, self.size)  # shared, read and write
        except BaseException as e:
            os.close(self.fd)
            if isinstance(e, OSError):
                raise _cannot_make(self.size, e) from None
            raise
        self._view = memoryview(self._map)
        self._view[:] = bytes(self.size)  # fault every page in now, not in the first messages

    def write(self, slot: int, parts: list, length: int, generation: int) -> None:
        """Write the message made of ``parts`` (bytes-like: bytes, memoryviews, flat uint8
        arrays; ``length`` bytes in all) into ``slot`` under ``generation`` (> 0), each part
        copied straight into the slot (no join). The caller owns the slot: no consumer holds it."""
        start = slot * self.stride
        view = self._view
        view[start:start + 8] = _HEADER.pack(0)
        at = start + HEADER_BYTES
        for part in parts:
            part = memoryview(part)
            if part.format != "B" or part.ndim != 1:
                part = part.cast("B")
            end = at + part.nbytes
            view[at:end] = part
            at = end
        if at - start - HEADER_BYTES != length:
            raise LinkError(f"a message's parts hold {at - start - HEADER_BYTES} bytes, not the {length} said")
        view[start:start + 8] = _HEADER.pack(generation)

    def close(self) -> None:
        if self.fd < 0:
            return
        self._view.release()
        self._map.close()
        os.close(self.fd)
        self.fd = -1


class RingReader:
    """A consumer's read-only mapping of a producer's ring, from the fd it was handed and the
    geometry announced with it, each checked against the fd before anything is mapped: a memfd
    (not a file, a pipe, a device), of exactly ``slots * stride`` bytes, sealed (``SEALS``).
    Takes ownership of ``fd`` (closed once mapped, or on refusal)."""

    def __init__(self, fd: int, slots: int, capacity: int, stride: int, peer: str):
        try:
            problem = _refusal(fd, slots, capacity, stride)
            if problem:
                raise LinkError(f"{peer}: refused its ring: {problem}")
            self.slots, self.capacity, self.stride = slots, capacity, stride
            self._map = mmap.mmap(fd, slots * stride, prot=mmap.PROT_READ)
        finally:
            os.close(fd)
        self.peer = peer

    def copy(self, slot: int, generation: int, length: int) -> bytes:
        """The message in ``slot`` (``length`` bytes), copied out, after checking the handle
        against the ring: the slot in it, the length within a slot, the slot's generation the
        handle's before and after the copy."""
        if not 0 <= slot < self.slots:
            raise LinkError(f"{self.peer}: a handle names slot {slot}, out of its ring's {self.slots}")
        if not 0 <= length <= self.capacity:
            raise LinkError(f"{self.peer}: a handle says {length} bytes, past its ring's slots of {self.capacity}")
        start = slot * self.stride
        held = _HEADER.unpack_from(self._map, start)[0]
        if held != generation or generation == 0:
            raise LinkError(f"{self.peer}: a handle of slot {slot} says generation {generation}, the slot holds "
                            f"{held}: a stale handle, or a slot rewritten before it was read")
        data = self._map[start + HEADER_BYTES:start + HEADER_BYTES + length]  # bytes: the one copy
        if _HEADER.unpack_from(self._map, start)[0] != generation:
            raise LinkError(f"{self.peer}: slot {slot} was rewritten while it was read (generation {generation})")
        return data

    def close(self) -> None:
        self._map.close()


def _refusal(fd: int, slots: object, capacity: object, stride: object) -> str | None:
    """Why the fd and geometry a producer announced are no ring of this module's, or None."""
    if type(slots) is not int or type(capacity) is not int or type(stride) is not int:
        return "its geometry is not three integers"
    if not 1 <= slots <= MAX_SLOTS or capacity < 1 or stride != stride_for(capacity) \
            or slots * stride > MAX_RING_BYTES:
        return f"its geometry ({slots} slots of {capacity} bytes, stride {stride}) is out of bounds"
    try:
        info = os.fstat(fd)
        target = os.readlink(f"/proc/self/fd/{fd}")
        seals = fcntl.fcntl(fd, fcntl.F_GET_SEALS)
    except OSError as e:  # F_GET_SEALS: EINVAL on anything but a memfd
        return f"its fd is no sealed memfd ({e.strerror})"
    if not stat.S_ISREG(info.st_mode) or not target.startswith("/memfd:"):
        return f"its fd is no memfd ({target})"
    if seals & SEALS != SEALS:
        return f"its memfd is not sealed against shrinking and growing (seals {seals:#x})"
    if info.st_size != slots * stride:
        return f"its memfd holds {info.st_size} bytes, not the {slots * stride} of {slots} slots of {stride}"
    return None
