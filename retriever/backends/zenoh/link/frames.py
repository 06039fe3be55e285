"""The link's messages on its socket, each with an exact decoder that refuses anything else.

A connection starts with a handshake in msgpack: the consumer's hello ``["retriever-link",
version, run, producer, consumer]``, the producer's welcome ``["retriever-link", version, run,
producer, slots, capacity, stride, inline_below]`` with the ring's memfd (SCM_RIGHTS), or its
refusal ``["retriever-link", version, reason]``. Then fixed binary frames, one per
SOCK_SEQPACKET record (the socket keeps their bounds and order):

    producer -> consumer   INLINE  type u8, kind u8, the message's bytes
                           HANDLE  type u8, kind u8, slot u32, generation u64, length u64 (22 bytes)
                           RING    type u8, slots u32, capacity u64, stride u64 (21 bytes), with the
                                   memfd of a new ring that replaces the old (no slot of which is held)
    consumer -> producer   ACK     type u8, slot u32, generation u64 (13 bytes)

``kind`` is the caller's: one ordered stream carries whatever kinds of message it sends (data,
progress), each handed to the consumer with its kind. Nothing decoded here is imported or
called; msgpack only, its values type-checked before use.
"""

from __future__ import annotations

import struct

import msgpack

from ....errors import LinkError

LINK_VERSION = 1
MAGIC = "retriever-link"
INLINE, HANDLE, ACK, RING = 1, 2, 3, 4
HANDLE_FRAME = struct.Struct("<BBIQQ")
RING_FRAME = struct.Struct("<BIQQ")
ACK_FRAME = struct.Struct("<BIQ")
#: a handshake message's bound, and a name's (a run, a producer, a consumer)
MAX_HANDSHAKE = 4096
MAX_NAME = 256
#: INLINE's head for each kind, made once
INLINE_HEADS = tuple(bytes((INLINE, kind)) for kind in range(256))


def hello(run: str, producer: str, consumer: str) -> bytes:
    return msgpack.packb([MAGIC, LINK_VERSION, run, producer, consumer])


def welcome(run: str, producer: str, slots: int, capacity: int, stride: int, inline_below: int) -> bytes:
    return msgpack.packb([MAGIC, LINK_VERSION, run, producer, slots, capacity, stride, inline_below])


def refusal(reason: str) -> bytes:
    return msgpack.packb([MAGIC, LINK_VERSION, reason[:MAX_HANDSHAKE // 2]])


def read_hello(data: bytes, peer: str) -> tuple[str, str, str]:
    """``(run, producer, consumer)`` of a consumer's hello."""
    fields = _handshake(data, "hello", peer)
    if len(fields) != 5 or not all(_is_name(f) for f in fields[2:]):
        raise LinkError(f"{peer}: its hello is not [magic, version, run, producer, consumer] of names")
    return fields[2], fields[3], fields[4]


def read_welcome(data: bytes, peer: str) -> tuple[str, str, int, int, int, int]:
    """``(run, producer, slots, capacity, stride, inline_below)`` of a producer's welcome (the
    geometry's values are checked against the memfd by ring.RingReader); its refusal raised."""
    fields = _handshake(data, "welcome", peer)
    if len(fields) == 3 and isinstance(fields[2], str):
        raise LinkError(f"{peer}: refused this consumer: {fields[2][:MAX_HANDSHAKE]}")
    if len(fields) != 8 or not _is_name(fields[2]) or not _is_name(fields[3]) \
            or not all(type(f) is int for f in fields[4:]):
        raise LinkError(f"{peer}: its welcome is not [magic, version, run, producer, slots, capacity, stride, "
                        "inline_below]")
    return tuple(fields[2:])


def _handshake(data: bytes, what: str, peer: str) -> list:
    if not data:
        raise LinkError(f"{peer}: closed the connection before its {what}")
    if len(data) > MAX_HANDSHAKE:
        raise LinkError(f"{peer}: its {what} is longer than {MAX_HANDSHAKE} bytes")
    try:
        fields = msgpack.unpackb(data, raw=False)
    except Exception as e:  # msgpack's own errors on garbage: ExtraData, ValueError, ...
        raise LinkError(f"{peer}: its {what} is not valid msgpack ({type(e).__name__})") from None
    if type(fields) is not list or len(fields) < 2 or fields[0] != MAGIC:
        raise LinkError(f"{peer}: its {what} is no retriever link handshake")
    if fields[1] != LINK_VERSION:
        raise LinkError(f"{peer}: its {what} is of link version {fields[1]!r}, this process's is {LINK_VERSION}")
    return fields


def _is_name(value: object) -> bool:
    return type(value) is str and 0 < len(value) <= MAX_NAME


def handle(kind: int, slot: int, generation: int, length: int) -> bytes:
    return HANDLE_FRAME.pack(HANDLE, kind, slot, generation, length)


def ring(slots: int, capacity: int, stride: int) -> bytes:
    return RING_FRAME.pack(RING, slots, capacity, stride)


def ack(slot: int, generation: int) -> bytes:
    return ACK_FRAME.pack(ACK, slot, generation)


def read_ack(data: bytes, peer: str) -> tuple[int, int]:
    """``(slot, generation)`` of a consumer's ack (checked against what it holds by the caller)."""
    if len(data) != ACK_FRAME.size or data[0] != ACK:
        raise LinkError(f"{peer}: sent a frame of {len(data)} bytes of type {data[0] if data else None}, "
                        f"not an ack ({ACK_FRAME.size} bytes of type {ACK})")
    _, slot, generation = ACK_FRAME.unpack(data)
    return slot, generation


#: the name of each frame a producer sends, and the bytes it must have (None: at least 2)
_SIZES = {INLINE: ("message", None), HANDLE: ("handle", HANDLE_FRAME.size), RING: ("ring", RING_FRAME.size)}


def frame_type(data: bytes, peer: str) -> int:
    """INLINE, HANDLE or RING, with the frame's length checked for it."""
    kind = data[0] if data else None
    if kind == INLINE and len(data) >= 2 or kind == HANDLE and len(data) == HANDLE_FRAME.size \
            or kind == RING and len(data) == RING_FRAME.size:
        return kind
    if kind in _SIZES:
        name, size = _SIZES[kind]
        raise LinkError(f"{peer}: sent a {name} frame of {len(data)} bytes "
                        f"({'exactly ' + str(size) if size else 'at least 2'} expected)")
    raise LinkError(f"{peer}: sent a frame of unknown type {kind} ({len(data)} bytes)")
