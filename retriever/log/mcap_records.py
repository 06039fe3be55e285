"""The bytes of the MCAP records the writer builds by hand instead of with ``mcap``'s record
classes: Message records (the hot path: one ``struct.pack`` each), the head of a Chunk record, and
the MessageIndex records that follow each chunk. Every other record is written with ``mcap``'s own
classes (:func:`record_bytes`).
"""

from __future__ import annotations

import struct

import numpy as np
from mcap.data_stream import RecordBuilder
from mcap.opcode import Opcode
from mcap.records import McapRecord

MAGIC = b"\x89MCAP0\r\n"
#: The head of a Message record: ``MESSAGE_HEAD.pack(Opcode.MESSAGE, MESSAGE_FIELDS + len(data),
#: channel_id, sequence & 0xFFFFFFFF, log_time, publish_time) + data`` is the whole record.
MESSAGE_HEAD = struct.Struct("<BQHIQQ")
MESSAGE_FIELDS = 2 + 4 + 8 + 8
_CHANNEL_AT, _LOG_TIME_AT = 9, 15  # where a Message record's channel id and log time begin
_LOG_TIME_BYTES = np.arange(_LOG_TIME_AT, _LOG_TIME_AT + 8)
#: The head of a Chunk record, up to its compression's name: opcode, record length, message start
#: and end time, uncompressed size and CRC, the name's length; then the name, and the records'
#: length (8 bytes) before them; CHUNK_FIELDS counts the fields' bytes but the name and records
CHUNK_HEAD = struct.Struct("<BQQQQII")
CHUNK_FIELDS = 8 + 8 + 8 + 4 + 4 + 8
#: the one compression the writer's chunks use, as a Chunk record names it
ZSTD = "zstd"
MESSAGE_INDEX_HEAD = struct.Struct("<BQHI")  # opcode, record length, channel id, entries' length
_U32 = 0xFFFFFFFF


def record_bytes(record: McapRecord) -> bytes:
    """One record, as ``mcap``'s own classes write it."""
    builder = RecordBuilder()
    record.write(builder)
    return builder.end()


def message_records(messages: list[tuple[int, int, int, int, bytes]]) -> list[bytes]:
    """The Message records of ``(channel_id, log_time, publish_time, sequence, data)`` messages."""
    pack = MESSAGE_HEAD.pack
    return [pack(Opcode.MESSAGE, MESSAGE_FIELDS + len(data), channel_id, sequence & _U32, log_time, publish_time)
            + data for channel_id, log_time, publish_time, sequence, data in messages]


def chunk_head(log_time: int, uncompressed_size: int, uncompressed_crc: int, compressed_size: int) -> bytes:
    """The bytes of a zstd Chunk record before its compressed records, for one message's chunk
    (its start and end time are the message's log time)."""
    name = ZSTD.encode()
    return (CHUNK_HEAD.pack(Opcode.CHUNK, chunk_fields(compressed_size), log_time, log_time, uncompressed_size,
                            uncompressed_crc, len(name)) + name + compressed_size.to_bytes(8, "little"))


def chunk_fields(compressed_size: int) -> int:
    """The record length of a zstd Chunk record whose compressed records take ``compressed_size``."""
    return CHUNK_FIELDS + len(ZSTD) + compressed_size


class ChunkIndexes:
    """What the summary and the indexes say of a chunk of Message records, read from its bytes
    (on the I/O thread, so that the run's thread adds a batch of records with one ``join``):
    its MessageIndex records, how many messages each channel has in it, its earliest and latest
    log time, and each channel's latest."""

    def __init__(self, chunk: bytes | bytearray, lengths: list[int]):
        sizes = np.array(lengths, dtype=np.int64)
        offsets = np.cumsum(sizes) - sizes
        raw = np.frombuffer(chunk, dtype=np.uint8)
        channels = (raw[offsets + _CHANNEL_AT].astype(np.uint16)
                    | (raw[offsets + _CHANNEL_AT + 1].astype(np.uint16) << 8))
        times = np.ascontiguousarray(raw[offsets[:, None] + _LOG_TIME_BYTES]).view("<u8").ravel()
        self.start_time, self.end_time = int(times.min()), int(times.max())
        order = np.lexsort((times, channels))  # by channel, then log time; stable
        channels, entries = channels[order], np.empty((len(order), 2), dtype="<u8")
        entries[:, 0], entries[:, 1] = times[order], offsets[order]
        firsts = np.flatnonzero(np.r_[True, channels[1:] != channels[:-1]])
        #: ``(channel_id, MessageIndex record)`` by channel id, each listing ``(log_time, offset in
        #: the chunk)`` in log-time order (ties in file order)
        self.records: list[tuple[int, bytes]] = []
        self.counts: dict[int, int] = {}
        self.channel_end_times: dict[int, int] = {}
        for first, last in zip(firsts.tolist(), [*firsts[1:].tolist(), len(order)]):
            body = entries[first:last].tobytes()
            channel_id = int(channels[first])
            self.records.append((channel_id, MESSAGE_INDEX_HEAD.pack(Opcode.MESSAGE_INDEX, 2 + 4 + len(body),
                                                                      channel_id, len(body)) + body))
            self.counts[channel_id] = last - first
            self.channel_end_times[channel_id] = int(entries[last - 1, 0])
