"""The attachment rmw_zenoh puts on every sample of a topic: who published it, which one it is,
and when.

rmw_zenoh's subscriptions refuse a sample without it ("Unable to obtain attachment"), and hand
its fields to the application as the message info (``publication_sequence_number``,
``source_timestamp``, ``publisher_gid``). Its layout is Zenoh's own serialization format
(zenoh-ext), positional since rmw_zenoh PR #601 (ros2/rmw_zenoh issue #600):

    int64 sequence_number    little endian; a publisher's first sample is 1
    int64 source_timestamp   little endian; the publisher's system time, ns since the Unix epoch
    16 x uint8 source_gid    a sequence: its LEB128 length (0x10), then the 16 bytes

33 bytes in all. Releases before that wrote each field after its name as a string
(``"sequence_number"``, …); :func:`decode` reads both, :func:`encode` writes the current one.
"""

from __future__ import annotations

import dataclasses
import struct

GID_SIZE = 16
_NUMBERS = struct.Struct("<qq")
_KEYED_NAMES = (b"sequence_number", b"source_timestamp", b"source_gid")


@dataclasses.dataclass(frozen=True)
class Attachment:
    sequence_number: int
    source_timestamp: int
    source_gid: bytes

    def __post_init__(self):
        if len(self.source_gid) != GID_SIZE:
            raise ValueError(f"a GID is {GID_SIZE} bytes, got {len(self.source_gid)}")


def encode(attachment: Attachment) -> bytes:
    """The attachment's bytes, as rmw_zenoh writes them."""
    return (_NUMBERS.pack(attachment.sequence_number, attachment.source_timestamp)
            + bytes([GID_SIZE]) + bytes(attachment.source_gid))


def decode(data: bytes) -> Attachment:
    """An attachment read back, in the current layout or the earlier keyed one; ValueError if
    ``data`` is neither."""
    data = bytes(data)
    if len(data) == _NUMBERS.size + 1 + GID_SIZE and data[_NUMBERS.size] == GID_SIZE:
        sequence_number, source_timestamp = _NUMBERS.unpack_from(data)
        return Attachment(sequence_number, source_timestamp, data[_NUMBERS.size + 1:])
    return _decode_keyed(data)


def _decode_keyed(data: bytes) -> Attachment:
    """The layout before PR #601: each field after its name, names and the GID as sequences."""
    at, fields = 0, []
    for name in _KEYED_NAMES:
        if data[at:at + 1] != bytes([len(name)]) or data[at + 1:at + 1 + len(name)] != name:
            raise ValueError(f"not an rmw_zenoh attachment: no {name.decode()} at byte {at} of {len(data)}")
        at += 1 + len(name)
        if name == b"source_gid":
            if data[at:at + 1] != bytes([GID_SIZE]) or len(data) != at + 1 + GID_SIZE:
                raise ValueError(f"not an rmw_zenoh attachment: its source_gid is not {GID_SIZE} bytes")
            fields.append(data[at + 1:])
        else:
            if len(data) < at + 8:
                raise ValueError(f"not an rmw_zenoh attachment: {name.decode()} is cut off")
            fields.append(struct.unpack_from("<q", data, at)[0])
            at += 8
    return Attachment(*fields)
