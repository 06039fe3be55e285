"""A link's ring (retriever/backends/zenoh/link/ring.py): a sealed, nameless memfd that a message's
parts are written into whole and copied out of, read only, by a reader that checked it."""

from __future__ import annotations

import fcntl
import hashlib
import mmap
import os

import numpy as np
import pytest

from retriever.backends.zenoh.link.ring import MAX_SLOTS, Ring, RingReader
from retriever.errors import LinkError


def test_a_ring_has_no_name_and_cannot_be_shrunk_grown_or_unsealed():
    ring = Ring(2, 10_000)
    try:
        assert os.readlink(f"/proc/self/fd/{ring.fd}").startswith("/memfd:retriever-link")
        assert os.fstat(ring.fd).st_size == 2 * ring.stride and ring.stride % mmap.PAGESIZE == 0
        for size in (ring.size - 4096, ring.size + 4096):
            with pytest.raises(PermissionError):
                os.ftruncate(ring.fd, size)
        with pytest.raises(PermissionError):
            fcntl.fcntl(ring.fd, fcntl.F_ADD_SEALS, fcntl.F_SEAL_WRITE)
    finally:
        ring.close()


def test_parts_of_any_buffer_form_are_written_whole_and_copied_out_read_only():
    floats = np.linspace(0, 1, 1000, dtype=np.float32)
    parts = [b"head", memoryview(b"\x00middle")[1:], np.arange(256, dtype=np.uint8), floats]
    whole = b"".join(bytes(memoryview(part).cast("B")) for part in parts)
    ring = Ring(2, 10_000)
    reader = RingReader(os.dup(ring.fd), 2, 10_000, ring.stride, "test")
    try:
        ring.write(1, parts, len(whole), 9)
        copied = reader.copy(1, 9, len(whole))
        assert type(copied) is bytes and hashlib.sha256(copied).digest() == hashlib.sha256(whole).digest()
        ring.write(1, [b"next"], 4, 10)  # the copy is the reader's own: the slot's next message leaves it be
        assert copied == whole and reader.copy(1, 10, 4) == b"next"
        with pytest.raises(LinkError, match="test: a handle of slot 1 says generation 9, the slot holds 10"):
            reader.copy(1, 9, 4)
    finally:
        reader.close()
        ring.close()


def test_parts_that_do_not_add_up_and_geometries_out_of_bounds_are_refused():
    ring = Ring(1, 100)
    try:
        with pytest.raises(LinkError, match="a message's parts hold 3 bytes, not the 4 said"):
            ring.write(0, [b"abc"], 4, 1)
    finally:
        ring.close()
    for slots, capacity in ((0, 100), (MAX_SLOTS + 1, 100), (2, 0), (MAX_SLOTS, 1 << 30)):
        with pytest.raises(LinkError, match=rf"a link ring of {slots} slots of {capacity} bytes is out of bounds"):
            Ring(slots, capacity)
